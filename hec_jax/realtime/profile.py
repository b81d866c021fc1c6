"""Pieces of the tick profiler ``benchmarks/realtime_profile.py``: a clock that idles before
each tick as the wall clock does, and the per-stage CPU table of a run's tick records.
"""

from __future__ import annotations

import time

import numpy as np

from hec_jax.realtime.clock import FreeClock

STAGES = ("cpu_read", "cpu_observe", "cpu_step", "cpu_write")


class IdleClock(FreeClock):
    """:class:`~hec_jax.realtime.clock.FreeClock`'s time (every torque on time) with a real
    wait of ``idle_s`` before each tick: sleep, then spin the last ``spin_s``.
    """

    def __init__(self, idle_s: float, spin_s: float):
        super().__init__()
        self.idle_s, self.spin_s = idle_s, min(spin_s, idle_s)

    def wait_until(self, t: float) -> float:
        """Waits ``idle_s`` of wall time, then sets the time to ``t`` [s] and returns it."""
        end = time.perf_counter() + self.idle_s
        if self.idle_s - self.spin_s > 0:
            time.sleep(self.idle_s - self.spin_s)
        while time.perf_counter() < end:
            pass
        return super().wait_until(t)


def stage_table(ticks: list[dict]) -> dict[str, dict[str, float]]:
    """{stage: {"min", "p50", "p90", "p99"} [us]} of the per-tick records (the first 50 ticks
    of each episode dropped: warm-up), with ``tick`` (the sum of the stages), ``other_threads``
    [us] (mean) and the context switches per tick (``switches_voluntary``,
    ``switches_involuntary``: mean).
    """
    rec = {k: np.concatenate([r[k][50:] for r in ticks]) for k in ticks[0]}
    ok = np.isfinite(rec["cpu_step"])
    out = {}
    cols = {k[4:]: rec[k][ok] for k in STAGES}
    cols["tick"] = sum(cols.values())
    for name, v in cols.items():
        q = np.percentile(v, [50, 90, 99]) * 1e-3
        out[name] = {"min": float(v.min() * 1e-3), "p50": q[0], "p90": q[1], "p99": q[2]}
    out["other_threads"] = {"mean": float(np.mean(rec["cpu_other_threads"][ok]) * 1e-3)}
    for k in ("switches_voluntary", "switches_involuntary"):
        out[k] = {"mean": float(np.mean(rec[k][ok]))}
    return out
