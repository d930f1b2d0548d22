"""Built-in bench descriptions (``NAME.toml``), read by :func:`eol_cal.bench.load_bench`."""
