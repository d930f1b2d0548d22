/* eol_comp.h: torque-ripple compensator evaluation (firmware contract section 2), C99, float only.
 * The exact arithmetic is specified in ../COMPENSATOR.md; the sources' floating-point contract
 * (eol_fp.h: no fused multiply-add) makes any build match the golden vectors bit for bit. */
#ifndef EOL_COMP_H
#define EOL_COMP_H

#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

/* 6/(2*pi) rounded to binary32: bit pattern 0x3F747645 (9 significant digits round-trip) */
#define EOL_COMP_K_6_OVER_2PI 0.954929650f

/* i_qc in A from theta_hat (rad, electrical, any finite value), omega_hat (rad/s, electrical,
 * signed), i_qo (A, signed), the block's tables of n entries (n a power of two), lead_s (s) and
 * iqc_limit (A). The caller applies the COMP_ENABLE flag. */
float eol_comp_iqc(float theta_hat, float omega_hat, float i_qo,
                   const float *table_const, const float *table_per_amp, uint16_t n,
                   float lead_s, float iqc_limit);

/* The same with the mechanical-order current of a layout-2 block (../MECH.md, "Compensation"):
 * where mech_on is non-zero, mech_sum (A, eol_mech_sum) is added before the clamp; else the
 * result is eol_comp_iqc's, bit for bit. */
float eol_comp_iqc_mech(float theta_hat, float omega_hat, float i_qo,
                        const float *table_const, const float *table_per_amp, uint16_t n,
                        float lead_s, float iqc_limit, int32_t mech_on, float mech_sum);

/* The two tables of n entries (a power of two) read at angle x (rad) with `scale` entries per rad
 * and summed, lerp(table_const) + i_qo * lerp(table_per_amp), before any clamp (A): the steps from
 * v to s of ../COMPENSATOR.md, shared by the 6th-harmonic and the mechanical tables. */
float eol_comp_table_sum(float x, float i_qo, const float *table_const, const float *table_per_amp,
                         uint16_t n, float scale);

#ifdef __cplusplus
}
#endif

#endif /* EOL_COMP_H */
