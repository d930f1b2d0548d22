/* eol_fp.c: see eol_fp.h. */
#include "eol_fp.h" /* first: the floating-point contract */

#include <math.h>
#include <stdint.h>
#include <string.h>

#ifdef EOL_FPU_C28X
/* the estimate instructions' 8 significand bits (EINVF32, EISQRTF32: SPRUEO2) */
#define EST_MASK 0xFFFF8000u

static float estimate(float x)
{
    uint32_t u;
    float y;
    (void)memcpy(&u, &x, sizeof u);
    u &= EST_MASK;
    (void)memcpy(&y, &u, sizeof y);
    return y;
}

float eol_div(float a, float b)
{
    float y = estimate(1.0f / b);
    y = y * (2.0f - (b * y));
    y = y * (2.0f - (b * y));
    return a * y;
}

float eol_sqrt(float x)
{
    float r = 0.0f;
    if (x > 0.0f) {
        float h = 0.5f * x;
        float y = estimate(1.0f / sqrtf(x));
        y = y * (1.5f - ((h * y) * y));
        y = y * (1.5f - ((h * y) * y));
        r = x * y;
    }
    return r;
}
#else
float eol_div(float a, float b)
{
    return a / b;
}

float eol_sqrt(float x)
{
    return sqrtf(x);
}
#endif
