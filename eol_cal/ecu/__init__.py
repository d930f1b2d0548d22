"""Flashing the parameter block over CAN (UDS on ISO-TP) and the ECU simulator.

Tester: :mod:`.protocol` (contract constants and codecs), :mod:`.transport` (python-can,
can-isotp, the guarded link), :mod:`.session` (the udsoncan session: step names, bounded waits,
retries), :mod:`.sequence` (the programming sequence), :mod:`.client` (keys, identification and
the entry points). Simulator: :mod:`.sim_ecu` (the UDS services), :mod:`.programming` (its boot
loader: erase, download, transfer, check), :mod:`.flash` (NOR banks and security memory in a
file), :mod:`.simconfig` (what it is, which faults it injects), :mod:`.remote` (serving over
python-can-remote). Import the submodules; this package imports nothing heavy.
"""
