"""Built-in bench descriptions (``NAME.toml``), read by :func:`eol_cal.mechanics.load_mechanics`."""
