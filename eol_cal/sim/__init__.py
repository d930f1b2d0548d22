"""Everything that stands in for the plant floor, for CI, ``eol-cal demo``, the benchmarks and the
tests: the rig (the plant behind the simulated dyno, running the ECU simulator's active bank,
:mod:`.rig`), a whole station and a line on loopback (:mod:`.loopback`), the ECU simulator served
to other processes (:mod:`.remote_ecu`), a simulated ECU and a tester on one virtual CAN channel
(:mod:`.virtual_rig`), a throwaway PostgreSQL server (:mod:`.postgres`), realistic run records and
lots of them (:mod:`.run_records`, :mod:`.lot_records`), the plant motors of the mechanical-order
fit (:mod:`.mech_motors`), and hostile inputs and fault scenarios (:mod:`.fuzz`).

The simulators of the instruments themselves stay with their clients (:mod:`eol_cal.dyno.sim_dyno`,
:mod:`eol_cal.ecu.sim_ecu`, the plant :mod:`eol_cal.plant`). Nothing in the product imports this
package but the commands that serve a simulator (``eol-cal demo``, ``station --demo``, ``dyno-sim``,
``ecu-sim``): ``tests/test_imports.py`` checks it.
"""

from pathlib import Path

#: the source tree (the fault campaign runs its CLI there; fixtures are read from it)
ROOT = Path(__file__).resolve().parents[2]
#: the repository's fixture files (a real demo run record, limits, fit results)
FIXTURES = ROOT / "fixtures"
