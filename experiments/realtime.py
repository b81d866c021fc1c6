"""Catching or hitting in real time: the 1 kHz controller + learner on the wall clock, the camera
and the eye in their own processes, MuJoCo C physics stepping at 1 kHz behind a robot-driver
interface (``hec_jax.realtime``), and the same run in simulated time beside it.

    python experiments/realtime.py --preset catching --eye camera --camera-msaa 0 --duration-s 60 --rt-priority 50 --cpu-latency-us 0 --out runs/realtime-catching

Writes ``config.json``, ``deadline.json`` (tick latency p50/p99/p99.9/max and histogram, missed
1 ms deadlines, the eye's exposure-to-state latency and age, dropped frames, load average),
``metrics.json`` (the task's metrics in real time and in simulated time, their ratios),
``deadline_histogram.png``, ``ticks.npz`` (every tick's times: the report can be recomputed)
and ``trajectory_*.npz``; prints the deadline table. Every field of the preset and of
``hec_jax.realtime.RealtimeConfig`` is a flag (``--help``).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from hec_jax.cli import command, parse
from hec_jax.loop.config import (
    PRESETS,
    CameraConfig,
    ExperimentConfig,
)
from hec_jax.realtime.clock import cpu_latency_refused, pool_idle_refused, realtime_refused
from hec_jax.realtime.config import RealtimeConfig


@dataclass(frozen=True)
class RealtimeRun:
    """A task experiment in real time and where it writes its run folder."""

    preset: Literal["catching", "hitting"] = "catching"  # the experiment's defaults
    experiment: ExperimentConfig = field(default_factory=ExperimentConfig)
    realtime: RealtimeConfig = field(default_factory=RealtimeConfig)
    out: Path = Path("runs/realtime")  # run folder (written complete or not at all)
    overwrite: bool = False  # replace an existing non-empty --out
    float32: bool = False  # float32 (default float64, as the simulated runs)

    def __post_init__(self):
        refused = self.experiment.camera.realtime_refused()
        if refused:
            raise ValueError(refused)
        rt = self.realtime
        refused = realtime_refused(max(rt.rt_priority, rt.camera_priority, rt.eye_priority))
        if refused:
            raise ValueError(refused)
        refused = cpu_latency_refused(rt.cpu_latency_us if rt.timed else None)
        if refused:
            raise ValueError(refused)
        refused = pool_idle_refused(rt.pool_idle_applies)
        if refused:
            raise ValueError(refused)


@command
def main(argv=None) -> dict:
    """Parses ``argv``, runs the experiment in real time, writes the run folder; returns the
    deadline report.
    """
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--preset", choices=sorted(PRESETS), default="catching")
    preset = pre.parse_known_args(argv)[0].preset
    # the void scene without defects (``CameraConfig.void_perfect``); --scene lab renders the
    # lab with its shadows (a GPU renderer keeps up with 30 fps; software rendering does not)
    experiment = PRESETS[preset](camera=CameraConfig.void_perfect())
    default = RealtimeRun(preset=preset, experiment=experiment, out=Path(f"runs/realtime-{preset}"))
    run = parse(default, argv, __doc__)
    if run.preset != preset:
        raise SystemExit("--preset must be given once")
    import jax

    jax.config.update("jax_enable_x64", not run.float32)
    # the jitted control step runs on the calling thread (JAX's default on CPU hands every call
    # to a dispatch thread; per tick that is one more thread hand-off: docs/realtime.md). Read
    # when JAX creates its CPU client, so before anything is computed.
    jax.config.update("jax_cpu_enable_async_dispatch", False)
    from hec_jax.realtime import print_report, run_realtime, write_report
    from hec_jax.report import cpu_model
    from hec_jax.runs import enable_compile_cache, run_folder

    enable_compile_cache()
    settings = dict(
        preset=run.preset,
        experiment=dataclasses.asdict(
            dataclasses.replace(run.experiment, camera=run.experiment.camera.resolved())
        ),
        realtime=dataclasses.asdict(run.realtime),
        out=str(run.out),
        float32=run.float32,
        argv_given=None if argv is None else list(argv),
        cpu=cpu_model(),
        cpus=os.cpu_count(),
        load_average_at_start=os.getloadavg(),
    )
    with run_folder(run.out, run.experiment.seed, settings, run.overwrite) as folder:
        result = run_realtime(run.experiment, run.realtime)
        write_report(folder, result)
    print(f"run folder: {run.out}")
    print_report(result)
    return result.report


if __name__ == "__main__":  # (the camera's and the eye's processes are spawned: keep the guard)
    main()
