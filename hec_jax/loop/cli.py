"""The task scripts' command line: a preset's fields as flags, one run folder per call."""

from __future__ import annotations

import dataclasses
import sys
from dataclasses import dataclass, field
from pathlib import Path

from hec_jax.cli import command, parse
from hec_jax.loop.config import (
    DEFECT_FIELDS,
    PRESETS,
    CameraConfig,
    ExperimentConfig,
)
from hec_jax.loop.sweep import SweepConfig


@dataclass(frozen=True)
class TaskRun:
    """A task experiment and where it writes its run folder."""

    experiment: ExperimentConfig = field(default_factory=ExperimentConfig)
    out: Path = Path("runs/experiment")  # run folder (written complete or not at all)
    overwrite: bool = False  # replace an existing non-empty --out (else refused up front)
    float32: bool = False  # float32 (default float64, as every number in the docs)
    # run on the wall clock (``hec_jax.realtime``, its default settings, one seed: the 1 kHz
    # controller + learner, camera and eye in their own processes, and the same run in simulated
    # time beside it; every real-time setting is a flag of experiments/realtime.py)
    realtime: bool = False

    def __post_init__(self):
        if self.realtime and self.experiment.eye == "paper":
            raise ValueError(
                "--realtime runs --eye truth or camera (the paper's eye: simulated time)"
            )
        refused = self.experiment.camera.realtime_refused() if self.realtime else None
        if refused:
            raise ValueError(refused)


def task_default(preset: str, argv=None) -> TaskRun:
    """The named preset as the flags' defaults; with ``--realtime`` in ``argv`` (default:
    ``sys.argv[1:]``) its camera is ``CameraConfig.void_perfect()``, real time's default (its
    camera has no defects; the void scene is the one software rendering keeps up with).
    """
    experiment = PRESETS[preset]()
    if "--realtime" in (sys.argv[1:] if argv is None else argv):
        experiment = dataclasses.replace(experiment, camera=CameraConfig.void_perfect())
    return TaskRun(experiment=experiment, out=Path(f"runs/{preset}"))


def given_defect_fields(argv) -> tuple[str, ...]:
    """The ``CameraDefects`` fields whose flag is in ``argv`` (``--focal-error 0``,
    ``--focal_error=0``, a prefixed ``--experiment.camera.defects.focal-error``), in field order.
    """
    named = set()
    for arg in argv:
        if arg.startswith("--"):
            named.add(arg[2:].split("=", 1)[0].rsplit(".", 1)[-1].replace("-", "_"))
    return tuple(name for name in DEFECT_FIELDS if name in named)


def parse_task(preset: str, argv=None, doc: str | None = None) -> TaskRun:
    """``argv`` (default: ``sys.argv[1:]``) over the named preset, with the camera's defect
    flags given on it recorded in ``CameraConfig.defects_given``: under the industrial camera a
    flag given at the perfect camera's value (``--focal-error 0``) turns that defect off rather
    than reading as unset.
    """
    args = sys.argv[1:] if argv is None else list(argv)
    run = parse(task_default(preset, args), args, doc)
    given = given_defect_fields(args)
    if not given:
        return run
    camera = dataclasses.replace(run.experiment.camera, defects_given=given)
    return dataclasses.replace(run, experiment=dataclasses.replace(run.experiment, camera=camera))


@command
def main_for(preset: str, doc: str | None = None, argv=None) -> dict:
    """Parses ``argv`` over the named preset, runs the experiment and writes its run folder.

    Returns the metrics. Bad arguments (a used ``--out`` included) end in one line and exit
    code 2 before anything is compiled; Ctrl-C or SIGTERM in a failed run folder and exit code
    130 or 143 (:func:`hec_jax.cli.command`).
    """
    run = parse_task(preset, argv, doc)
    import jax

    jax.config.update("jax_enable_x64", not run.float32)
    if run.realtime:  # the jitted call on the calling thread, as experiments/realtime.py does
        jax.config.update("jax_cpu_enable_async_dispatch", False)  # (docs/realtime.md)
    from hec_jax.loop.experiment import run_experiment
    from hec_jax.loop.report import print_summary, write_experiment
    from hec_jax.runs import run_folder

    exp = run.experiment
    settings = dict(
        experiment=dataclasses.asdict(dataclasses.replace(exp, camera=exp.camera.resolved())),
        preset=preset,
        out=str(run.out),
        float32=run.float32,
        argv_given=None if argv is None else list(argv),
    )
    if run.realtime:
        from hec_jax.realtime import print_report, run_realtime, write_report

        with run_folder(run.out, exp.seed, dict(settings, realtime=True), run.overwrite) as folder:
            rt_result = run_realtime(exp)
            write_report(folder, rt_result)
        print(f"run folder: {run.out}")
        print_report(rt_result)
        return rt_result.report
    with run_folder(run.out, exp.seed, settings, run.overwrite) as folder:
        result = run_experiment(exp)
        write_experiment(folder, result)
    print(f"run folder: {run.out}")
    print_summary(result)
    return result.metrics


@dataclass(frozen=True)
class SweepRun:
    """A sweep and where its folder is; which shard this process computes."""

    sweep: SweepConfig = field(default_factory=SweepConfig)
    out: Path = Path("runs/sweep")  # sweep folder (chunks/, shard_*/, metrics.json)
    shard_index: int = 0  # this process takes every num_shards-th chunk from here
    num_shards: int = 1
    merge_only: bool = False  # only merge the chunk files that exist

    def __post_init__(self):
        if not 0 <= self.shard_index < self.num_shards:
            raise ValueError(
                f"need 0 <= shard_index < num_shards, got {self.shard_index}, {self.num_shards}"
            )


@command
def sweep_main(doc: str | None = None, argv=None) -> dict:
    """Parses ``argv`` into a :class:`SweepRun`, runs (or merges) the sweep; returns the merged
    metrics.
    """
    run = parse(SweepRun(), argv, doc)
    import jax

    jax.config.update("jax_enable_x64", not run.sweep.float32)
    from hec_jax.loop.sweep import merge, run_sweep
    from hec_jax.runs import enable_compile_cache

    enable_compile_cache()
    from hec_jax.cli import usage_error
    from hec_jax.loop.sweep import check_same_sweep

    try:  # a folder of another sweep: refused as a bad --out, before anything is compiled
        check_same_sweep(run.out / "chunks", run.sweep)
    except SystemExit as e:
        raise usage_error(str(e.code)) from None
    if run.merge_only:
        return merge(run.out, run.sweep)
    given = {"argv_given": None if argv is None else list(argv)}
    return run_sweep(run.sweep, run.out, run.shard_index, run.num_shards, given)


def catching_main() -> None:
    """Console entry point ``hec-catching`` (``experiments/catching.py``)."""
    main_for("catching", "Catching (Sec. 6.2, Fig. 6): the catching preset's fields as flags.")


def hitting_main() -> None:
    """Console entry point ``hec-hitting`` (``experiments/hitting.py``)."""
    main_for("hitting", "Hitting (Sec. 6.3, Fig. 7): the hitting preset's fields as flags.")


def sweep_entry() -> None:
    """Console entry point ``hec-sweep`` (``experiments/sweep.py``)."""
    sweep_main("Catching over a grid of pendulum conditions and seeds (resumable, shardable).")
