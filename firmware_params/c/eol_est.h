/* eol_est.h: rotor angle/speed estimator (seed paper eqs. 13-16 plus switchable improvements),
 * C99, float only, no heap. The algorithm is specified in ../ESTIMATOR.md; the Python reference
 * is eol_cal/firmware/estimator.py. Compile with -ffp-contract=off (no fused multiply-add) to
 * match the golden vectors bit for bit. All integer state is int32_t (int is 16 bits on C28x). */
#ifndef EOL_EST_H
#define EOL_EST_H

#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

/* Largest encoder_ppr the static tables of improvement 4 hold (2 floats + 2 int32 per pulse). */
#ifndef EOL_EST_MAX_PPR
#define EOL_EST_MAX_PPR 256
#endif

/* Improvement switches (eol_est_config_t.flags) */
#define EOL_EST_CLAMP_TO_NEXT_EDGE 0x1u
#define EOL_EST_LEARN_GRID_OFFSET 0x2u
#define EOL_EST_ACCEL_PREDICTION 0x4u
#define EOL_EST_LEARN_PITCH_ERRORS 0x8u

/* Status bits (eol_est_out_t.status), see ESTIMATOR.md */
#define EOL_EST_ST_STANDSTILL 0x001
#define EOL_EST_ST_REVERSE 0x002
#define EOL_EST_ST_HALL_FAULT 0x004
#define EOL_EST_ST_HALL_SEQ 0x008
#define EOL_EST_ST_NO_ANCHOR 0x010
#define EOL_EST_ST_QEP_ERROR 0x020
#define EOL_EST_ST_EDGE_REJECT 0x040
#define EOL_EST_ST_MISSING_EDGE 0x080
#define EOL_EST_ST_DIR_MISMATCH 0x100
#define EOL_EST_ST_NO_SPEED 0x200

typedef struct {
    int32_t poles;            /* P, even, >= 2 */
    int32_t n_enc;            /* A pulses per mechanical revolution, 1..EOL_EST_MAX_PPR */
    float tick_hz;            /* estimator tick = PWM frequency, Hz */
    float hall_angle[6];      /* rad electrical; [s-1] = where hall state s begins forward */
    int32_t standstill_ticks; /* 1 .. 2^29-1 */
    uint16_t flags;           /* EOL_EST_* improvement switches */
} eol_est_config_t;

typedef struct {
    /* configuration and constants derived at init (ESTIMATOR.md, "Constants") */
    eol_est_config_t cfg;
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
} eol_est_out_t;

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
