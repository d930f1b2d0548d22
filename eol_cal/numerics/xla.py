"""One process-wide XLA option: the CPU backend compiles a small-enough ``while`` loop into a
single kernel, and the tick loops of this package (the plant's, the firmware estimator's) are
small enough once the threshold is raised."""

from __future__ import annotations

import os
import sys

#: XLA CPU compiles a while loop into one kernel when the bytes it accesses stay below this
#: backend option (default 1024); above it, every fused kernel of the body is dispatched on its
#: own and the tick's ~80 kernels cost ~4 us per iteration instead of ~0.5 us.
_LOOP_OPTION = "xla_cpu_small_while_loop_byte_threshold"
_LOOP_BYTES = 1 << 28


def configure_xla() -> bool:
    """Let XLA compile tick loops (the plant's, the firmware estimator's) into a single kernel
    (about 8x faster on CPU).

    Adds ``--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=2**28`` to
    ``XLA_FLAGS``. XLA reads its flags once, when JAX's backend starts, so this must run before
    the process's first JAX computation; it returns False (and changes nothing) when that has
    happened already or when ``XLA_FLAGS`` sets backend options of its own. The option applies
    to every ``while`` loop of the process without custom calls (LAPACK, ...): call it from
    entry points that mostly simulate or refit (the CLI, benchmarks, a refit worker:
    :func:`eol_cal.lot.cluster.prepare_fit_process`) and from the fit's and the station's (`eol-cal fit`,
    `eol-cal run`, `eol-cal station` without its in-process simulators), not from library code. The plant's tick
    loops give results within float32 rounding of the default (XLA fuses the body differently: a
    layout-2 plant run's i_qc within 0.02 A, its i_q within 0.05 A rms, the identification the
    same, as tests/test_plant_identifying_loop.py checks); the firmware estimator's scan (the
    fit's frame) gives the same output bit for bit at a tenth of the CPU
    (tests/test_firmware_frame_chunk.py); the fit's solver loops hold LAPACK calls and are left
    as they are.
    """
    flags = os.environ.get("XLA_FLAGS", "")
    if _LOOP_OPTION in flags:
        return True
    if "xla_backend_extra_options" in flags:
        return False
    if "jax" in sys.modules:
        try:
            from jax._src import xla_bridge

            if xla_bridge.backends_are_initialized():
                return False
        except (ImportError, AttributeError):
            return False
    os.environ["XLA_FLAGS"] = f"{flags} --xla_backend_extra_options={_LOOP_OPTION}={_LOOP_BYTES}".strip()
    return True
