"""Eye pipeline benchmark (issue 5): accuracy vs OpenCV and the latency breakdown.

1. Synthetic two-frame problems (``make_cube_scenes``, sigma = 0.5 px on every corner): our
   ``two_frame_motion`` (homography/paper start + LM over all visible corners) against OpenCV
   ``solvePnP(IPPE_SQUARE)`` on the most frontal face, same data; batched JAX throughput against
   the OpenCV per-problem loop.
2. A rendered swing of the scene's cube (640x480, 30 fps, release angle drawn from the seed in
   0.3-0.6 rad): ``track_box`` against MuJoCo's ground truth, smoothed (offline, the main output)
   and causal (per-frame fit + forward filter), and its per-frame latency (after a full warm-up
   run; the offline smoothing is reported per frame beside it).
Writes config.json, metrics.json and table.md to --out.

``--synthetic-only`` skips part 2 (it needs MuJoCo rendering), e.g. on a GPU machine without it;
``--batch`` takes several sizes (a sweep: GPU throughput needs large batches), the top-level
timings are those of the first size, the ``sweep`` entry holds all of them; ``--transfer`` also
times the batched core with the host-to-device copy of the inputs and the copy of the rotations
back included. The OpenCV loop always runs on the host's CPU, in the same run.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import jax
import numpy as np

from hec_jax import report
from hec_jax.cli import command, parse, require
from hec_jax.geometry import SceneConfig, make_cube_scenes, rotation_error_deg, two_frame_motion
from hec_jax.geometry.accuracy import track_errors
from hec_jax.geometry.baselines import pnp_rotation_errors
from hec_jax.runs import run_folder, write_json, write_text

FPS = 30.0
# the JAX core's two settings: float64 with the default 10 LM iterations, float32 with 5 (the same
# median error here: LM has converged by then)
SETTINGS = (("f64_iters10", np.float64, 10), ("f32_iters5", np.float32, 5))


@dataclass(frozen=True)
class EyePipeline:
    """What the benchmark draws and measures, and where it writes."""

    out: Path = Path("runs/eye_pipeline")  # run folder

    overwrite: bool = False  # replace an existing non-empty out (else refused up front)
    seed: int = 0  # draws the synthetic problems and the swing's release angle
    scenes: int = 1000  # synthetic two-frame problems
    batch: tuple[int, ...] = (10000,)  # batch sizes of the JAX timing (the first is reported)
    seconds: float = 5.0  # length of the rendered swing [s]
    synthetic_only: bool = False  # skip the rendered swing
    transfer: bool = False  # also time with host<->device copies

    def __post_init__(self):
        require(self, "count", "scenes", "batch")
        require(self, "positive", "seconds")
        require(self, "seed", "seed")


def synthetic(rng, n: int, batches: tuple[int, ...], transfer: bool = False) -> dict:
    """Accuracy against IPPE_SQUARE and per-problem cost of the batched JAX core against the
    OpenCV loop, in one run (the top-level timings are the first batch size's; all are under
    ``sweep`` when there are several or ``transfer``).
    """
    sweep = {str(b): {} for b in batches}
    cfg = SceneConfig()
    k = cfg.intrinsics
    sc = make_cube_scenes(rng, n, cfg, motion="mixed", noise_px=0.5)
    cv_loop = lambda: pnp_rotation_errors(sc, k, cfg.edge)  # noqa: E731
    ippe, cv_s = report.timed(cv_loop)
    cv_us = cv_s / n * 1e6  # includes the frontal-face choice
    out = {"ippe_rotation_median_deg": float(np.median(ippe)), "opencv_loop_us_per_problem": cv_us}
    for name, dtype, iters in SETTINGS:
        g = jax.jit(jax.vmap(lambda a, b, it=iters: two_frame_motion(a, b, cfg.edge, k, it)))
        pb, pa = np.asarray(sc.pixels_before, dtype), np.asarray(sc.pixels_after, dtype)
        res = g(pb, pa)
        ours = rotation_error_deg(np.asarray(res.rotation, np.float64), sc.rotation)
        rotation = lambda x, y, g=g: g(x, y).rotation  # noqa: E731
        for b in batches:
            t = report.batched_us_per_item(
                rotation, [report.tile_batch(pb, b), report.tile_batch(pa, b)], transfer
            )
            sweep[str(b)] |= {f"jax_batched_{name}_{key}": val for key, val in t.items()}
            print(f"batch {b} {name}: {t}", flush=True)
        us = f"jax_batched_{name}_us_per_problem"
        out |= {
            f"ours_{name}_rotation_median_deg": float(np.median(ours)),
            f"ours_{name}_valid_rate": float(np.asarray(res.valid).mean()),
            us: sweep[str(batches[0])][us],
            f"speedup_jax_batched_{name}_over_opencv": None,  # below
        }
    # after the JAX runs too: the OpenCV loop again, the faster of the two (contention)
    cv_us = min(cv_us, report.timed(cv_loop)[1] / n * 1e6)
    out["opencv_loop_us_per_problem"] = cv_us
    for name, _, _ in SETTINGS:
        for d in (out, *sweep.values()):
            d[f"speedup_jax_batched_{name}_over_opencv"] = (
                cv_us / d[f"jax_batched_{name}_us_per_problem"]
            )
    if len(batches) > 1 or transfer:
        out["sweep"] = sweep
    out |= {"opencv_cpu": report.cpu_model(), "opencv_threads": cv2.getNumThreads()}
    out["jax_device"] = str(jax.devices()[0])
    out["ours_rotation_median_deg"] = out["ours_f64_iters10_rotation_median_deg"]
    out["ratio_ours_over_ippe"] = out["ours_rotation_median_deg"] / out["ippe_rotation_median_deg"]
    return out


def rendered(seed: int, seconds: float) -> dict:
    """Accuracy and per-frame time of ``track_box`` on a rendered swing of ``seconds``."""
    from hec_jax.geometry import track_box
    from hec_jax.mjx_scene import CUBE_EDGE
    from hec_jax.mjx_scene.render import render_swing

    angle = float(np.random.default_rng(seed).uniform(0.3, 0.6))
    seq = render_swing(angle, int(round(seconds * FPS)), FPS)
    # compile on the same sequence: a short warm-up may never reach the tracked path (or the
    # smoother's padded length), and the timed run would include compilation
    track = lambda: track_box(seq.frames, seq.intrinsics, CUBE_EDGE, FPS)  # noqa: E731
    _, compile_s = report.timed(track)
    tr, wall = report.timed(track)
    return {"release_rad": angle, "first_call_s": compile_s, "wall_s": wall} | track_errors(tr, seq)


def table(metrics: dict) -> list[str]:
    """The Markdown lines of the benchmark's table."""
    lines = report.metrics_table(metrics)
    syn = metrics["synthetic_two_frame_0.5px"]
    if "sweep" in syn:
        cv_us = syn["opencv_loop_us_per_problem"]
        rows = []
        for b, d in syn["sweep"].items():
            for name, _, _ in SETTINGS:
                us = d[f"jax_batched_{name}_us_per_problem"]
                tr = d.get(f"jax_batched_{name}_with_transfer_us_per_problem", float("nan"))
                rows.append((b, name, f"{us:.4g}", f"{tr:.4g}", f"{cv_us / us:.3g}x"))
        header = ["batch", "dtype, LM iterations", "JAX us/problem", "with transfer", "speedup"]
        lines += ["", f"Batch sweep ({syn['jax_device']}; OpenCV loop {cv_us:.1f} us per problem)"]
        lines += ["", *report.markdown_table(header, rows)]
    return lines


@command
def main(argv=None) -> dict:
    """Runs the benchmark (flags: ``--help``); returns its metrics."""
    a = parse(EyePipeline(), argv, __doc__)
    jax.config.update("jax_enable_x64", True)
    settings = {"scenes": a.scenes, "batch": a.batch[0] if len(a.batch) == 1 else a.batch}
    settings |= {"seconds": a.seconds, "synthetic_only": a.synthetic_only}
    settings |= {
        "opencv": cv2.__version__,
        "cpu": report.cpu_model(),
        "os_cpu_count": os.cpu_count(),
    }
    with run_folder(a.out, a.seed, settings, a.overwrite) as folder:
        syn = synthetic(np.random.default_rng(a.seed), a.scenes, a.batch, a.transfer)
        print("synthetic:", syn, flush=True)
        metrics = {"synthetic_two_frame_0.5px": syn}
        if not a.synthetic_only:
            ren = rendered(a.seed, a.seconds)
            print("rendered:", ren, flush=True)
            metrics["rendered_swing"] = ren
        write_json(folder / "metrics.json", metrics)
        lines = table(metrics)
        write_text(folder / "table.md", "\n".join(lines) + "\n")
        print("\n".join(lines))
        return metrics


if __name__ == "__main__":
    main()
