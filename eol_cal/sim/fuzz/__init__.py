"""Hostile inputs for the fault test and the fault benchmark (issue 16): seeded mutations of
real files, and a runner that feeds them to the real CLI in a child process and judges the end.

Six kinds of input, each a mutation of a valid file the tool writes itself:

- ``csv``: a CSV capture (bit flips, truncation, hostile cells, units and metadata, huge headers);
- ``mdf4``: an MDF4 capture (bit flips, truncation, block links patched to point at their own
  block, outside the file or at a block of another type, block lengths, link counts,
  compressed-data lengths, cycle counts and channel offsets patched);
- ``block``: a parameter block (bit flips, fields patched to NaN, infinities, 3e38, 0, with the
  CRC made right again so that only a physical-sanity check can refuse it);
- ``fitjson``: a fit result (values of the wrong type or out of bounds, deep nesting, huge
  numbers, truncation);
- ``block2`` and ``fitjson2``: the same for a layout-2 block (contract revision 1.2, its
  mechanical fields patched too) and a fit result carrying a ``mech`` object.

A run is judged on what a station cares about: the exit code is 0, 1 or 2 (no signal, no
other code), no ``Traceback`` on stderr, the command ended within its time bound, its memory
stayed under ``RLIMIT_AS``, and no input file changed (hash before and after). A refusal must
name the file it refuses.

Used by ``tests/test_fuzz.py`` (a small seeded campaign, ~30 s) and ``bench/bench_faults.py``
(a bigger one).
"""

from eol_cal.sim.fuzz.campaign import ROOT, Outcome, Tally, campaign, judge, run_batch, run_case, run_cli
from eol_cal.sim.fuzz.mutate import (
    CHILD_MEMORY_BYTES,
    KINDS,
    MUTATORS,
    SUFFIX,
    Case,
    base_files,
    cases,
    mdf4_blocks,
    mutate_block,
    mutate_csv,
    mutate_fitjson,
    mutate_mdf4,
)

__all__ = ["CHILD_MEMORY_BYTES", "KINDS", "MUTATORS", "ROOT", "SUFFIX", "Case", "Outcome", "Tally", "base_files",
           "campaign", "cases", "judge", "mdf4_blocks", "mutate_block", "mutate_csv", "mutate_fitjson", "mutate_mdf4",
           "run_batch", "run_case", "run_cli"]
