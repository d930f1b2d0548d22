"""Flashing the parameter block over CAN (UDS on ISO-TP) and the ECU simulator.

Modules: :mod:`.protocol` (contract constants and codecs), :mod:`.transport` (python-can and
can-isotp), :mod:`.client` (the programming sequence), :mod:`.flash` (NOR banks in a file),
:mod:`.sim` (the UDS server and its faults), :mod:`.remote` (serving over python-can-remote).
Import the submodules; this package imports nothing heavy.
"""
