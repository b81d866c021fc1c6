"""The paper protocol's command line and run folder (``experiments/paper.py``): one table per call
(arms x metrics over seeds x held-out pendulums), learning curves, Fig. 6/7-style panels.
"""

from __future__ import annotations

import dataclasses
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from hec_jax.cli import command, parse, usage_error
from hec_jax.loop.arms import PaperProtocol

PaperPreset = Literal["catching_paper", "hitting_paper"]


@dataclass(frozen=True)
class PaperRun:
    """A paper-protocol table and where its run folder goes.

    ``preset`` picks the preset (``catching_paper`` / ``hitting_paper``); every other field of the
    preset and the protocol is a flag; ``--reduced`` shrinks the protocol for a 2-core CPU
    (2 seeds, 4 training swings, 3 held-out pendulums, a 4 x 4 fixed-impedance grid, no BPTT).
    """

    preset: PaperPreset = "catching_paper"
    protocol: PaperProtocol = field(default_factory=PaperProtocol)
    reduced: bool = False
    out: Path = Path("runs/paper")  # run folder (written complete or not at all)
    overwrite: bool = False  # replace an existing non-empty --out
    float32: bool = False  # float32 (default float64)


def _reduced(p: PaperProtocol) -> PaperProtocol:
    from hec_jax.loop.config import replace

    return dataclasses.replace(
        p,
        experiment=replace(p.experiment, seeds=2, swings=4),
        held_out=3,
        fixed_grid=4,
        fixed_grid_m=1,
        fixed_search_pendulums=3,
        arms=tuple(a for a in p.arms if a != "bptt"),
    )


# the flags of what _reduced sets (tyro's names of those fields)
_REDUCED_FLAGS = (
    "--seeds",
    "--swings",
    "--held-out",
    "--fixed-grid",
    "--fixed-grid-m",
    "--fixed-search-pendulums",
    "--arms",
)


def default_run(preset: str) -> PaperRun:
    """The defaults of ``--preset preset``: that paper preset under the full protocol (hitting:
    each held-out run is the preset's continuous run, ``final_s``).
    """
    from hec_jax.loop.config import PRESETS

    if preset not in ("catching_paper", "hitting_paper"):
        raise usage_error(f"--preset must be catching_paper or hitting_paper, got {preset!r}")
    exp = PRESETS[preset]()
    protocol = PaperProtocol(experiment=exp)
    return PaperRun(preset=preset, protocol=protocol, out=Path(f"runs/{preset}"))


def _preset_in(argv: list[str]) -> str:
    for i, a in enumerate(argv):
        if a.startswith("--preset="):
            return a.split("=", 1)[1]
        if a == "--preset" and i + 1 < len(argv):
            return argv[i + 1]
    return "catching_paper"


@command
def paper_main(argv=None, doc: str | None = None) -> dict:
    """Parses ``argv`` over the defaults of its ``--preset`` (:func:`default_run`), runs the table
    and writes its run folder; returns the results (without logs).
    """
    args = list(sys.argv[1:] if argv is None else argv)
    default = default_run(_preset_in(args))
    run = parse(default, args, doc)
    if run.reduced:
        # --reduced sets these itself: a flag given for one of them would be silently dropped
        given = {a.split("=", 1)[0].replace("_", "-") for a in args if a.startswith("--")}
        clash = [f for f in _REDUCED_FLAGS if f in given]
        if clash:
            raise usage_error(
                f"--reduced sets {', '.join(clash)} itself; drop --reduced or those flags"
            )
    protocol = _reduced(run.protocol) if run.reduced else run.protocol
    if protocol.experiment.eye != "truth":
        raise usage_error(
            "--eye: the paper protocol runs with the simulator's object state (truth)"
        )
    import jax

    jax.config.update("jax_enable_x64", not run.float32)
    from hec_jax.loop.arms import markdown_table, run_arms, table_rows
    from hec_jax.runs import run_folder, write_json, write_text

    settings = dict(
        protocol=dataclasses.asdict(protocol),
        preset=run.preset,
        reduced=run.reduced,
        float32=run.float32,
        argv_given=args,
    )
    task = protocol.experiment.task.learner.task
    with run_folder(run.out, protocol.experiment.seed, settings, run.overwrite) as folder:
        results = run_arms(protocol, progress=lambda arm: print(f"arm {arm}: done", flush=True))
        logs = results.pop("logs")
        table = markdown_table(table_rows(results, task))
        write_text(folder / "table.md", table + "\n")
        write_json(folder / "metrics.json", results)
        if logs:
            _figures(folder, task, protocol, results, logs)
    print(table)
    print(f"run folder: {run.out}")
    return results


def _figures(folder: Path, task: str, protocol: PaperProtocol, results: dict, logs: dict) -> None:
    """Learning curves over training swings (per arm) and a Fig. 6/7-style panel of the online
    arm's first held-out run of seed 0 (force, positions, virtual impedance).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from hec_jax.runs import save_figure

    key = "relative_speed_at_contact" if task == "catching" else "max_pulse"
    fig, ax = plt.subplots(figsize=(6, 3.5))
    for arm, entry in results["arms"].items():
        curve = entry.get("learning_curve", {}).get(key)
        if curve:
            ax.plot(
                np.arange(1, len(curve) + 1),
                [np.nan if v is None else v for v in curve],
                "o-",
                label=arm,
            )
    ax.set_xlabel("training swing")
    ax.set_ylabel(key.replace("_", " "))
    ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, folder / "learning_curves.png")

    ev = {k: v[0, 0] for k, v in logs["eval"].items()}
    dt = 1e-3
    t = np.arange(ev["f_contact"].shape[0]) * dt
    fig, axes = plt.subplots(4, 1, figsize=(7, 8), sharex=True)
    axes[0].plot(t, np.linalg.norm(ev["f_contact"][:, [0, 2]], axis=-1), "k")
    f_d = protocol.experiment.task.learner.f_desired
    axes[0].axhline(f_d, color="r", ls="--", lw=0.8)
    axes[0].set_ylabel("|F_int| [N]")
    axes[1].plot(t, ev["x_e"][:, 0], label="hand x")
    axes[1].plot(t, ev["x_o_true"][:, 0], label="cube x")
    axes[1].set_ylabel("x [m]")
    axes[1].legend(fontsize=7)
    for i, name in enumerate(("k_o", "b_o")):
        axes[2 + i].plot(t, ev[name][:, 0], label=f"{name} x")
        axes[2 + i].plot(t, ev[name][:, 1], label=f"{name} z")
        axes[2 + i].legend(fontsize=7)
    axes[2].set_ylabel("K_o [N/m]")
    axes[3].set_ylabel("B_o [N s/m]")
    axes[3].set_xlabel("t [s]")
    fig.suptitle(f"{task}, paper preset, online arm: held-out pendulum 1, seed 0")
    fig.tight_layout()
    save_figure(fig, folder / f"fig_{task}_online.png")


# protocol fields that only the BPTT arm reads: runs of other arms may differ in them
_BPTT_FIELDS = ("bptt_epochs", "bptt_lr", "bptt_clip", "bptt_horizon_s")


def merge_runs(parts: list[tuple[dict, dict]]) -> dict:
    """One table's results from paper-protocol runs that each ran some of the arms (e.g. one
    process per group of arms, ``scripts/gpu_paper.sh``).

    Args:
        parts: (``config.json``, ``metrics.json``) of each run folder, as loaded.

    Returns:
        The merged ``metrics.json``: ``arms`` in :data:`~hec_jax.loop.arms.ALL_ARMS` order,
        ``pendulums`` (the runs'), ``fixed_search`` (from the run that ran a fixed arm, if any).

    Raises:
        ValueError: no parts; a run not complete; runs of another preset, precision, reduction or
            protocol (the arms and the BPTT settings aside: only the run holding the BPTT arm
            uses them); different pendulums; an arm in two runs; two different fixed-impedance
            searches.
    """
    from hec_jax.loop.arms import ALL_ARMS

    if not parts:
        raise ValueError("no runs to merge")
    arms: dict[str, dict] = {}
    fixed_search = None

    def key(config: dict) -> dict:
        # the arms differ by design; the BPTT settings matter only to the one run holding BPTT
        skip = ("arms", *_BPTT_FIELDS)
        protocol = {k: v for k, v in config["protocol"].items() if k not in skip}
        return {k: config[k] for k in ("preset", "reduced", "float32")} | {"protocol": protocol}

    first_config, first_metrics = parts[0]
    for config, metrics in parts:
        if config.get("status") != "complete":
            raise ValueError(f"a run is not complete (status {config.get('status')!r})")
        if key(config) != key(first_config):
            raise ValueError("the runs differ in preset, precision, reduction or protocol")
        if metrics["pendulums"] != first_metrics["pendulums"]:
            raise ValueError("the runs drew different pendulums")
        for arm, entry in metrics["arms"].items():
            if arm in arms:
                raise ValueError(f"arm {arm!r} is in two runs")
            arms[arm] = entry
        search = metrics.get("fixed_search")
        if search is not None:
            if fixed_search is not None and search != fixed_search:
                raise ValueError("two runs hold different fixed-impedance searches")
            fixed_search = search
    ordered = {arm: arms[arm] for arm in ALL_ARMS if arm in arms}
    out = {"arms": ordered, "pendulums": first_metrics["pendulums"]}
    if fixed_search is not None:
        out["fixed_search"] = fixed_search
    return out


@dataclass(frozen=True)
class PaperMerge:
    """Run folders of ``experiments/paper.py`` (one preset, disjoint arms) merged into one
    table's run folder.
    """

    runs: tuple[Path, ...] = ()  # the run folders to merge (each with config.json, metrics.json)
    out: Path = Path("runs/paper_merged")  # run folder (written complete or not at all)
    overwrite: bool = False  # replace an existing non-empty --out


@command
def merge_main(argv=None, doc: str | None = None) -> dict:
    """Parses ``argv`` (:class:`PaperMerge`), merges the runs (:func:`merge_runs`) and writes
    ``table.md`` and ``metrics.json`` in ``--out``; its ``config.json`` names the source runs with
    their own commits and devices. Returns the merged results.
    """
    import json

    from hec_jax.loop.arms import markdown_table, table_rows
    from hec_jax.runs import run_folder, write_json, write_text

    run = parse(PaperMerge(), argv, doc)
    if len(run.runs) < 2:
        raise usage_error("--runs: give at least two run folders to merge")
    parts = []
    for folder in run.runs:
        try:
            config = json.loads((folder / "config.json").read_text())
            metrics = json.loads((folder / "metrics.json").read_text())
        except (OSError, json.JSONDecodeError) as e:
            raise usage_error(f"--runs: {folder} is not a readable run folder ({e})") from e
        parts.append((config, metrics))
    try:
        merged = merge_runs(parts)
    except (ValueError, KeyError) as e:
        raise usage_error(f"--runs: cannot merge: {e}") from e
    first = parts[0][0]
    settings = dict(
        preset=first["preset"],
        merged_from=[
            dict(
                folder=str(folder),
                arms=config["protocol"]["arms"],
                code=config.get("code"),
                device=config.get("device"),
                started_utc=config.get("started_utc"),
                finished_utc=config.get("finished_utc"),
                protocol=config["protocol"],
            )
            for folder, (config, _) in zip(run.runs, parts, strict=True)
        ],
    )
    task = "catching" if first["preset"] == "catching_paper" else "hitting"
    with run_folder(run.out, first["seed"], settings, run.overwrite) as folder:
        table = markdown_table(table_rows(merged, task))
        write_text(folder / "table.md", table + "\n")
        write_json(folder / "metrics.json", merged)
    print(table)
    print(f"run folder: {run.out}")
    return merged
