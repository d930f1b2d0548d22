/* eol_est.c: rotor angle/speed estimator, see eol_est.h and ../ESTIMATOR.md.
 * Every float expression keeps the order of the Python reference (eol_cal/firmware/estimator.py)
 * so that the host build matches the golden vectors bit for bit. */
#include "eol_fp.h" /* first: the floating-point contract */
#include <math.h>
#include <stdbool.h>

#include "eol_est.h"

/* binary32 constants; 9 significant digits round-trip exactly */
#define PI_F 3.14159274f          /* 0x40490fdb */
#define TWO_PI_F 6.28318548f      /* 0x40c90fdb */
#define INV_TWO_PI_F 0.159154937f /* 0x3e22f983 */
#define N_LEARN 16
#define K_ACC 0.125f
#define K_PITCH 0.5f
#define STEADY_TICKS 2
#define TICK_MASK 0x3FFFFFFFu

/* forward successor of hall state s (contract: 5 -> 1 -> 3 -> 2 -> 6 -> 4 -> 5) */
static const int32_t HALL_NEXT[8] = EOL_PB_HALL_NEXT;

float eol_est_wrap(float x)
{
    float r = x - (TWO_PI_F * floorf(x * INV_TWO_PI_F));
    if (r >= TWO_PI_F) {
        r = r - TWO_PI_F;
    }
    if (r < 0.0f) {
        r = r + TWO_PI_F;
    }
    return r;
}

float eol_est_wrap_pm(float x)
{
    return eol_est_wrap(x + PI_F) - PI_F;
}

static int32_t phase_of(int32_t a, int32_t b)
{
    const uint32_t x = (uint32_t)a ^ (uint32_t)b;
    return (2 * b) + (int32_t)x;
}

/* signed quadrature counts from boundary k_last to count q, in [-M/2, M/2) */
static int32_t dq_of(int32_t q, int32_t k_last, int32_t M)
{
    int32_t y = q - k_last; /* in (-M, M): no runtime modulo (the C28x has no divider) */
    if (y >= (M / 2)) {
        y -= M;
    } else if (y < -(M / 2)) {
        y += M;
    } else {
        /* already in [-M/2, M/2) */
    }
    return y;
}

/* x mod M for x in [-M, 2M): a count moved by less than a revolution (no runtime modulo) */
static int32_t wrap_count(int32_t x, int32_t M)
{
    int32_t y = x;
    if (y >= M) {
        y -= M;
    } else if (y < 0) {
        y += M;
    } else {
        /* already in [0, M) */
    }
    return y;
}

static float fminf_(float x, float y)
{
    return (x < y) ? x : y;
}

static float fmaxf_(float x, float y)
{
    return (x > y) ? x : y;
}

static int32_t imin(int32_t x, int32_t y)
{
    return (x < y) ? x : y;
}

/* 1/0 of a condition, for the int32_t fields the contract's structs carry */
static int32_t i32_of(bool x)
{
    return x ? 1 : 0;
}

/* the configuration refused by eol_est_init (ESTIMATOR.md, "Init") */
static bool config_bad(const eol_est_config_t *cfg)
{
    return (cfg->poles < 2) || ((cfg->poles % 2) != 0) || (cfg->n_enc < 1) || (cfg->n_enc > EOL_EST_MAX_PPR) ||
           !(cfg->tick_hz > 0.0f) || (cfg->standstill_ticks < 1) || (cfg->standstill_ticks >= 0x20000000L);
}

uint32_t eol_est_options(uint32_t block_flags)
{
    return ((block_flags & EOL_PB_FLAG_INTERP_ENABLE) != 0u) ? (block_flags & EOL_PB_FLAGS_ESTIMATOR) : 0u;
}

int eol_est_config_from_block(const uint16_t *w, int32_t standstill_ticks, eol_est_config_t *cfg)
{
    int32_t s;
    cfg->poles = (int32_t)EOL_PB_GET_POLES(w);
    cfg->n_enc = (int32_t)EOL_PB_GET_ENCODER_PPR(w);
    cfg->tick_hz = EOL_PB_GET_TICK_HZ(w);
    for (s = 0; s < 6; ++s) {
        cfg->hall_angle[s] = EOL_PB_GET_HALL_ANGLE(w, s);
    }
    cfg->standstill_ticks = standstill_ticks;
    cfg->flags = EOL_PB_GET_FLAGS(w);
    return config_bad(cfg) ? -1 : 0;
}

int eol_est_init(eol_est_t *est, const eol_est_config_t *cfg, int32_t hall0, int32_t a0, int32_t b0)
{
    int32_t s, i, h0 = hall0;
    if (config_bad(cfg)) {
        return -1;
    }
    est->cfg = *cfg;
    est->opts = eol_est_options(cfg->flags);
    est->T = 1.0f / cfg->tick_hz;
    est->DELTA = ((float)cfg->poles * PI_F) / (float)cfg->n_enc;
    est->QUARTER = est->DELTA * 0.25f;
    est->HALF_QUARTER = est->QUARTER * 0.5f;
    est->HALF_DELTA = est->DELTA * 0.5f;
    est->K_OMEGA = est->DELTA * cfg->tick_hz;
    est->TWO_TICK_HZ = cfg->tick_hz * 2.0f;
    est->TICK_HZ = cfg->tick_hz;
    est->K_NDELTA = (float)cfg->n_enc * est->DELTA;
    est->M = 4 * cfg->n_enc;
    est->h_start[0] = 0.0f;
    est->h_start[7] = 0.0f;
    for (s = 1; s <= 6; ++s) {
        est->h_start[s] = cfg->hall_angle[s - 1];
    }
    for (s = 0; s < 8; ++s) {
        est->h_width[s] = 0.0f;
        est->h_mid[s] = 0.0f;
    }
    for (s = 1; s <= 6; ++s) {
        est->h_width[s] = eol_est_wrap(est->h_start[HALL_NEXT[s]] - est->h_start[s]);
        est->h_mid[s] = eol_est_wrap(est->h_start[s] + (est->h_width[s] * 0.5f));
    }
    if ((h0 < 1) || (h0 > 6)) {
        h0 = 0;
    }
    est->phase = phase_of(a0, b0);
    est->q = est->phase;
    est->n = 0;
    est->k_last = 0;
    est->dir_last = 0;
    est->nc_prev = 0;
    est->against = 0;
    est->omega = 0.0f;
    est->alpha = 0.0f;
    est->adv = 0.0f;
    est->G = 0.0f;
    est->hall_last = h0;
    est->sector = h0;
    est->anchored = 0;
    est->n_anchor = 0;
    est->tick = 0;
    est->run = 0;
    est->R_prev = 0;
    for (i = 0; i < (2 * EOL_EST_MAX_PPR); ++i) {
        est->c_tab[i] = 0.0f;
        est->ts[i] = 0;
    }
    return 0;
}

void eol_est_step(eol_est_t *e, int32_t a, int32_t b, int32_t hall, eol_est_out_t *out)
{
    const uint32_t fl = e->opts;
    const bool learn_on = (fl & EOL_PB_FLAG_EST_LEARN_PITCH_ERRORS) != 0u;
    const bool accel_on = (fl & EOL_PB_FLAG_EST_ACCEL_PREDICTION) != 0u;
    const bool clamp_on = (fl & EOL_PB_FLAG_EST_CLAMP_TO_NEXT_EDGE) != 0u;
    const int32_t M = e->M;
    const int32_t S = e->cfg.standstill_ticks;
    int32_t ph, d, stp, q, edir, k, n1, nc_eff, fix, n, k_last, dir_last, nc_prev, run, hs, ha;
    bool qep_err, a_rise, against, bounce, ev, same_dir, pitch_ok, interval, long_iv, missing, reject, measured;
    bool speed_upd, still, speed_ok, hv, trans, fwd, rev, adj, jump, first, anchored_before, big, unanchored;
    uint32_t status;
    float omega_new, omega, alpha, omega_pred, adv, adv_eff, hb, c_last, rel, theta_pred, err, g, G;
    float theta_enc, theta, start, width, dd, end, omega_out;

    out->learn = 0;
    out->learn_idx = 0;
    out->pitch_err = 0.0f;

    /* 1. quadrature decoding (x4) */
    ph = phase_of(a, b);
    d = wrap_count(ph - e->phase, 4);
    if (d == 1) {
        stp = 1;
    } else if (d == 3) {
        stp = -1;
    } else {
        stp = 0;
    }
    qep_err = (d == 2);
    q = wrap_count(e->q + stp, M);
    a_rise = ((d == 1) && (ph == 1)) || ((d == 3) && (ph == 2));
    edir = -1;
    if (ph == 1) {
        edir = 1;
    }
    k = (edir > 0) ? q : wrap_count(q + 1, M);
    against = (e->against != 0) || ((stp != 0) && (stp == -e->dir_last));
    n1 = imin(e->n + 1, S + 1);

    /* 2. A edge event */
    bounce = a_rise && (k == e->k_last) && (edir == e->dir_last);
    ev = a_rise && !bounce;
    same_dir = (edir == e->dir_last);
    pitch_ok = (k == wrap_count(e->k_last + (4 * edir), M));
    interval = ev && same_dir && pitch_ok && (n1 <= S);
    long_iv = interval && (e->nc_prev > 0) && ((2 * n1) > (3 * e->nc_prev));
    missing = long_iv && against;
    reject = long_iv && !against;
    measured = interval && !long_iv;
    nc_eff = n1;
    if (missing) {
        nc_eff = n1 / 2;
    }
    omega_new = (float)edir * (e->K_OMEGA / (float)nc_eff);
    fix = 0;
    if (missing) {
        fix = 4 * edir;
    }
    q = wrap_count(q + fix, M);
    k = wrap_count(k + fix, M);
    speed_upd = measured || missing;
    run = e->run;
    if (learn_on) {
        const uint32_t tick_u = ((uint32_t)e->tick + 1u) & TICK_MASK;
        int32_t tick = (int32_t)tick_u;
        int32_t i_new = k / 2;
        float c_old = e->c_tab[e->k_last / 2];
        float c_new = e->c_tab[i_new];
        const uint32_t R_u = (tick_u - (uint32_t)e->ts[i_new]) & TICK_MASK;
        int32_t R = (int32_t)R_u;
        int32_t dR;
        bool learn;
        if (R < 1) {
            R = 1;
        }
        dR = R - e->R_prev;
        if (dR < 0) {
            dR = -dR;
        }
        learn = measured && (e->run >= e->cfg.n_enc) && (dR <= STEADY_TICKS);
        if (learn) {
            float pitch = (float)n1 * (e->K_NDELTA / (float)R);
            float pitch_err = pitch - e->DELTA;
            float target = c_old + ((float)edir * pitch_err);
            c_new = c_new + (K_PITCH * (target - c_new));
            out->pitch_err = pitch_err;
        }
        out->learn = i32_of(learn);
        out->learn_idx = (edir > 0) ? i_new : (e->k_last / 2);
        e->c_tab[i_new] = c_new;
        if (ev) {
            e->ts[i_new] = tick;
        }
        e->tick = tick;
        if (measured) {
            e->R_prev = R;
            run = imin(e->run + 1, e->cfg.n_enc);
            omega_new = (float)edir * (((e->DELTA + ((float)edir * (c_new - c_old))) * e->TICK_HZ) / (float)n1);
        } else if (ev) {
            run = 0;
        } else {
            /* no edge: the run goes on */
        }
    }
    if (speed_upd) {
        omega = omega_new;
    } else if (ev && !same_dir) {
        omega = 0.0f;
    } else {
        omega = e->omega;
    }
    if (speed_upd) {
        nc_prev = nc_eff;
    } else if (reject) {
        nc_prev = n1;
    } else if (ev) {
        nc_prev = 0;
    } else {
        nc_prev = e->nc_prev;
    }
    alpha = e->alpha;
    if (accel_on) {
        if (measured && (e->nc_prev > 0)) {
            const int32_t n_two = n1 + e->nc_prev;
            float alpha_raw = (omega_new - e->omega) * (e->TWO_TICK_HZ / (float)n_two);
            alpha = e->alpha + (K_ACC * (alpha_raw - e->alpha));
        } else if (ev && !(missing || reject)) {
            alpha = 0.0f;
        } else {
            /* kept */
        }
    }
    n = ev ? 0 : n1;
    k_last = ev ? k : e->k_last;
    dir_last = ev ? edir : e->dir_last;
    if (ev) {
        against = false;
    }

    /* 3. standstill and the prediction between edges (eq. 16) */
    still = n > S;
    if (still) {
        nc_prev = 0;
    }
    speed_ok = nc_prev > 0; /* omega_hat is valid exactly while nc_prev > 0 */
    if (!speed_ok) {
        omega = 0.0f;
    }
    if (still) {
        run = 0;
        alpha = 0.0f;
    }
    if (accel_on) {
        float tau = (((float)nc_prev * 0.5f) + (float)n) * e->T;
        omega_pred = omega + (alpha * tau);
    } else {
        omega_pred = omega;
    }
    adv = ev ? 0.0f : (e->adv + (omega_pred * e->T));
    if (clamp_on && !against) {
        float lo = (float)dq_of(q, k_last, M) * e->QUARTER;
        adv = fminf_(fmaxf_(adv, lo), lo + e->QUARTER);
    }

    /* 4. halls */
    hv = (hall >= 1) && (hall <= 6);
    ha = hv ? hall : 0;
    hs = e->hall_last;
    trans = hv && (hall != hs) && (hs != 0);
    fwd = trans && (hall == HALL_NEXT[hs]);
    rev = trans && (hs == HALL_NEXT[ha]);
    adj = fwd || rev;
    jump = trans && !adj;
    first = hv && (hs == 0);
    hb = fwd ? e->h_start[ha] : e->h_start[hs];
    anchored_before = e->anchored != 0;
    if (adj && !anchored_before && (dir_last == 0)) {
        k_last = q;
    }
    c_last = learn_on ? e->c_tab[k_last / 2] : 0.0f;
    rel = ((float)k_last * e->QUARTER) + c_last;
    /* without a valid speed: the middle of the current quadrature count */
    adv_eff = speed_ok ? adv : (((float)dq_of(q, k_last, M) * e->QUARTER) + e->HALF_QUARTER);
    theta_pred = eol_est_wrap(eol_est_wrap(e->G + rel) + adv_eff);
    err = eol_est_wrap_pm(hb - theta_pred);
    big = fabsf(err) > e->HALF_DELTA;
    if ((fl & EOL_PB_FLAG_EST_LEARN_GRID_OFFSET) != 0u) {
        float gain = 1.0f / (float)imin(e->n_anchor + 1, N_LEARN);
        g = big ? err : (err * gain);
    } else {
        g = err;
    }
    if (adj && anchored_before) {
        G = eol_est_wrap(e->G + g);
    } else if (adj) {
        G = eol_est_wrap(hb - (rel + adv_eff));
    } else {
        G = e->G;
    }
    if (adj) {
        e->anchored = 1;
        e->n_anchor = (!anchored_before || big) ? 1 : imin(e->n_anchor + 1, N_LEARN);
    }
    status = 0u;
    if (adj && (dir_last != 0) && ((fwd ? 1 : -1) != dir_last)) {
        status |= EOL_EST_ST_DIR_MISMATCH;
    }
    if (hv) {
        e->hall_last = hall;
    }
    if (adj || first) {
        e->sector = hall;
    }

    /* 5. outputs */
    theta_enc = eol_est_wrap(G + rel);
    theta = eol_est_wrap(theta_enc + adv_eff);
    if (still) {
        start = e->h_start[e->sector];
        width = e->h_width[e->sector];
        dd = eol_est_wrap(theta - start);
        if (dd > width) {
            end = eol_est_wrap(start + width);
            theta = ((dd - width) < (TWO_PI_F - dd)) ? end : start;
        }
    }
    unanchored = (e->anchored == 0);
    if (unanchored) {
        theta = e->h_mid[e->sector];
        theta_enc = e->h_mid[e->sector];
    }
    omega_out = omega_pred;
    if (clamp_on && (n > 0)) {
        float bound = e->K_OMEGA / (float)n;
        omega_out = fminf_(fmaxf_(omega_out, -bound), bound);
    }
    if (still) {
        status |= EOL_EST_ST_STANDSTILL;
    }
    if (dir_last < 0) {
        status |= EOL_EST_ST_REVERSE;
    }
    if (!hv) {
        status |= EOL_EST_ST_HALL_FAULT;
    }
    if (jump) {
        status |= EOL_EST_ST_HALL_SEQ;
    }
    if (unanchored) {
        status |= EOL_EST_ST_NO_ANCHOR;
    }
    if (qep_err) {
        status |= EOL_EST_ST_QEP_ERROR;
    }
    if (bounce || reject || (ev && !speed_upd)) {
        status |= EOL_EST_ST_EDGE_REJECT;
    }
    if (missing) {
        status |= EOL_EST_ST_MISSING_EDGE;
    }
    if ((nc_prev == 0) && !speed_upd) {
        status |= EOL_EST_ST_NO_SPEED;
    }

    e->phase = ph;
    e->q = q;
    e->n = n;
    e->k_last = k_last;
    e->dir_last = dir_last;
    e->nc_prev = nc_prev;
    e->against = i32_of(against);
    e->omega = omega;
    e->alpha = alpha;
    e->adv = adv;
    e->G = G;
    e->run = run;

    out->theta_hat = theta;
    out->omega_hat = omega_out;
    out->theta_enc = theta_enc;
    out->status = (int32_t)status;
}
