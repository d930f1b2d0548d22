"""The operator panel in the browser (``eol-cal station --panel``) and the line view (``eol-cal line``).

:mod:`state` (what the panel shows, fed by the cycle's events), :mod:`controls` (the operator's
actions, checked as the terminal loop checks them), :mod:`app` (the ASGI applications and their
pages in ``pages/``), :mod:`serve` (where a panel listens, credentials, one panel per station),
:mod:`line` (the line view's figures from the records database). docs/station.md, "The operator
panel" and "The line view", says how to run them and the security model.
"""
