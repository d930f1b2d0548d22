/* eol_fp.h: the floating-point contract of the C reference (docs/firmware-contract.md, section 4,
 * "Floating point"): every binary32 operation is rounded once, in the order written; no multiply
 * and add is contracted into a fused multiply-add, whatever the build's flags allow. Included
 * first by every source, so the pragma holds for the whole translation unit.
 *
 * GCC does not implement the standard pragma (it warns and ignores it) but honours its own, which
 * overrides -ffp-contract=fast. Clang honours the standard one unless built with
 * -ffp-contract=fast, which by its definition disregards pragmas: the contract forbids that flag
 * (and TI's --fp_mode=relaxed, its equivalent). */
#ifndef EOL_FP_H
#define EOL_FP_H

#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC optimize("fp-contract=off")
#else
#pragma STDC FP_CONTRACT OFF
#endif

/* Division and square root of the identification's evaluation (a background task): the target's
 * own (the C28x: estimate + two Newton steps), within the golden vectors' ulp classes (the
 * manifest's "ulp", docs/firmware-contract.md section 4). The host build is correctly rounded;
 * built with -DEOL_FPU_C28X it models the C28x bit for bit as eol_cal/firmware/fpu_c28x.py does. */
float eol_div(float a, float b);
float eol_sqrt(float x);

#endif /* EOL_FP_H */
