"""The end-of-line station: the cycle for one motor as steps through one executor, its settings,
reports, restores and what-if lots (the records it writes: :mod:`eol_cal.records`)."""
