"""The machine's floor for a 1 kHz loop: how late do the real-time run's ticks wake, and how
often does a tick of fixed work end past its 1 ms deadline, with nothing of the project running?

    sudo python benchmarks/realtime_jitter.py --rt-priority 50 --cpu-latency-us 0 --duration-s 60

What :func:`~hec_jax.realtime.runner.run_loop`'s clock does, reduced to its timing (no JAX, no
MuJoCo, as cyclictest): on the first CPU at ``SCHED_FIFO`` (:class:`~hec_jax.realtime.clock.
realtime_priority`, :class:`~hec_jax.realtime.clock.pinned`), with the CPUs' wake-up latency
asked of the kernel (:class:`~hec_jax.realtime.clock.cpu_latency_request`), ticks at 1 kHz on the
wall clock (:class:`~hec_jax.realtime.clock.WallClock`: sleep, then spin the last ``--spin-us``),
each doing ``--work-us`` of work (a control tick's CPU time, as a run's deadline report gives
it): a busy wait (``--work spin``: a fixed time, so only the scheduling shows), or a fixed
number of passes over a working set (``--work memory``: as many as take ``--work-us`` on the quiet
machine, so their time shows what the machine does to a tick whose data should stay in its
caches). Two arms alternate in blocks of ``--block-s``: the other CPUs idle, and the other CPUs
each loaded by a process at normal priority (``--load``: a busy loop, or a stream through
memory; as the camera and the eye load the second CPU). Per arm: the wake-up lateness (the
tick's start after its time) and the tick's end after its time, percentiles and the share past
1 ms (a missed deadline), and the host's steal per CPU over the arm's blocks. A deadline missed
here is the machine's, not the loop's: the loop's own work is fixed. Writes ``metrics.json``
and ``table.md`` in ``--out``.
"""

from __future__ import annotations

import os
import signal
import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from hec_jax.cli import command, parse, require, usage_error
from hec_jax.realtime.clock import (
    WallClock,
    cpu_latency_refused,
    cpu_latency_request,
    filler_command,
    host_steal_ms,
    monotonic_s,
    pin_process,
    pinned,
    realtime_priority,
    realtime_refused,
)
from hec_jax.runs import run_folder, write_json, write_text

ARMS = ("others idle", "others busy")


@dataclass(frozen=True)
class JitterProbe:
    """The probe's ticks and where it writes."""

    duration_s: float = 60.0  # [s] per arm
    block_s: float = 10.0  # [s] of one arm before the other (alternated)
    rt_priority: int = 50  # SCHED_FIFO priority of the loop (root); 0: normal scheduling
    cpu_latency_us: int | None = 0  # the CPUs' wake-up latency asked (None: nothing asked)
    spin_us: float = 200.0  # [us] busy-wait before each tick (RealtimeConfig.spin_us)
    work_us: float = 270.0  # [us] of work per tick (a control tick's CPU time)
    # the tick's work: "spin" busy-waits work_us (a fixed time: only the scheduling shows);
    # "memory" makes the same number of passes over a working set of work_kib every tick, as
    # many as take work_us on the quiet machine (calibrated first), so its time shows what the
    # other CPUs' memory traffic does to a tick whose data must stay in the caches
    work: Literal["spin", "memory"] = "spin"
    work_kib: int = 512  # [KiB] the memory work's working set
    # the other CPUs' load in its arm: "spin" a busy loop (no memory traffic), "memory" a
    # stream through 256 MiB (a frame's worth of image work, without end): ``clock.IDLE_FILLERS``
    load: Literal["spin", "memory"] = "spin"
    out: Path = Path("runs/realtime_jitter")  # run folder
    overwrite: bool = False  # replace an existing non-empty out

    def __post_init__(self):
        require(self, "positive", "duration_s", "block_s")
        require(self, "non_negative", "spin_us", "work_us", "rt_priority")
        require(self, "count", "work_kib")
        if self.work_us >= 1000.0:
            raise ValueError("--work-us must be under the 1000 us period")
        if self.block_s > self.duration_s:
            raise ValueError("--block-s must be <= --duration-s")


def _busy_until(t_end: float) -> None:
    while monotonic_s() < t_end:
        pass


class _Work:
    """A tick's work: ``spin`` (busy until ``work_us`` after the wake-up) or ``memory``
    (``passes`` passes over ``work_kib`` of float64, calibrated to take ``work_us`` here).
    """

    def __init__(self, a: JitterProbe):
        self.a = a
        n = a.work_kib * 1024 // 16  # two arrays of float64
        self.x, self.y = np.ones(n), np.zeros(n)
        self.passes = 0
        if a.work == "memory":
            self.passes = 1
            while self._timed() < 0.5 * a.work_us * 1e-6:
                self.passes *= 2
            per_pass = np.median([self._timed() for _ in range(200)]) / self.passes
            self.passes = max(1, int(round(a.work_us * 1e-6 / per_pass)))

    def _timed(self) -> float:
        t0 = monotonic_s()
        self.do(t0)
        return monotonic_s() - t0

    def do(self, woke_s: float) -> None:
        """One tick's work after waking at ``woke_s`` (monotonic [s])."""
        if self.a.work == "spin":
            _busy_until(woke_s + self.a.work_us * 1e-6)
            return
        for _ in range(self.passes):
            np.add(self.x, self.y, out=self.y)


def _block(a: JitterProbe, work: _Work) -> tuple[np.ndarray, np.ndarray]:
    """One block of ticks: (wake-up lateness, end after the tick's time) [us] per tick."""
    n = int(round(a.block_s * 1e3))
    clock = WallClock(a.spin_us * 1e-6)
    clock.start(20e-3)
    wake, end = np.empty(n), np.empty(n)
    for j in range(n):
        t = j * 1e-3
        woke = clock.wait_until(t)
        work.do(clock.origin + woke)
        wake[j], end[j] = woke - t, clock.now() - t
    return wake * 1e6, end * 1e6


def _percentiles(x: np.ndarray) -> dict:
    p50, p99, p99_9 = np.percentile(x, (50, 99, 99.9))
    return {"p50": float(p50), "p99": float(p99), "p99_9": float(p99_9), "max": float(x.max())}


def _summary(wake: np.ndarray, end: np.ndarray, steal_ms: np.ndarray) -> dict:
    return {
        "ticks": int(len(end)),
        "wake_us": _percentiles(wake),
        "end_us": _percentiles(end),
        "past_deadline_share": float(np.mean(end > 1000.0)),
        "steal_ms_per_cpu": steal_ms.tolist(),
    }


@command
def main(argv=None) -> dict:
    """Parses ``argv``, runs the alternated blocks, prints and writes the table."""
    a = parse(JitterProbe(), argv, __doc__)
    # asked of the machine once the flags are read (the defaults' priority may be refused where
    # the flags ask for none)
    refused = realtime_refused(a.rt_priority) or cpu_latency_refused(a.cpu_latency_us)
    if refused:
        raise usage_error(refused)
    cpus = sorted(os.sched_getaffinity(0))
    if len(cpus) < 2:
        raise SystemExit("the probe needs two CPUs (the loop's and the others')")
    settings = {"probe": a.__dict__ | {"out": str(a.out)}, "cpus": cpus}
    blocks = int(np.ceil(a.duration_s / a.block_s))
    with run_folder(a.out, 0, settings, a.overwrite) as folder:
        # per arm, per block: wake-up lateness, tick end [us], the host's steal per CPU [ms]
        got = {arm: {"wake": [], "end": [], "steal": []} for arm in ARMS}
        # the load: one process per other CPU at normal priority, started before the
        # loop takes real-time priority (a child inherits it), stopped between its blocks
        load = [subprocess.Popen(filler_command(a.load)) for _ in cpus[1:]]
        try:
            for p, cpu in zip(load, cpus[1:], strict=True):
                pin_process(p.pid, {cpu})
                p.send_signal(signal.SIGSTOP)
            with pinned({cpus[0]}), realtime_priority(a.rt_priority):
                work = _Work(a)  # calibrated on the loop's CPU, the others idle
                with cpu_latency_request(a.cpu_latency_us):
                    for i in range(blocks):
                        for arm in ARMS if i % 2 == 0 else ARMS[::-1]:
                            busy = arm == "others busy"
                            for p in load if busy else ():
                                p.send_signal(signal.SIGCONT)
                            before = np.asarray(host_steal_ms())
                            wake, end = _block(a, work)
                            got[arm]["steal"].append(np.asarray(host_steal_ms()) - before)
                            for p in load if busy else ():
                                p.send_signal(signal.SIGSTOP)
                            got[arm]["wake"].append(wake)
                            got[arm]["end"].append(end)
        finally:
            for p in load:
                p.kill()
                p.wait()
        table = {
            arm: _summary(
                np.concatenate(g["wake"]), np.concatenate(g["end"]), np.sum(g["steal"], axis=0)
            )
            for arm, g in got.items()
        }
        write_json(folder / "metrics.json", {"table": table, "memory_passes": work.passes})
        lines = [
            f"{a.work_us:g} us of {a.work} work a tick ({a.work_kib} KiB) at 1 kHz on CPU"
            f" {cpus[0]}, SCHED_FIFO {a.rt_priority}, spin {a.spin_us:g} us, cpu latency"
            f" {a.cpu_latency_us} us; the others' load: {a.load}",
            "| arm | ticks | wake-up late p50 / p99 / p99.9 / max [us] | tick end p50 / p99.9 / "
            "max [us] | ends past 1 ms | host steal per CPU [ms] |",
            "|---|---|---|---|---|---|",
        ]
        for arm, t in table.items():
            w, e = t["wake_us"], t["end_us"]
            lines.append(
                f"| {arm} | {t['ticks']} | {w['p50']:.0f} / {w['p99']:.0f} / {w['p99_9']:.0f} /"
                f" {w['max']:.0f} | {e['p50']:.0f} / {e['p99_9']:.0f} / {e['max']:.0f} |"
                f" {100 * t['past_deadline_share']:.3f}% |"
                f" {' / '.join(f'{s:.0f}' for s in t['steal_ms_per_cpu'])} |"
            )
        write_text(folder / "table.md", "\n".join(lines) + "\n")
        print("\n".join(lines))
        return table


if __name__ == "__main__":
    main()
