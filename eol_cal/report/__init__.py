"""Pages people look at: the per-motor report and the lot page, each one self-contained HTML file.

Plots are matplotlib figures written as inline SVG (:mod:`eol_cal.report.svg`), pages are
Jinja2 templates shipped in ``eol_cal/report/templates``; nothing on a page refers to a file
beside it or to the network, so a page can be mailed, archived with the motor and opened from
``file://``. The same inputs give the same bytes (no generation time, fixed SVG ids).
"""
