"""Built-in plant: a simulated end-of-line bench (motor, inverter, ECU control, sensors, ripple,
dyno) in JAX, running the firmware reference's estimator and compensator.

Entry points: :func:`eol_cal.plant.simulate.simulate`, presets in :mod:`eol_cal.plant.presets`,
production spread in :mod:`eol_cal.plant.variation`, test profiles in :mod:`eol_cal.plant.profile`.
Nothing here imports JAX at module import time except :mod:`eol_cal.plant.simulate`'s functions.
"""
