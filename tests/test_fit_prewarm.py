"""The fit's pre-warming (eol_cal.analysis.fit.prewarm): what it traces while the dyno turns is
what the capture's fit then asks for, so the first fit of an `eol-cal run` process traces nothing."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# In a fresh interpreter: the solvers this process has traced are its own (no other test's).
# The "capture" is the profile's segments drawn anew (other noise, other parameters): what the
# station's fit sees after the pre-warming; every solver build after the pre-warming is counted.
_SCRIPT = r"""
import dataclasses, json, sys
import numpy as np
from eol_cal.analysis.fit import FitSpec, fit_many, solver
from eol_cal.analysis.fit.model_check import check_model
from eol_cal.analysis.fit.prewarm import prewarm_fit
from eol_cal.analysis.fit.synth import synthetic_segments
from eol_cal.dyno.setpoints import setpoints_from_profile
from eol_cal.plant.profile import load_profile

points = [(s.speed_rpm, s.iq) for s in setpoints_from_profile(load_profile("eol-default"))]
if sys.argv[1] == "points":
    prewarm_fit(len(points), None, False, points)
else:
    prewarm_fit(len(points), None, False)
built = []
build = solver.build_solver
solver.build_solver = lambda spec, S: built.append(S) or build(spec, S)
loads = sorted({i for _w, i in points})
speeds = sorted({abs(w) for w, _i in points})
grid = [(d, w, i) for d in (1, -1) for w in speeds for i in loads]
seg, _ = synthetic_segments(np.random.default_rng(7), k6=0.0007, c6=0.003, loads_a=tuple(loads),
                            speeds_rpm=tuple(speeds), directions=(1, -1), seg_s=0.12, fs_hz=10000.0)
keep = [grid.index((1 if w >= 0 else -1, abs(w), i)) for w, i in points]
seg = dataclasses.replace(seg, **{f.name: [v[k] for k in keep] if isinstance(v, list) else v[keep]
                                  for f in dataclasses.fields(seg)
                                  if isinstance(v := getattr(seg, f.name), (list, np.ndarray))})
(fit,) = fit_many([seg], FitSpec(), mode="loop")
check = check_model(seg, fit, FitSpec(), 0.05)
print(json.dumps({"built": built, "status": check.status, "segments": seg.n_segments}))
"""


def _builds(mode: str) -> dict:
    out = subprocess.run([sys.executable, "-c", _SCRIPT, mode], cwd=ROOT, capture_output=True, text=True, timeout=600,
                         env=dict(os.environ, EOL_CAL_JAX_CACHE="off"))
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.slow  # two fresh interpreters that import JAX and trace the solvers: ~20 s
def test_after_the_prewarm_on_the_profiles_points_the_fit_and_its_model_check_trace_nothing():
    got = _builds("points")
    assert got["segments"] == 8 and got["status"] != "not checked"  # the bands were fitted
    assert got["built"] == []
    # without the profile's points the model check's band solver is traced by the fit (what an
    # `eol-cal run` process paid in its fit step): the count above can see a build
    assert _builds("grid")["built"] != []


_CACHED = r"""
import json, sys
import numpy as np
from eol_cal.analysis.fit import FitSpec, fit_many, solver
from eol_cal.analysis.fit.model_check import check_model
from eol_cal.analysis.fit.synth import synthetic_segments

built = []
build = solver.build_solver
solver.build_solver = lambda spec, S: built.append(S) or build(spec, S)
seg, _ = synthetic_segments(np.random.default_rng(int(sys.argv[2])), k6=0.0007, c6=0.003, loads_a=(20.0, 40.0),
                            speeds_rpm=(60.0, 120.0), directions=(1,), seg_s=0.12, fs_hz=10000.0)
(fit,) = fit_many([seg], FitSpec(), mode="loop", cache_dir=sys.argv[1])
check = check_model(seg, fit, FitSpec(), 0.05, cache_dir=sys.argv[1])
print(json.dumps({"built": built, "status": check.status}))
"""


@pytest.mark.slow  # two fresh interpreters that import JAX and trace or load the solvers: ~20 s
def test_the_model_checks_band_solver_is_kept_in_the_fits_cache_between_processes(tmp_path):
    """``eol-cal fit`` (no pre-warming) traced the speed bands' solver in every process: with the
    fit's cache directory the second process, another capture, builds neither solver."""
    def run(seed: int) -> dict:
        out = subprocess.run([sys.executable, "-c", _CACHED, str(tmp_path), str(seed)], cwd=ROOT, capture_output=True,
                             text=True, timeout=600, env=dict(os.environ, EOL_CAL_JAX_CACHE="off"))
        assert out.returncode == 0, out.stderr[-3000:]
        return json.loads(out.stdout.strip().splitlines()[-1])

    first = run(1)
    assert first["status"] != "not checked" and len(first["built"]) == 2  # the joint fit's and the bands'
    second = run(2)
    assert second["status"] != "not checked" and second["built"] == []
