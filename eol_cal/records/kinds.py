"""The run kinds of a record (docs/records.md, "Run kinds"): names only, so the command line's
options list them without loading the records' machinery."""

from __future__ import annotations

KINDS = ("production", "refusal", "restore", "master", "simulated")
#: the kind lot statistics, first-pass yield, latest status, ``lot diff`` and ``refit`` take by default
MEASURED_KIND = "production"
