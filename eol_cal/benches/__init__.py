"""Built-in bench descriptions (``NAME.toml``), read by :func:`eol_cal.domain.bench_mechanics.load_mechanics`."""
