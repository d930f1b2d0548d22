/* eol_comp.h: torque-ripple compensator evaluation (firmware contract section 2), C99, float only.
 * The exact arithmetic is specified in ../COMPENSATOR.md; compile with -ffp-contract=off (no
 * fused multiply-add) to match the golden vectors bit for bit. */
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

#ifdef __cplusplus
}
#endif

#endif /* EOL_COMP_H */
