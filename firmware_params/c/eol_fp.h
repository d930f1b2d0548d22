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

#endif /* EOL_FP_H */
