"""Built-in production spreads (TOML), read by :func:`eol_cal.plant.spread.load_spread`."""
