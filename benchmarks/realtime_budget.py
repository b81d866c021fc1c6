"""The kernel's real-time throttling and the rest before an episode: does a busy set-up at
real-time priority stall the first ticks after it, and does the rest prevent it?

    sudo python benchmarks/realtime_budget.py --rt-priority 50 --trials 30

What a real-time run does before episode 0, reduced to its timing (no JAX, no MuJoCo): on the
first CPU at ``SCHED_FIFO``, a busy stretch (the step's compilation before episode 0: seconds of
CPU) of a seeded random length, then the lead and ticks at 1 kHz on the wall clock
(:class:`~hec_jax.realtime.clock.WallClock`: sleep, spin the last 200 us), each tick busy for
``--work-us``. Trials alternate two arms: the rest before the lead
(:func:`~hec_jax.realtime.clock.rt_budget_rest_s`, as :func:`~hec_jax.realtime.runner.run_loop`
does by default) and none (``RealtimeConfig.rt_budget_rest`` False). Per trial: the latest
wake-up of a tick after its time. The kernel stops a CPU's real-time threads for the rest of a
period once they ran ``sched_rt_runtime_us`` of it; a trial counts as stalled when a tick woke
over ``--stall-ms`` late. Writes ``metrics.json`` and ``table.md`` in ``--out``.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hec_jax.cli import command, parse, require
from hec_jax.realtime.clock import (
    RT_PERIOD_FILE,
    RT_RUNTIME_FILE,
    WallClock,
    monotonic_s,
    realtime_refused,
    rt_budget_rest_s,
)
from hec_jax.runs import run_folder, write_json, write_text


@dataclass(frozen=True)
class BudgetProbe:
    """The probe's trials and where it writes."""

    trials: int = 30  # per arm (alternated)
    rt_priority: int = 50  # SCHED_FIFO priority of the probe (root)
    busy_min_s: float = 1.0  # [s] shortest busy stretch before the lead
    busy_max_s: float = 2.0  # [s] longest
    lead_ms: float = 20.0  # [ms] as RealtimeConfig.lead_ms (busy: the dry ticks)
    ticks: int = 150  # ticks after the lead
    work_us: float = 300.0  # [us] busy per tick (the 2-core VM's tick is 160-400 us)
    stall_ms: float = 5.0  # [ms] a wake-up this late counts as a stall
    seed: int = 0  # of the busy stretches' lengths
    out: Path = Path("runs/realtime_budget")  # run folder
    overwrite: bool = False  # replace an existing non-empty out

    def __post_init__(self):
        require(self, "count", "trials", "ticks", "rt_priority")
        require(self, "positive", "busy_min_s", "busy_max_s", "lead_ms", "stall_ms")
        require(self, "non_negative", "work_us", "seed")
        if self.busy_max_s < self.busy_min_s:
            raise ValueError("--busy-max-s must be >= --busy-min-s")
        refused = realtime_refused(self.rt_priority)
        if refused:
            raise ValueError(refused)


def _busy(seconds: float) -> None:
    end = monotonic_s() + seconds
    while monotonic_s() < end:
        pass


def _trial(a: BudgetProbe, busy_s: float, rest: bool) -> dict:
    """One set-up and start: the busy stretch, the rest (or none), the lead, the ticks."""
    _busy(busy_s)
    rest_s = rt_budget_rest_s() if rest else 0.0
    if rest_s > 0:
        time.sleep(rest_s)
    clock = WallClock()
    clock.start(a.lead_ms * 1e-3)
    while clock.now() < -1.5e-3:  # the dry ticks of the lead: busy
        pass
    late = np.empty(a.ticks)
    for j in range(a.ticks):
        late[j] = clock.wait_until(j * 1e-3) - j * 1e-3
        _busy(a.work_us * 1e-6)
    return {"busy_s": busy_s, "rest_s": rest_s, "max_late_ms": float(late.max() * 1e3)}


@command
def main(argv=None) -> dict:
    """Parses ``argv``, runs the alternated trials, prints and writes the table."""
    a = parse(BudgetProbe(), argv, __doc__)
    rng = np.random.default_rng(a.seed)
    busy = rng.uniform(a.busy_min_s, a.busy_max_s, a.trials)
    with open(RT_PERIOD_FILE) as f, open(RT_RUNTIME_FILE) as g:
        kernel = {"sched_rt_period_us": int(f.read()), "sched_rt_runtime_us": int(g.read())}
    settings = {"probe": a.__dict__ | {"out": str(a.out)}, "kernel": kernel}
    with run_folder(a.out, a.seed, settings, a.overwrite) as folder:
        old_cpus = os.sched_getaffinity(0)
        old = (os.sched_getscheduler(0), os.sched_getparam(0))
        os.sched_setaffinity(0, {min(old_cpus)})
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(a.rt_priority))
        rows = {"rest": [], "no rest": []}
        try:
            for i in range(a.trials):
                for arm in ("rest", "no rest") if i % 2 == 0 else ("no rest", "rest"):
                    rows[arm].append(_trial(a, float(busy[i]), arm == "rest"))
        finally:
            os.sched_setscheduler(0, *old)
            os.sched_setaffinity(0, old_cpus)
        table = {}
        for arm, r in rows.items():
            late = np.array([x["max_late_ms"] for x in r])
            table[arm] = {
                "trials": len(r),
                "stalled": int(np.sum(late > a.stall_ms)),
                "max_late_ms_p50": float(np.median(late)),
                "max_late_ms_max": float(late.max()),
                "rest_ms": 1e3 * r[0]["rest_s"],
            }
        write_json(folder / "metrics.json", {"kernel": kernel, "table": table, "trials": rows})
        lines = [
            f"kernel: {kernel}",
            "| arm | trials | stalled (a tick > "
            f"{a.stall_ms:g} ms late) | worst wake-up p50 [ms] | max [ms] | rest [ms] |",
            "|---|---|---|---|---|---|",
        ]
        for arm, t in table.items():
            lines.append(
                f"| {arm} | {t['trials']} | {t['stalled']} | {t['max_late_ms_p50']:.3f} |"
                f" {t['max_late_ms_max']:.1f} | {t['rest_ms']:.0f} |"
            )
        write_text(folder / "table.md", "\n".join(lines) + "\n")
        print("\n".join(lines))
        return table


if __name__ == "__main__":
    main()
