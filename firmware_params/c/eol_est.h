/* eol_est.h: rotor angle/speed estimator (seed paper eqs. 13-16 plus switchable improvements),
 * C99, float only, no heap. The algorithm is specified in ../ESTIMATOR.md; the Python reference
 * is eol_cal/firmware/estimator.py. The sources' floating-point contract (eol_fp.h, no fused
 * multiply-add) makes any build match the golden vectors bit for bit. All integer state is int32_t (int is 16 bits on C28x). */
#ifndef EOL_EST_H
#define EOL_EST_H

#include <stdint.h>

#include "eol_param_block.h"

#ifdef __cplusplus
extern "C" {
#endif

/* Largest encoder_ppr the static tables of improvement 4 hold (2 floats + 2 int32 per pulse). */
#ifndef EOL_EST_MAX_PPR
#define EOL_EST_MAX_PPR 256
#endif

/* Improvement switches: the parameter block's estimator option bits, EOL_PB_FLAG_EST_* of
 * eol_param_block.h (flags bits 2-5, contract revision 1.1), honoured only together with
 * EOL_PB_FLAG_INTERP_ENABLE; eol_est_options() is the one place that says which count. */

/* Status bits (eol_est_out_t.status), see ESTIMATOR.md */
#define EOL_EST_ST_STANDSTILL 0x001u
#define EOL_EST_ST_REVERSE 0x002u
#define EOL_EST_ST_HALL_FAULT 0x004u
#define EOL_EST_ST_HALL_SEQ 0x008u
#define EOL_EST_ST_NO_ANCHOR 0x010u
#define EOL_EST_ST_QEP_ERROR 0x020u
#define EOL_EST_ST_EDGE_REJECT 0x040u
#define EOL_EST_ST_MISSING_EDGE 0x080u
#define EOL_EST_ST_DIR_MISMATCH 0x100u
#define EOL_EST_ST_NO_SPEED 0x200u

typedef struct {
    int32_t poles;            /* P, even, >= 2 */
    int32_t n_enc;            /* A pulses per mechanical revolution, 1..EOL_EST_MAX_PPR */
    float tick_hz;            /* estimator tick = PWM frequency, Hz */
    float hall_angle[6];      /* rad electrical; [s-1] = where hall state s begins forward */
    int32_t standstill_ticks; /* 1 .. 2^29-1 */
    uint32_t flags;           /* the block's flags word; the options it selects: eol_est_options() */
} eol_est_config_t;

typedef struct {
    /* configuration and constants derived at init (ESTIMATOR.md, "Constants") */
    eol_est_config_t cfg;
    uint32_t opts;            /* eol_est_options(cfg.flags) */
    float T, DELTA, QUARTER, HALF_QUARTER, HALF_DELTA, K_OMEGA, TWO_TICK_HZ, TICK_HZ, K_NDELTA;
    int32_t M;
    float h_start[8], h_width[8], h_mid[8];
    /* state (ESTIMATOR.md, "State") */
    int32_t phase, q, n, k_last, dir_last, nc_prev, against;
    float omega, alpha, adv, G;
    int32_t hall_last, sector, anchored, n_anchor;
    int32_t tick, run, R_prev;
    float c_tab[2 * EOL_EST_MAX_PPR];
    int32_t ts[2 * EOL_EST_MAX_PPR];
} eol_est_t;

typedef struct {
    float theta_hat; /* rad electrical, [0, 2*pi) */
    float omega_hat; /* rad/s electrical, signed (+ forward) */
    float theta_enc; /* rad electrical, [0, 2*pi): raw angle of the last A edge */
    int32_t status;  /* EOL_EST_ST_* bits */
    /* improvement 4's pitch sample (the mechanical identifier's input, ../MECH.md); 0 without it */
    int32_t learn;     /* 1: this tick's A edge closed a pitch at steady speed */
    int32_t learn_idx; /* c_tab index of the edge ending the pitch in forward rotation */
    float pitch_err;   /* rad electrical: the pitch's size minus DELTA */
} eol_est_out_t;

/* The estimator options a block's flags word selects: its EOL_PB_FLAGS_ESTIMATOR bits when
 * EOL_PB_FLAG_INTERP_ENABLE is set, none without it. */
uint32_t eol_est_options(uint32_t block_flags);

/* The configuration a valid parameter block (word image w, see eol_param_block.h) gives:
 * poles, encoder_ppr, tick_hz, hall_angle and the flags word, with standstill_ticks from the
 * caller. Returns 0, or -1 when the block's values are outside what eol_est_init accepts. */
int eol_est_config_from_block(const uint16_t *w, int32_t standstill_ticks, eol_est_config_t *cfg);

/* Power-on: derive the constants from cfg and take the first sample (hall0 0..7, a0/b0 0/1).
 * Returns 0, or -1 when cfg is out of range (est is then unusable). */
int eol_est_init(eol_est_t *est, const eol_est_config_t *cfg, int32_t hall0, int32_t a0, int32_t b0);

/* One PWM tick with this tick's samples: a, b (0/1), hall (0..7). */
void eol_est_step(eol_est_t *est, int32_t a, int32_t b, int32_t hall, eol_est_out_t *out);

/* angle reductions used by the estimator: [0, 2*pi) and [-pi, pi), rad */
float eol_est_wrap(float x);
float eol_est_wrap_pm(float x);

#ifdef __cplusplus
}
#endif

#endif /* EOL_EST_H */
