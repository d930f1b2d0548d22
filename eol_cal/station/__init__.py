"""The end-of-line station: limits per variant, the cycle for one motor, records and reports."""
