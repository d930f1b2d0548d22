"""Every table of the records database, in one ``MetaData``: the runs, the frozen baselines of lot
statistics, the master gate's rules, and the one ``schema_version`` of them all.

One row per run in ``runs`` (columns in ``docs/records.md``): serial, variant, station, operator,
start/end times (UTC ISO 8601), verdict and reasons, k6, phase_k6, c6, the peak-to-peak ripple
before/after, capture paths and SHA-256, the calibrated block's CRC and sequence, tool and layout
versions, what lot statistics read besides (the limits in force as JSON text, the error step,
phase_c6, the fit's R^2 and RMS, the run's kind and its failure causes), and last the fit record
and the whole record as JSON (:func:`eol_cal.records.rows.row_values` maps a record to them).
``baselines`` and ``baseline_lines``: :mod:`eol_cal.lot.baseline`; ``gate_rules``:
:mod:`eol_cal.msa.rules`. Which columns came with which version, and how an older database is
brought up: :mod:`eol_cal.records.migrations`.
"""

from __future__ import annotations

import sqlalchemy as sa

from eol_cal.records.kinds import KINDS

metadata = sa.MetaData()
runs = sa.Table(
    "runs", metadata,
    sa.Column("run_id", sa.Text, primary_key=True),
    sa.Column("serial", sa.Text, nullable=False),
    sa.Column("variant", sa.Text),
    sa.Column("started_at", sa.Text, nullable=False),
    sa.Column("ended_at", sa.Text),
    sa.Column("verdict", sa.Text, sa.CheckConstraint("verdict IN ('pass', 'fail', 'error')"), nullable=False),
    sa.Column("reasons", sa.Text, nullable=False),
    sa.Column("k6", sa.Float),
    sa.Column("phase_k6", sa.Float),
    sa.Column("c6", sa.Float),
    sa.Column("pp_before_pct", sa.Float),
    sa.Column("pp_after_pct", sa.Float),
    sa.Column("improvement_pct", sa.Float),
    sa.Column("capture_before", sa.Text),
    sa.Column("sha256_before", sa.Text),
    sa.Column("capture_after", sa.Text),
    sa.Column("sha256_after", sa.Text),
    sa.Column("block_crc32", sa.Text),
    sa.Column("block_sequence", sa.Integer),
    sa.Column("tool_version", sa.Text),
    sa.Column("layout_version", sa.Integer),
    sa.Column("report_dir", sa.Text),
    # version 2
    sa.Column("station", sa.Text),
    sa.Column("operator", sa.Text),
    # version 3: what lot statistics need besides the values above, so they never parse record_json
    sa.Column("limits_json", sa.Text),
    sa.Column("error_step", sa.Text),
    sa.Column("phase_c6", sa.Float),
    sa.Column("fit_r2", sa.Float),
    sa.Column("fit_rms_nm", sa.Float),
    # version 4: the run's kind (lot statistics take production runs) and why it did not pass
    sa.Column("kind", sa.Text, sa.CheckConstraint(f"kind IN ({', '.join(repr(k) for k in KINDS)})")),
    sa.Column("causes", sa.Text),
    # the documents last: SQLite reads a row's columns in order, through the overflow pages of
    # the kB of JSON before them (a database created at version 3; a migrated one adds its new
    # columns after them)
    sa.Column("fit_json", sa.Text),
    sa.Column("record_json", sa.Text, nullable=False),
    sa.Index("runs_serial", "serial"),
    sa.Index("runs_started", "started_at"),
    sa.Index("runs_variant_station", "variant", "station"),
    sa.Index("runs_kind_serial", "kind", "serial"),
)

COLUMN_NAMES = tuple(c.name for c in runs.columns)

#: frozen baselines (``eol-cal lot baseline``): one row per baseline, its filters and ``min_n``
baselines = sa.Table(
    "baselines", metadata,
    sa.Column("name", sa.Text, primary_key=True),
    sa.Column("created_at", sa.Text, nullable=False),
    sa.Column("since", sa.Text),
    sa.Column("until", sa.Text),
    sa.Column("variant", sa.Text),
    sa.Column("station", sa.Text),
    sa.Column("min_n", sa.Integer, nullable=False),
    sa.Column("runs", sa.Integer, nullable=False),
    sa.Column("tool_version", sa.Text),
    # the baselines' layout 2: the kind of the runs and every station chosen (a JSON list; station: the one, if one)
    sa.Column("kind", sa.Text),
    sa.Column("stations", sa.Text),
)
#: one row per baseline, quantity, variant and station: n, centre, sigma, MRbar (stored units), or why none
baseline_lines = sa.Table(
    "baseline_lines", metadata,
    sa.Column("name", sa.Text, sa.ForeignKey("baselines.name", ondelete="CASCADE"), primary_key=True),
    sa.Column("quantity", sa.Text, primary_key=True),
    sa.Column("variant", sa.Text, primary_key=True),
    sa.Column("station", sa.Text, primary_key=True),
    sa.Column("circular", sa.Boolean, nullable=False),
    sa.Column("n", sa.Integer, nullable=False),
    sa.Column("center", sa.Float),
    sa.Column("sigma", sa.Float),
    sa.Column("mr_center", sa.Float),
    sa.Column("reason", sa.Text),
)
#: the master gate's rules per station, each change a row (``seq`` 1, 2, ... per station), never changed
gate_rules = sa.Table(
    "gate_rules", metadata,
    sa.Column("station", sa.Text, primary_key=True),
    sa.Column("seq", sa.Integer, primary_key=True),
    sa.Column("set_at", sa.Text, nullable=False),
    sa.Column("set_by", sa.Text),
    sa.Column("action", sa.Text, sa.CheckConstraint("action IN ('set', 'clear')"), nullable=False),
    sa.Column("rules_json", sa.Text),
    sa.Column("note", sa.Text),
    sa.Column("tool_version", sa.Text),
)
#: the layout of every table above (one row; :data:`eol_cal.records.migrations.SCHEMA_VERSION`)
schema_version = sa.Table("schema_version", metadata, sa.Column("version", sa.Integer, nullable=False))
