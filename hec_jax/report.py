"""Tables and timings for the benchmark scripts (NumPy boundary; nothing here is jitted).

Timing rules used by the scripts: a jitted function is called once to compile before it is timed,
every timed call blocks until its outputs are ready, and per-call wall times come back as an
array so that a script reports their mean or minimum as it says.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import TypeVar

import numpy as np

from hec_jax.runs import cpu_model  # noqa: F401  (the scripts' tables read it from here)

T = TypeVar("T")


def fmt(x, spec: str = "{:.3g}") -> str:
    """``spec.format(x)``, or "-" for None (a quantity a method does not give)."""
    return "-" if x is None else spec.format(x)


def markdown_table(header: Sequence[str], rows: Sequence[Sequence]) -> list[str]:
    """Lines of a Markdown table; cells are turned into text with ``str``.

    Raises:
        ValueError: a row has another number of cells than the header.
    """
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for row in rows:
        if len(row) != len(header):
            raise ValueError(f"row {row!r} has {len(row)} cells, the header {len(header)}")
        lines.append("| " + " | ".join(str(c) for c in row) + " |")
    return lines


def metrics_table(metrics: dict[str, dict]) -> list[str]:
    """Lines of a Markdown table "| quantity | value |" of {part: {name: value}}: one row
    "part: name" per value, numbers to 4 significant digits, strings and dicts as they print.
    """
    rows = [
        (f"{part}: {key}", val if isinstance(val, (dict, str)) else f"{val:.4g}")
        for part, d in metrics.items()
        for key, val in d.items()
    ]
    return markdown_table(["quantity", "value"], rows)


def error_table(groups: dict[str, dict[str, dict]], group_header: str) -> list[str]:
    """Lines of a Markdown table of error summaries (``hec_jax.geometry.accuracy.error_summary``),
    one row per group and method: rotation median and p90 [deg], translation median and p90 [mm]
    ("-" where a method gives none), failure rate.

    Args:
        groups: {group label: {method: error summary}}, e.g. per noise level.
        group_header: the first column's header, e.g. "noise [px]".
    """
    keys = (
        "rotation_median_deg",
        "rotation_p90_deg",
        "translation_median_mm",
        "translation_p90_mm",
    )
    header = [group_header, "method", "rot median", "rot p90", "trans median", "trans p90"]
    rows = [
        [group, name, *(fmt(m[k]) for k in keys), f"{m['failure_rate']:.1%}"]
        for group, per_method in groups.items()
        for name, m in per_method.items()
    ]
    return markdown_table([*header, "failures"], rows)


def timed(fn: Callable[[], T]) -> tuple[T, float]:
    """``(fn(), wall time of the call [s])``."""
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


def call_times(fn: Callable[[], object], repeats: int) -> np.ndarray:
    """Wall time [s] of each of ``repeats`` calls of ``fn`` (which must block until done)."""
    out = np.empty(repeats)
    for i in range(repeats):
        t0 = time.perf_counter()
        fn()
        out[i] = time.perf_counter() - t0
    return out


def batched_us_per_item(f, host_args: Sequence[np.ndarray], transfer: bool = False) -> dict:
    """Per-item time [us] of a jitted batched function ``f(*args)``: the minimum of 3 calls on
    inputs already on the device, after one call that compiles. The batch is the leading axis of
    the first argument.

    With ``transfer``, also ``with_transfer_us_per_problem``: from the host arrays to all outputs
    back on the host (minimum of 3).
    """
    import jax
    import jax.numpy as jnp

    batch = len(host_args[0])
    dev = [jnp.asarray(a) for a in host_args]
    jax.block_until_ready(f(*dev))
    out = {"us_per_problem": call_times(lambda: jax.block_until_ready(f(*dev)), 3).min()}
    if transfer:
        host = [np.asarray(a) for a in host_args]
        t = call_times(lambda: jax.tree.map(np.asarray, f(*map(jnp.asarray, host))), 3).min()
        out["with_transfer_us_per_problem"] = t
    return {k: float(v) / batch * 1e6 for k, v in out.items()}


def tile_batch(x: np.ndarray, batch: int) -> np.ndarray:
    """``x`` (n, ...) repeated along its leading axis and cut to ``batch`` rows."""
    x = np.asarray(x)
    return np.resize(x, (batch, *x.shape[1:]))


class CompileMeter:
    """JAX's tracing, lowering and compiling in this process, summed from ``jax.monitoring``'s
    duration events (``/jax/core/compile/...``; the backend's compile includes a load from the
    persistent cache) since :meth:`install`: ``ms`` [ms] of all of them, ``events`` (a program
    compiled on first use gives three: its trace, its lowering and the backend's compile),
    ``compilations`` (the backend's compiles alone: programs compiled) and ``last_name``, the
    function of the last event. A timed caller reads them around what it times: a function
    traced or compiled on first use shows there (the real-time eye's ``jax_compile_ms`` per
    frame; the randomized eye benchmark's compilations while its timed sequences run).
    """

    def __init__(self) -> None:
        self.ms, self.events, self.compilations, self.last_name = 0.0, 0, 0, ""

    def _on_duration(self, event: str, duration_s: float, **kwargs) -> None:
        if event.startswith("/jax/core/compile/"):
            self.ms += 1e3 * float(duration_s)
            self.events += 1
            self.compilations += event == "/jax/core/compile/backend_compile_duration"
            self.last_name = str(kwargs.get("fun_name", ""))

    def install(self) -> CompileMeter:
        """Register with ``jax.monitoring`` (once per meter); returns self."""
        import jax.monitoring

        jax.monitoring.register_event_duration_secs_listener(self._on_duration)
        return self

    def uninstall(self) -> None:
        """Unregister from ``jax.monitoring`` (the counts stay)."""
        import jax.monitoring

        jax.monitoring.unregister_event_duration_listener(self._on_duration)
