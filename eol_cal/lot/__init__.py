"""A lot of motors: statistics over run records (:mod:`eol_cal.lot.stats`)."""
