/* eol_comp.c: see eol_comp.h and ../COMPENSATOR.md. One statement per rounding step. */
#include "eol_fp.h" /* first: the floating-point contract */
#include <math.h>

#include "eol_comp.h"

float eol_comp_table_sum(float x, float i_qo, const float *table_const, const float *table_per_amp,
                         uint16_t n, float scale)
{
    const float n_f = (float)n;
    const float recip_n = 1.0f / n_f; /* exact */
    const uint16_t mask = (uint16_t)(n - 1u);
    float v, q, u, g, f, w, lc, lp, m;
    uint16_t j, j1;

    v = x * scale;
    q = floorf(v * recip_n);
    u = v - (q * n_f);           /* in [0, n]; n only by rounding of a tiny negative v */
    g = floorf(u);
    f = u - g;
    j = (uint16_t)((uint16_t)g & mask);  /* g in [0, n]: j = n maps to entry 0 (f = 0) */
    j1 = (uint16_t)((uint16_t)(j + 1u) & mask);
    w = 1.0f - f;
    lc = w * table_const[j];
    lc = lc + (f * table_const[j1]);
    lp = w * table_per_amp[j];
    lp = lp + (f * table_per_amp[j1]);
    m = i_qo * lp;
    return lc + m;
}

static float clamp_iqc(float s, float iqc_limit)
{
    float c = s;
    if (s > iqc_limit) {
        c = iqc_limit;
    } else if (s < -iqc_limit) {
        c = -iqc_limit;
    } else {
        /* within the limit */
    }
    return c;
}

float eol_comp_iqc(float theta_hat, float omega_hat, float i_qo,
                   const float *table_const, const float *table_per_amp, uint16_t n,
                   float lead_s, float iqc_limit)
{
    return eol_comp_iqc_mech(theta_hat, omega_hat, i_qo, table_const, table_per_amp, n, lead_s, iqc_limit,
                             0, 0.0f);
}

float eol_comp_iqc_mech(float theta_hat, float omega_hat, float i_qo,
                        const float *table_const, const float *table_per_amp, uint16_t n,
                        float lead_s, float iqc_limit, int32_t mech_on, float mech_sum)
{
    const float scale = (float)n * EOL_COMP_K_6_OVER_2PI; /* exact: n is a power of two */
    float a, t, s;

    a = omega_hat * lead_s;
    t = theta_hat + a;
    s = eol_comp_table_sum(t, i_qo, table_const, table_per_amp, n, scale);
    if (mech_on != 0) {
        s = s + mech_sum;
    }
    return clamp_iqc(s, iqc_limit);
}
