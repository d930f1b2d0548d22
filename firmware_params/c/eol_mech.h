/* eol_mech.h: the rotor's mechanical angle without an index pulse and the mechanical-order
 * compensation of a layout-2 block (firmware contract revision 1.2), C99, float only, no heap.
 * The algorithm is specified in ../MECH.md; the Python reference is eol_cal/firmware/mech.py.
 * The evaluation's divisions and square root go through eol_div/eol_sqrt (eol_fp.h): the target's
 * own, within the scenario files' ulp classes. */
#ifndef EOL_MECH_H
#define EOL_MECH_H

#include <stdint.h>

#include "eol_est.h"
#include "eol_param_block.h"

#ifdef __cplusplus
extern "C" {
#endif

/* entries of the mechanical tables over one mechanical revolution (the block's mech_table_len) */
#define EOL_MECH_TABLE_LEN 128
/* most pole pairs (hypotheses) the identifier evaluates */
#define EOL_MECH_MAX_PP 64
/* edges whose mean pitch error one background slice computes */
#define EOL_MECH_SLICE_EDGES 16
/* a pitch sample is accumulated only while its edge has fewer */
#define EOL_MECH_CNT_MAX 1024
/* estimator status bits that reset the identification (count or halls not trusted) */
#define EOL_MECH_RESET_STATUS (EOL_EST_ST_QEP_ERROR | EOL_EST_ST_MISSING_EDGE | EOL_EST_ST_HALL_FAULT | EOL_EST_ST_HALL_SEQ)

/* eol_mech_out_t.events */
#define EOL_MECH_EV_EVAL 0x01u           /* an evaluation ran this tick */
#define EOL_MECH_EV_PASS 0x02u           /* its best hypothesis passed the three thresholds */
#define EOL_MECH_EV_IDENTIFIED 0x04u     /* confirmed: the mechanical compensation starts */
#define EOL_MECH_EV_RESET_FAULT 0x08u    /* a count or hall fault reset the identification */
#define EOL_MECH_EV_RESET_FRACTION 0x10u /* identified, the hall fraction disagreed at a revolution mark */
#define EOL_MECH_EV_RESET_EVAL 0x20u     /* identified, an evaluation failed or gave another offset */

typedef struct {
    /* from the block and the estimator, derived at init (MECH.md, "Init") */
    int32_t enabled, dirs, N, PP, M;
    float DELTA, QUARTER, INV_DELTA, KM;
    float dF[2 * EOL_EST_MAX_PPR];
    float EF[2];
    float grid_phase, id_min_score, id_margin, id_frac_tol, lead_s;
    float table_const[EOL_MECH_TABLE_LEN];
    float table_per_amp[EOL_MECH_TABLE_LEN];
    /* state (MECH.md, "State") */
    float acc[2 * EOL_EST_MAX_PPR];
    int32_t cnt[2 * EOL_EST_MAX_PPR];
    int32_t n_new, cand, active, r;
    float score, margin;
    int32_t miss[2]; /* edges of each direction without a sample yet */
    /* the background evaluation (MECH.md, "Background"): busy 0 none, k its k-th slice is next
     * (1..n_slices), n_slices + 1 finished; the tick froze the samples and G when it started */
    int32_t n_slices, busy, ev_d, ev_ok, ev_r;
    float ev_G, ev_score, ev_margin;
    /* the slices' partial results */
    float dg, Ea, den, best_rho, best_e;
    int32_t best_j;
    float rho_j[EOL_MECH_MAX_PP];
    float a[EOL_EST_MAX_PPR]; /* each edge's mean pitch error */
    /* the revolution mark's check: mk 0 none, 1 asked, 2 done (verdict mk_bad) */
    int32_t mk, mk_d, mk_bad;
    float mk_G;
    /* after a withdrawal the background clears the samples, 16 entries a slice: 0 done, k slice k next */
    int32_t clr, n_clear;
} eol_mech_t;

typedef struct {
    int32_t active; /* 1: identified, the mechanical compensation runs */
    int32_t r;      /* firmware pulse m is the block's pulse (m + r) mod N */
    int32_t events; /* EOL_MECH_EV_* */
    float score;    /* the last evaluation's best cosine */
    float margin;   /* and its margin over the next hypothesis */
} eol_mech_out_t;

/* Whether a block's mechanical compensation is honoured: layout 2, MECH_COMP_ENABLE with
 * COMP_ENABLE, INTERP_ENABLE and EST_LEARN_PITCH_ERRORS, fp_len == encoder_ppr, a fingerprint. */
int eol_mech_enabled(const uint16_t *w);

/* Power-on, after eol_est_init: constants from the initialised estimator, tables from the valid
 * block w (either layout; a layout-1 block or one without MECH_COMP_ENABLE leaves it disabled).
 * Returns 0, or -1 when the motor has more than EOL_MECH_MAX_PP pole pairs (then disabled). */
int eol_mech_init(eol_mech_t *m, const eol_est_t *est, const uint16_t *w);

/* One tick, in the interrupt after eol_est_step (est is the estimator after the step, eo its
 * outputs): constant work, no loop over the edges (MECH.md, "Per tick"). */
void eol_mech_step(eol_mech_t *m, const eol_est_t *est, const eol_est_out_t *eo, eol_mech_out_t *out);

/* One slice of the background work, in the background loop (MECH.md, "Background"): the running
 * evaluation's next slice (at most EOL_MECH_SLICE_EDGES edges, or one hypothesis), else the
 * revolution mark's check. The golden vectors call it once after every eol_mech_step. */
void eol_mech_background(eol_mech_t *m, const eol_est_t *est);

/* The mechanical-order current before the clamp (A) at count q with offset r (MECH.md, "Compensation"). */
float eol_mech_sum(const eol_mech_t *m, int32_t r, int32_t q, float theta_hat, float omega_hat, float i_qo);

#ifdef __cplusplus
}
#endif

#endif /* EOL_MECH_H */
