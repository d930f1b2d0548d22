"""Built-in test profiles (TOML), see :mod:`eol_cal.plant.profile`."""
