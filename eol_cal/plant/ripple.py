"""Torque ripple sources of the motor (contract section 2 sign convention).

The electromagnetic torque the rotor sees is ``kt*i_q - ripple`` with

    ripple = c6*sin(6*theta_r + phase_c6) + k6*i_q*sin(6*theta_r + phase_k6)
           + c12*sin(12*theta_r + phase_c12) + k12*i_q*sin(12*theta_r + phase_k12)
           + c18*sin(18*theta_r + phase_c18) + k18*i_q*sin(18*theta_r + phase_k18)
           + unb1*sin(theta_m + phase_unb1) + unb2*sin(2*theta_m + phase_unb2)
           + unb3*sin(3*theta_m + phase_unb3)

so that the measured torque reads ``T_avg - c6 sin(6θ+φc) - k6 i_qo sin(6θ+φk) - ...`` exactly as
the contract's ripple model (seed eq. 17 with phases and a cogging term). The load-proportional
terms scale with the motor's actual q current: saturation follows the current that flows, and at
steady state that is the commanded i_qo (plus the small i_qc when compensating).

For speed the scan never calls ``sin`` per harmonic: ``c*sin(n*theta + phi)`` is
``(c*cos phi)*sin(n*theta) + (c*sin phi)*cos(n*theta)`` with the coefficients precomputed
(:func:`coefficients`) and ``sin/cos(n*theta)`` from powers of the unit phasor ``e^{j*theta}``.
"""

from __future__ import annotations

import math
from typing import Protocol

from eol_cal.numerics.arrays import Array


#: Ripple harmonics of the electrical angle (orders) in the coefficient layout.
ORDERS = (6, 12, 18)
#: Orders of the mechanical angle (load-independent: unbalance, eccentricity, ...).
MECH_ORDERS = (1, 2, 3)


class RippleTruth(Protocol):
    """A motor's ripple as built: amplitude and phase of each term (a plant spec holds them)."""

    @property
    def c6(self) -> float: ...  # N*m

    @property
    def phase_c6(self) -> float: ...  # rad

    @property
    def k6(self) -> float: ...  # N*m/A

    @property
    def phase_k6(self) -> float: ...  # rad

    @property
    def c12(self) -> float: ...  # N*m

    @property
    def phase_c12(self) -> float: ...  # rad

    @property
    def k12(self) -> float: ...  # N*m/A

    @property
    def phase_k12(self) -> float: ...  # rad

    @property
    def c18(self) -> float: ...  # N*m

    @property
    def phase_c18(self) -> float: ...  # rad

    @property
    def k18(self) -> float: ...  # N*m/A

    @property
    def phase_k18(self) -> float: ...  # rad

    @property
    def unb1(self) -> float: ...  # N*m

    @property
    def phase_unb1(self) -> float: ...  # rad

    @property
    def unb2(self) -> float: ...  # N*m

    @property
    def phase_unb2(self) -> float: ...  # rad

    @property
    def unb3(self) -> float: ...  # N*m

    @property
    def phase_unb3(self) -> float: ...  # rad


class RippleCoefficients(Protocol):
    """The sine/cosine coefficients of :func:`coefficients`, per tick (a plant's parameters hold them)."""

    @property
    def s6c(self) -> Array: ...  # N*m

    @property
    def c6c(self) -> Array: ...  # N*m

    @property
    def s6k(self) -> Array: ...  # N*m/A

    @property
    def c6k(self) -> Array: ...  # N*m/A

    @property
    def s12c(self) -> Array: ...  # N*m

    @property
    def c12c(self) -> Array: ...  # N*m

    @property
    def s12k(self) -> Array: ...  # N*m/A

    @property
    def c12k(self) -> Array: ...  # N*m/A

    @property
    def s18c(self) -> Array: ...  # N*m

    @property
    def c18c(self) -> Array: ...  # N*m

    @property
    def s18k(self) -> Array: ...  # N*m/A

    @property
    def c18k(self) -> Array: ...  # N*m/A

    @property
    def s1u(self) -> Array: ...  # N*m

    @property
    def c1u(self) -> Array: ...  # N*m

    @property
    def s2u(self) -> Array: ...  # N*m

    @property
    def c2u(self) -> Array: ...  # N*m

    @property
    def s3u(self) -> Array: ...  # N*m

    @property
    def c3u(self) -> Array: ...  # N*m


def coefficients(spec: RippleTruth) -> dict[str, float]:
    """Sine/cosine coefficients of every ripple term of a motor (N*m and N*m/A).

    Keys ``s6c, c6c`` (cogging: coefficient of sin and cos of 6*theta, N*m), ``s6k, c6k``
    (per ampere of i_q, N*m/A), likewise for 12 and 18, and ``s1u, c1u`` .. ``s3u, c3u`` for the
    mechanical orders 1..3 (unbalance, eccentricity, ...).
    """
    out: dict[str, float] = {}
    for n in ORDERS:
        c, pc = getattr(spec, f"c{n}"), getattr(spec, f"phase_c{n}")
        k, pk = getattr(spec, f"k{n}"), getattr(spec, f"phase_k{n}")
        out[f"s{n}c"], out[f"c{n}c"] = c * math.cos(pc), c * math.sin(pc)
        out[f"s{n}k"], out[f"c{n}k"] = k * math.cos(pk), k * math.sin(pk)
    for h in MECH_ORDERS:
        u, pu = getattr(spec, f"unb{h}"), getattr(spec, f"phase_unb{h}")
        out[f"s{h}u"], out[f"c{h}u"] = u * math.cos(pu), u * math.sin(pu)
    return out


def harmonic_phasors(cos_r: Array, sin_r: Array) -> tuple[tuple[Array, Array], ...]:
    """``(cos, sin)`` of 6, 12 and 18 times the electrical angle from its own cos and sin."""
    c2, s2 = cos_r * cos_r - sin_r * sin_r, 2.0 * sin_r * cos_r
    c3, s3 = c2 * cos_r - s2 * sin_r, s2 * cos_r + c2 * sin_r
    c6, s6 = c3 * c3 - s3 * s3, 2.0 * s3 * c3
    c12, s12 = c6 * c6 - s6 * s6, 2.0 * s6 * c6
    c18, s18 = c12 * c6 - s12 * s6, s12 * c6 + c12 * s6
    return (c6, s6), (c12, s12), (c18, s18)


def ripple_torque(cos_r: Array, sin_r: Array, cos_m: Array, sin_m: Array, i_q: Array, p: RippleCoefficients) -> Array:
    """Ripple torque to subtract from ``kt*i_q`` (N*m).

    Parameters
    ----------
    cos_r, sin_r : array
        Cosine and sine of the actual electrical angle theta_r.
    cos_m, sin_m : array
        Cosine and sine of the actual mechanical angle theta_m (mechanical orders 1..3).
    i_q : array
        Actual q-axis current (A).
    p : RippleCoefficients
        The coefficients of :func:`coefficients` as attributes.
    """
    (c6, s6), (c12, s12), (c18, s18) = harmonic_phasors(cos_r, sin_r)
    total = (p.s6c + p.s6k * i_q) * s6 + (p.c6c + p.c6k * i_q) * c6
    total = total + (p.s12c + p.s12k * i_q) * s12 + (p.c12c + p.c12k * i_q) * c12
    total = total + (p.s18c + p.s18k * i_q) * s18 + (p.c18c + p.c18k * i_q) * c18
    c2m, s2m = cos_m * cos_m - sin_m * sin_m, 2.0 * sin_m * cos_m
    c3m, s3m = c2m * cos_m - s2m * sin_m, s2m * cos_m + c2m * sin_m
    total = total + p.s1u * sin_m + p.c1u * cos_m
    return total + p.s2u * s2m + p.c2u * c2m + p.s3u * s3m + p.c3u * c3m
