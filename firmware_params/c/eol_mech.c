/* eol_mech.c: see eol_mech.h and ../MECH.md. Every float expression keeps the order of the
 * Python reference (eol_cal/firmware/mech.py); sums run from element 0 up. */
#include "eol_fp.h" /* first: the floating-point contract */
#include <math.h>
#include <stdbool.h>

#include "eol_comp.h"
#include "eol_mech.h"

#define TWO_PI_F 6.28318548f /* 0x40c90fdb */
#define PI_F 3.14159274f     /* 0x40490fdb */

static int32_t mech_i32_of(bool x)
{
    return x ? 1 : 0;
}

int eol_mech_enabled(const uint16_t *w)
{
    uint32_t flags = EOL_PB_GET_FLAGS(w);
    uint16_t n = EOL_PB_GET_TABLE_LEN(w);
    bool ok = (EOL_PB_GET_LAYOUT_VERSION(w) == EOL_PB_LAYOUT_VERSION_MECH) &&
              ((flags & EOL_PB_FLAG_MECH_COMP_ENABLE) != 0u) &&
              ((flags & EOL_PB_FLAGS_MECH_NEEDS) == EOL_PB_FLAGS_MECH_NEEDS);
    /* the extension's fields are read only from a layout-2 block */
    if (ok) {
        ok = (EOL_PB_V2_GET_FP_DIRS(w, n) != 0u) && (EOL_PB_V2_GET_FP_LEN(w, n) == EOL_PB_GET_ENCODER_PPR(w));
    }
    return mech_i32_of(ok);
}

int eol_mech_init(eol_mech_t *m, const eol_est_t *est, const uint16_t *w)
{
    int32_t i, d, mm;
    uint16_t n = EOL_PB_GET_TABLE_LEN(w);
    m->N = est->cfg.n_enc;
    m->PP = est->cfg.poles / 2;
    m->M = est->M;
    m->DELTA = est->DELTA;
    m->QUARTER = est->QUARTER;
    m->INV_DELTA = 1.0f / est->DELTA;
    m->KM = (float)EOL_MECH_TABLE_LEN / ((float)est->cfg.poles * PI_F);
    m->enabled = mech_i32_of((eol_mech_enabled(w) != 0) && (m->PP <= EOL_MECH_MAX_PP));
    m->lead_s = EOL_PB_GET_LEAD_S(w);
    m->dirs = 0;
    m->grid_phase = 0.0f;
    m->id_min_score = 0.0f;
    m->id_margin = 0.0f;
    m->id_frac_tol = 0.0f;
    for (i = 0; i < EOL_MECH_TABLE_LEN; ++i) {
        m->table_const[i] = 0.0f;
        m->table_per_amp[i] = 0.0f;
    }
    for (i = 0; i < (2 * m->N); ++i) {
        m->dF[i] = 0.0f;
        m->acc[i] = 0.0f;
        m->cnt[i] = 0;
    }
    for (i = 0; i < EOL_EST_MAX_PPR; ++i) {
        m->a[i] = 0.0f;
    }
    m->EF[0] = 0.0f;
    m->EF[1] = 0.0f;
    if (m->enabled != 0) {
        m->dirs = (int32_t)EOL_PB_V2_GET_FP_DIRS(w, n);
        m->grid_phase = EOL_PB_V2_GET_GRID_PHASE(w, n);
        m->id_min_score = EOL_PB_V2_GET_ID_MIN_SCORE(w, n);
        m->id_margin = EOL_PB_V2_GET_ID_MARGIN(w, n);
        m->id_frac_tol = EOL_PB_V2_GET_ID_FRAC_TOL(w, n);
        for (i = 0; i < EOL_MECH_TABLE_LEN; ++i) {
            m->table_const[i] = EOL_PB_V2_GET_MECH_TABLE_CONST(w, n, i);
            m->table_per_amp[i] = EOL_PB_V2_GET_MECH_TABLE_PER_AMP(w, n, i);
        }
        for (d = 0; d < 2; ++d) {
            float ef = 0.0f;
            for (mm = 0; mm < m->N; ++mm) {
                int32_t prev = ((mm + m->N) - 1) % m->N;
                const int32_t i_now = (2 * mm) + d;
                const int32_t i_prev = (2 * prev) + d;
                float df = EOL_PB_V2_GET_FINGERPRINT(w, n, i_now) - EOL_PB_V2_GET_FINGERPRINT(w, n, i_prev);
                m->dF[(2 * mm) + d] = df;
                ef = ef + (df * df);
            }
            m->EF[d] = ef;
        }
    }
    m->n_new = 0;
    m->cand = -1;
    m->active = 0;
    m->r = 0;
    m->score = 0.0f;
    m->margin = 0.0f;
    return (m->PP > EOL_MECH_MAX_PP) ? -1 : 0;
}

/* mean of the estimator's learned edge errors of direction d (rad) */
static float mean_c_of(const eol_mech_t *m, const eol_est_t *est, int32_t d)
{
    float s = 0.0f;
    int32_t mm;
    for (mm = 0; mm < m->N; ++mm) {
        s = s + est->c_tab[(2 * mm) + d];
    }
    return eol_div(s, (float)m->N);
}

typedef struct {
    bool ok;      /* the best hypothesis passed the three thresholds */
    int32_t r;    /* its offset */
    float score;  /* its cosine */
    float margin; /* over the next */
} eval_t;

/* whether every edge of direction d has a sample (an evaluation needs them all) */
static bool complete(const eol_mech_t *m, int32_t d)
{
    bool all = true;
    int32_t mm;
    for (mm = 0; mm < m->N; ++mm) {
        if (m->cnt[(2 * mm) + d] < 1) {
            all = false;
        }
    }
    return all;
}

/* one evaluation of a complete direction d (MECH.md, "Evaluation") */
static eval_t evaluate(eol_mech_t *m, const eol_est_t *est, int32_t d)
{
    float Ea = 0.0f, dg, den, best_rho = 0.0f, best_e = 0.0f, second = 0.0f;
    float rho_j[EOL_MECH_MAX_PP];
    int32_t mm, j, best_j = 0, rb = 0;
    eval_t out;
    for (mm = 0; mm < m->N; ++mm) {
        m->a[mm] = eol_div(m->acc[(2 * mm) + d], (float)m->cnt[(2 * mm) + d]);
        Ea = Ea + (m->a[mm] * m->a[mm]);
    }
    dg = eol_est_wrap((est->G + mean_c_of(m, est, d)) - m->grid_phase);
    den = eol_sqrt(Ea * m->EF[d]);
    for (j = 0; j < m->PP; ++j) {
        float x = (dg + (TWO_PI_F * (float)j)) * m->INV_DELTA;
        int32_t r = (int32_t)floorf(x + 0.5f) % m->N;
        float e = eol_est_wrap_pm(dg - ((float)r * m->DELTA));
        float s = 0.0f;
        float rho;
        for (mm = 0; mm < m->N; ++mm) {
            s = s + (m->a[mm] * m->dF[(2 * ((mm + r) % m->N)) + d]);
        }
        rho = (den > 0.0f) ? eol_div(s, den) : 0.0f;
        rho_j[j] = rho;
        if ((j == 0) || (rho > best_rho)) {
            best_rho = rho;
            rb = r;
            best_e = e;
            best_j = j;
        }
    }
    for (j = 0; j < m->PP; ++j) {
        if ((j != best_j) && (rho_j[j] > second)) {
            second = rho_j[j];
        }
    }
    out.margin = best_rho - second;
    out.score = best_rho;
    out.r = rb;
    out.ok = (best_rho >= m->id_min_score) && (out.margin >= m->id_margin) && (fabsf(best_e) <= m->id_frac_tol);
    return out;
}

static void withdraw(eol_mech_t *m)
{
    int32_t i;
    for (i = 0; i < (2 * m->N); ++i) {
        m->acc[i] = 0.0f;
        m->cnt[i] = 0;
    }
    m->n_new = 0;
    m->cand = -1;
    m->active = 0;
}

void eol_mech_step(eol_mech_t *m, const eol_est_t *est, const eol_est_out_t *eo, eol_mech_out_t *out)
{
    const bool enabled = m->enabled != 0;
    const bool active = m->active != 0;
    const bool reverse = est->dir_last < 0;
    int32_t d = 0;
    uint32_t dir_bit = 1u;
    bool take, fault, due, mark, ev_eval = false, passed, confirm, eval_bad, frac_bad = false;
    eval_t ev = {false, 0, 0.0f, 0.0f};
    uint32_t events = 0u;

    if (reverse) {
        d = 1;
        dir_bit = 2u;
    }
    /* 1. accumulate this tick's pitch sample */
    take = enabled && (eo->learn != 0) && (m->cnt[eo->learn_idx] < EOL_MECH_CNT_MAX);
    if (take) {
        m->acc[eo->learn_idx] = m->acc[eo->learn_idx] + eo->pitch_err;
        m->cnt[eo->learn_idx] += 1;
        if (m->n_new < m->N) {
            m->n_new += 1;
        }
    }
    fault = enabled && (((uint32_t)eo->status & EOL_MECH_RESET_STATUS) != 0u);
    /* 2. evaluation */
    due = enabled && !fault && (est->anchored != 0) && (m->n_new >= m->N) && (((uint32_t)m->dirs & dir_bit) != 0u);
    mark = (est->n == 0) && ((est->k_last / 4) == 0);
    if (due && complete(m, d)) {
        ev = evaluate(m, est, d);
        ev_eval = true;
    }
    passed = ev_eval && ev.ok;
    confirm = passed && !active && (m->cand == ev.r);
    eval_bad = ev_eval && active && (!ev.ok || (ev.r != m->r));
    /* 3. revolution mark: the hall-to-encoder fraction of the identified offset */
    if (enabled && active && mark && !ev_eval) {
        float e_now = eol_est_wrap_pm(((est->G + mean_c_of(m, est, d)) - m->grid_phase) - ((float)m->r * m->DELTA));
        frac_bad = fabsf(e_now) > m->id_frac_tol;
    }
    if (ev_eval) {
        events |= EOL_MECH_EV_EVAL;
        m->score = ev.score;
        m->margin = ev.margin;
        m->n_new = 0;
        m->cand = ev.ok ? ev.r : -1;
    }
    if (passed) {
        events |= EOL_MECH_EV_PASS;
    }
    if (fault || eval_bad || frac_bad) {
        withdraw(m);
        if (fault) {
            events |= EOL_MECH_EV_RESET_FAULT;
        }
        if (frac_bad) {
            events |= EOL_MECH_EV_RESET_FRACTION;
        }
        if (eval_bad) {
            events |= EOL_MECH_EV_RESET_EVAL;
        }
    } else if (confirm) {
        m->active = 1;
        m->r = ev.r;
        events |= EOL_MECH_EV_IDENTIFIED;
    } else {
        /* the state stays */
    }
    out->active = m->active;
    out->r = m->r;
    out->events = (int32_t)events;
    out->score = m->score;
    out->margin = m->margin;
}

float eol_mech_sum(const eol_mech_t *m, int32_t r, int32_t q, float theta_hat, float omega_hat, float i_qo)
{
    float a, t, ek, e;
    int32_t k;
    a = omega_hat * m->lead_s;
    t = theta_hat + a;
    k = (q + (4 * r)) % m->M;
    ek = m->grid_phase + ((float)k * m->QUARTER);
    e = ek + eol_est_wrap_pm(t - ek);
    return eol_comp_table_sum(e, i_qo, m->table_const, m->table_per_amp, EOL_MECH_TABLE_LEN, m->KM);
}
