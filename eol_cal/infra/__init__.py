"""Infrastructure every layer uses: atomic writes, bounded input files, retries, signals, the
exchange log, addresses, JSON numbers."""
