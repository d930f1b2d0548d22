"""Measurement system analysis: is the station's ripple measurement itself capable?

:mod:`eol_cal.msa.type1` is the type-1 gauge study (one reference part measured n times:
bias, repeatability, Cg and Cgk against a tolerance); ``docs/spc.md`` defines the figures.
"""
