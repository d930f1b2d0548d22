/* eol_mech.c: see eol_mech.h and ../MECH.md. Every float expression keeps the order of the
 * Python reference (eol_cal/firmware/mech.py); sums run from element 0 up. */
#include "eol_fp.h" /* first: the floating-point contract */
#include <math.h>
#include <stdbool.h>
#include <string.h>

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
    /* everything 0 (0.0f is all-zero bits in binary32), then what is not */
    (void)memset(m, 0, sizeof *m);
    m->N = est->cfg.n_enc;
    m->PP = est->cfg.poles / 2;
    m->M = est->M;
    m->DELTA = est->DELTA;
    m->QUARTER = est->QUARTER;
    m->INV_DELTA = 1.0f / est->DELTA;
    m->KM = (float)EOL_MECH_TABLE_LEN / ((float)est->cfg.poles * PI_F);
    m->enabled = mech_i32_of((eol_mech_enabled(w) != 0) && (m->PP <= EOL_MECH_MAX_PP));
    m->lead_s = EOL_PB_GET_LEAD_S(w);
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
    m->cand = -1;
    m->miss[0] = m->N;
    m->miss[1] = m->N;
    /* the grid, the mean pitch errors 16 edges a slice, the norm, one per hypothesis, the verdict */
    m->n_slices = 1 + ((m->N + (EOL_MECH_SLICE_EDGES - 1)) / EOL_MECH_SLICE_EDGES) + 1 + m->PP + 1;
    m->n_clear = ((2 * m->N) + (EOL_MECH_SLICE_EDGES - 1)) / EOL_MECH_SLICE_EDGES;
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

/* constant work: the samples are cleared by the background (clr), the tick takes none until then */
static void withdraw(eol_mech_t *m)
{
    m->clr = 1;
    m->miss[0] = m->N;
    m->miss[1] = m->N;
    m->n_new = 0;
    m->cand = -1;
    m->active = 0;
    m->busy = 0;
    m->mk = 0;
}

void eol_mech_step(eol_mech_t *m, const eol_est_t *est, const eol_est_out_t *eo, eol_mech_out_t *out)
{
    const bool enabled = m->enabled != 0;
    const bool done = m->busy == (m->n_slices + 1);
    const bool ok = m->ev_ok != 0;
    bool take, fault, passed, confirm, eval_bad, frac_bad, reset, due, mark;
    int32_t d = 0;
    uint32_t dir_bit = 1u;
    uint32_t events = 0u;

    if (est->dir_last < 0) {
        d = 1;
        dir_bit = 2u;
    }
    /* 1. collect this tick's pitch sample (not while an evaluation reads the samples) */
    take = enabled && (m->clr == 0) && (m->busy == 0) && (eo->learn != 0) && (m->cnt[eo->learn_idx] < EOL_MECH_CNT_MAX);
    if (take) {
        if (m->cnt[eo->learn_idx] == 0) {
            m->miss[eo->learn_idx % 2] -= 1;
        }
        m->acc[eo->learn_idx] = m->acc[eo->learn_idx] + eo->pitch_err;
        m->cnt[eo->learn_idx] += 1;
        if (m->n_new < m->N) {
            m->n_new += 1;
        }
    }
    fault = enabled && (((uint32_t)eo->status & EOL_MECH_RESET_STATUS) != 0u);
    /* 2. a finished evaluation, a finished mark check */
    passed = done && ok;
    confirm = passed && (m->active == 0) && (m->cand == m->ev_r);
    eval_bad = done && (m->active != 0) && (!ok || (m->ev_r != m->r));
    frac_bad = (m->mk == 2) && (m->active != 0) && (m->mk_bad != 0);
    reset = fault || eval_bad || frac_bad;
    if (done) {
        events |= EOL_MECH_EV_EVAL;
        m->score = m->ev_score;
        m->margin = m->ev_margin;
        m->cand = ok ? m->ev_r : -1;
        m->busy = 0;
    }
    if (m->mk == 2) {
        m->mk = 0;
    }
    if (passed) {
        events |= EOL_MECH_EV_PASS;
    }
    if (reset) {
        withdraw(m);
        if (fault) {
            events |= EOL_MECH_EV_RESET_FAULT;
        } else if (frac_bad) {
            events |= EOL_MECH_EV_RESET_FRACTION;
        } else {
            /* an evaluation withdrew it */
        }
        if (eval_bad && !fault) {
            events |= EOL_MECH_EV_RESET_EVAL;
        }
    } else if (confirm) {
        m->active = 1;
        m->r = m->ev_r;
        events |= EOL_MECH_EV_IDENTIFIED;
    } else {
        /* the state stays */
    }
    /* 3. start an evaluation when a revolution of fresh samples is in */
    due = enabled && !reset && (est->anchored != 0) && (m->n_new >= m->N) && (((uint32_t)m->dirs & dir_bit) != 0u) &&
          (m->miss[d] == 0) && (m->busy == 0) && (m->clr == 0);
    if (due) {
        m->busy = 1;
        m->ev_d = d;
        m->ev_G = est->G;
        m->n_new = 0;
    }
    /* 4. ask for the revolution mark's check: an A edge at the firmware's pulse 0 */
    mark = enabled && (m->active != 0) && (est->n == 0) && ((est->k_last / 4) == 0) && (m->mk == 0);
    if (mark) {
        m->mk = 1;
        m->mk_d = d;
        m->mk_G = est->G;
    }
    out->active = m->active;
    out->r = m->r;
    out->events = (int32_t)events;
    out->score = m->score;
    out->margin = m->margin;
}

/* one hypothesis of the evaluation: pole pair j (MECH.md, "Evaluation") */
static void hypothesis(eol_mech_t *m, int32_t j)
{
    const int32_t d = m->ev_d;
    float x = (m->dg + (TWO_PI_F * (float)j)) * m->INV_DELTA;
    int32_t r = (int32_t)floorf(x + 0.5f) % m->N;
    float e = eol_est_wrap_pm(m->dg - ((float)r * m->DELTA));
    float s = 0.0f;
    float rho;
    int32_t mm;
    for (mm = 0; mm < m->N; ++mm) {
        int32_t i = mm + r; /* (mm + r) mod N without a runtime modulo */
        if (i >= m->N) {
            i -= m->N;
        }
        s = s + (m->a[mm] * m->dF[(2 * i) + d]);
    }
    rho = (m->den > 0.0f) ? eol_div(s, m->den) : 0.0f;
    m->rho_j[j] = rho;
    if ((j == 0) || (rho > m->best_rho)) {
        m->best_rho = rho;
        m->ev_r = r;
        m->best_e = e;
        m->best_j = j;
    }
}

/* the evaluation's verdict from its hypotheses */
static void verdict(eol_mech_t *m)
{
    float second = 0.0f;
    int32_t j;
    for (j = 0; j < m->PP; ++j) {
        if ((j != m->best_j) && (m->rho_j[j] > second)) {
            second = m->rho_j[j];
        }
    }
    m->ev_margin = m->best_rho - second;
    m->ev_score = m->best_rho;
    m->ev_ok = mech_i32_of((m->best_rho >= m->id_min_score) && (m->ev_margin >= m->id_margin) &&
                           (fabsf(m->best_e) <= m->id_frac_tol));
}

void eol_mech_background(eol_mech_t *m, const eol_est_t *est)
{
    const int32_t n_chunks = (m->N + (EOL_MECH_SLICE_EDGES - 1)) / EOL_MECH_SLICE_EDGES;
    const int32_t k = m->busy;
    if (m->clr != 0) {
        int32_t i;
        const int32_t i0 = (m->clr - 1) * EOL_MECH_SLICE_EDGES;
        for (i = i0; (i < (i0 + EOL_MECH_SLICE_EDGES)) && (i < (2 * m->N)); ++i) {
            m->acc[i] = 0.0f;
            m->cnt[i] = 0;
        }
        m->clr = (m->clr >= m->n_clear) ? 0 : (m->clr + 1);
    } else if ((k >= 1) && (k <= m->n_slices)) {
        const int32_t d = m->ev_d;
        if (k == 1) {
            /* the firmware's mean grid against the block's; the samples' norm starts */
            m->dg = eol_est_wrap((m->ev_G + mean_c_of(m, est, d)) - m->grid_phase);
            m->Ea = 0.0f;
        } else if (k <= (1 + n_chunks)) {
            int32_t mm;
            const int32_t m0 = (k - 2) * EOL_MECH_SLICE_EDGES;
            for (mm = m0; (mm < (m0 + EOL_MECH_SLICE_EDGES)) && (mm < m->N); ++mm) {
                m->a[mm] = eol_div(m->acc[(2 * mm) + d], (float)m->cnt[(2 * mm) + d]);
                m->Ea = m->Ea + (m->a[mm] * m->a[mm]);
            }
        } else if (k == (2 + n_chunks)) {
            m->den = eol_sqrt(m->Ea * m->EF[d]);
        } else if (k < m->n_slices) {
            hypothesis(m, k - (3 + n_chunks));
        } else {
            verdict(m);
        }
        m->busy = k + 1;
    } else if (m->mk == 1) {
        float e_now = eol_est_wrap_pm(((m->mk_G + mean_c_of(m, est, m->mk_d)) - m->grid_phase) -
                                      ((float)m->r * m->DELTA));
        m->mk_bad = mech_i32_of(fabsf(e_now) > m->id_frac_tol);
        m->mk = 2;
    } else {
        /* nothing to do */
    }
}

float eol_mech_sum(const eol_mech_t *m, int32_t r, int32_t q, float theta_hat, float omega_hat, float i_qo)
{
    float a, t, ek, e;
    int32_t k;
    a = omega_hat * m->lead_s;
    t = theta_hat + a;
    k = q + (4 * r); /* mod M: both in [0, M) */
    if (k >= m->M) {
        k -= m->M;
    }
    ek = m->grid_phase + ((float)k * m->QUARTER);
    e = ek + eol_est_wrap_pm(t - ek);
    return eol_comp_table_sum(e, i_qo, m->table_const, m->table_per_amp, EOL_MECH_TABLE_LEN, m->KM);
}
