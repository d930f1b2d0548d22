"""Offline analysis of captures: angle reconstruction, ripple metrics, order spectra, the fit.

Submodules are imported explicitly (``from eol_cal.analysis.angle import reconstruct_angle``)
so that importing one of them never pulls in JAX.
"""
