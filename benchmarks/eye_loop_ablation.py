"""Ablation of the loop's box tracker on the real-time camera's frames, in simulated time.

The real-time camera on a software renderer draws the void without multisampling
(``--camera-msaa 0``); there the eye lost the held cube in 2-3 of 20 episodes (docs/realtime.md,
"The eye's CPU and the held cube"). This runs the simulated camera loop (``loop.run_camera``)
of the real-time preset (``realtime_experiment``: one seed, the swings of ``--duration-s``, the
scene's tracker with the real-time ``eye_local_starts``) on frames rendered as the real-time camera renders
them (``CameraConfig.msaa``), once per variant (``VARIANTS``: fields of the loop's tracker and of
its camera replaced), and tabulates what the eye did (frames valid, swings with a loss, the
longest run of invalid frames, which hypothesis gave each fit) beside the task's metrics and,
for reference, the same task with the simulator's object state (``--eye truth``, no camera).
``--no-maneuver-restart`` starts every variant from the real-time eye's tracker instead of the
loop's (``RealtimeConfig.eye_maneuver_restart``).

Deterministic: same seed, same frames, same numbers (CPU).

    python benchmarks/eye_loop_ablation.py --task catching --out runs/eye_loop_ablation_catching
    python benchmarks/eye_loop_ablation.py --task catching --no-maneuver-restart --seed 1 \
        --variants "tracker as configured" "coverage blind to the mask" \
        --out runs/eye_loop_ablation_coverage_seed1
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import jax
import numpy as np

from hec_jax.cli import command, parse, require
from hec_jax.geometry.track import FIT_SOURCES
from hec_jax.loop.camera_loop import run_camera
from hec_jax.loop.experiment import condition_metrics
from hec_jax.loop.policy import build_loop
from hec_jax.realtime.config import RealtimeConfig
from hec_jax.realtime.runner import simulated_twins, void_camera_experiment
from hec_jax.runs import run_folder, write_json, write_text

# name: (fields of the tracker (the loop's, with the real-time local starts), fields of the
# camera) replaced
VARIANTS = {
    "loop tracker (manoeuvre restart at NIS 16.3)": ({}, {}),
    # the same, named for --no-maneuver-restart (then the real-time eye's tracker)
    "tracker as configured": ({}, {}),
    "no manoeuvre restart": ({"maneuver_nis": None}, {}),
    "inner-edge check 0.05": ({"min_inner_support": 0.05}, {}),
    # the eye not told which pixels the robot's mask replaced (as before 2026-11-26)
    "coverage blind to the mask": ({}, {"mask_aware_coverage": False}),
    # no fit with fewer than 4 segments where the mask hides edges (as before 2026-11-27)
    "4 segments always": ({"min_segments_hidden": 4}, {}),
    # no stop hypothesis: a failed tracked fit goes straight to the local search, whose first
    # stage also starts at the last fitted centre (with the search's wider gates)
    "no stop hypothesis": ({"stop_hypothesis": False}, {}),
    # the floor drawn at a 0.05 m grid instead of scene.xml's 0.01 (``--camera-plane-grid-m``)
    "floor grid 0.05 m": ({}, {"plane_grid_m": 0.05}),
}

# the task metrics tabulated (catching: last swing; hitting: the continuous run)
METRICS = {
    "catching": ("peak_force", "settle_force"),
    "hitting": ("hits", "periodic_hits", "peak_force"),
}


@dataclass(frozen=True)
class LoopAblation:
    """Which task, how long, how the frames are rendered, and where to write."""

    task: Literal["catching", "hitting"] = "catching"
    out: Path = Path("runs/eye_loop_ablation")  # run folder
    overwrite: bool = False  # replace an existing non-empty out
    duration_s: float = 60.0  # [s] as the real-time run (its number of swings)
    msaa: int = 0  # multisample anti-aliasing of the frames (0: as the real-time camera)
    width: int = 640  # [px]
    height: int = 480  # [px]
    # names of VARIANTS to run (by default all but the alias "tracker as configured")
    variants: tuple[str, ...] = tuple(v for v in VARIANTS if v != "tracker as configured")
    seed: int = 0  # the networks' initialisation (the preset's, 0, is the real-time runs')
    # every variant from the loop's tracker (True) or the real-time eye's, without the
    # manoeuvre restart (False)
    maneuver_restart: bool = True

    def __post_init__(self):
        require(self, "seed", "seed")
        unknown = [v for v in self.variants if v not in VARIANTS]
        if unknown:
            raise ValueError(f"--variants: unknown {unknown}; known: {list(VARIANTS)}")


def _scalar(metrics: dict, key: str):
    """A metric's value for one seed (a ``{"mean": ...}`` summary or a number)."""
    v = metrics.get(key)
    if isinstance(v, dict):
        v = v.get("mean")
    return None if v is None else float(v)


def eye_summary(eye: dict, lost_after: int) -> dict:
    """What the eye did over the run (its one network initialisation): valid fraction, swings with a run of at least
    ``lost_after`` invalid frames after the first valid one (a loss), the longest such run.
    """
    valid = np.asarray(eye["valid"])[0]  # (swings, frames)
    longest, lost = [], 0
    for row in valid:
        seen = np.flatnonzero(row)
        run = best = 0
        for v in row[seen[0] :] if len(seen) else row:
            run = 0 if v else run + 1
            best = max(best, run)
        longest.append(best)
        lost += int(best >= lost_after)
    err = np.linalg.norm(np.asarray(eye["x_est"])[0] - np.asarray(eye["x_true"])[0], axis=-1)
    err = err[valid & np.isfinite(err)]
    return {
        # [mm] task-plane centre of the valid frames against the simulator's
        "position_error_mm_p50": float(1e3 * np.median(err)) if err.size else None,
        "position_error_mm_max": float(1e3 * err.max()) if err.size else None,
        "frames": int(valid.size),
        "frames_valid_fraction": float(valid.mean()),
        "swings": int(valid.shape[0]),
        "swings_fully_valid": int(np.all(valid, axis=1).sum()),
        "swings_with_a_loss": lost,
        "longest_invalid_run_frames": int(max(longest)),
        "eye_ms_p50": float(np.median(np.asarray(eye["eye_ms"]))),
        # frames by the hypothesis that gave their fit (FIT_SOURCES; "" : not valid)
        "fits_by_source": {
            (name or "invalid"): int(np.sum(np.asarray(eye["fit_source"]) == k))
            for k, name in enumerate(FIT_SOURCES)
        },
    }


@command
def main(argv=None) -> dict:
    """Runs the ablation (flags: ``--help``); returns its results."""
    a = parse(LoopAblation(), argv, __doc__)
    jax.config.update("jax_enable_x64", True)
    rt = RealtimeConfig(duration_s=a.duration_s, eye_maneuver_restart=a.maneuver_restart)
    exp = void_camera_experiment(a.task, a.seed, a.width, a.height, a.msaa, rt)
    loop = build_loop(exp.task)
    conditions = exp.task.pendulum.conditions()
    keys = jax.random.split(jax.random.PRNGKey(exp.seed), 1)
    settings = {k: v for k, v in dataclasses.asdict(a).items() if k != "seed"}  # the folder's
    fields = {v: {"track": VARIANTS[v][0], "camera": VARIANTS[v][1]} for v in a.variants}
    settings |= {"variants_fields": fields}
    with run_folder(a.out, exp.seed, settings, a.overwrite) as folder:
        truth = simulated_twins(exp, loop, "learned", "truth", progress=False)["truth"]
        results = {"truth": {"metrics": truth["metrics"]}}
        for name in a.variants:
            track_fields, camera_fields = VARIANTS[name]
            track = dataclasses.replace(exp.camera.tracker, **track_fields)
            c = dataclasses.replace(exp.camera, track=track, **camera_fields)
            t0 = time.perf_counter()
            logs, eye, _ = run_camera(loop, conditions, keys, "learned", c, progress=False)
            results[name] = {
                "metrics": condition_metrics(loop, logs, "learned"),
                "eye": eye_summary(eye, track.lost_after),
                "wall_s": time.perf_counter() - t0,
            }
            print(name, results[name]["eye"], flush=True)
        write_json(folder / "results.json", results)
        write_text(folder / "table.md", "\n".join(table(results, a.task)) + "\n")
    print("\n".join(table(results, a.task)))
    return results


def table(results: dict, task: str) -> list[str]:
    """Markdown rows: the eye's record and the task's metrics per variant."""
    keys = METRICS[task]
    head = ["variant", "frames valid", "swings fully valid", "swings with a loss"]
    head += ["longest invalid run [frames]", "error p50 / max [mm]"]
    head += [
        "fits: tracked / stopped / three_segments / local / local_turned / along_sight / search",
        *keys,
    ]
    rows = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, r in results.items():
        e = r.get("eye")
        cells = [name]
        cells += (
            [
                f"{100 * e['frames_valid_fraction']:.2f}%",
                f"{e['swings_fully_valid']} / {e['swings']}",
                str(e["swings_with_a_loss"]),
                str(e["longest_invalid_run_frames"]),
                "-"
                if e.get("position_error_mm_p50") is None
                else f"{e['position_error_mm_p50']:.1f} / {e['position_error_mm_max']:.1f}",
            ]
            if e
            else ["-"] * 5
        )
        fits = (e or {}).get("fits_by_source")
        names = (
            "tracked",
            "stopped",
            "three_segments",
            "local",
            "local_turned",
            "along_sight",
            "search",
        )
        cells.append(" / ".join(str(fits.get(n, 0)) for n in names) if fits else "-")
        for k in keys:
            v = _scalar(r["metrics"], k)
            cells.append("-" if v is None else f"{v:.4g}")
        rows.append("| " + " | ".join(cells) + " |")
    return rows


if __name__ == "__main__":
    main()
