"""Eye benchmark: the paper's two-segment motion estimate against OpenCV on the same synthetic data.

Scenes: a 0.1 m cube 0.5-2 m from a 640x480, f = 600 px camera, random small and large motions
(``hec_jax.geometry.make_cube_scenes``), Gaussian pixel noise on every corner. Methods, all on the
same noisy corners (``hec_jax.geometry.accuracy.motion_errors``): ``paper`` (``estimate_motion``,
Eqs. 7-38, one pair of parallel cube edges, metric via |AB|) and the OpenCV baselines of
``hec_jax.geometry.baselines``: ``pnp_ippe_square`` (IPPE_SQUARE on the most frontal face in
each frame), ``homography`` (one face, oracle choice of the decomposition; rotation only) and
``essential`` (all 8 corners, LMedS + recoverPose; rotation only).

Rotation error: angle of R_est^T R_true [deg]. Translation error: |Gamma_est - Gamma_true| [mm]
(Gamma of Eq. 1, camera frame). Failure: the method reports no valid solution. Errors are over
the non-failed problems.

Timing (CPU, same run): single-problem latency of the jitted JAX estimate against the OpenCV PnP
two-frame call, and batched throughput of the jitted estimate against the OpenCV per-problem loop,
as ratios. Writes ``config.json``, ``metrics.json``, ``table.md`` and a plot to ``--out``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from hec_jax.cli import command, parse, require
from hec_jax.geometry import SceneConfig, make_cube_scenes
from hec_jax.geometry.accuracy import METHODS, motion_errors
from hec_jax.geometry.baselines import frontal_face, opencv_pnp
from hec_jax.geometry.parallel_motion import estimate_motion_core
from hec_jax.report import call_times, error_table, fmt, markdown_table, tile_batch
from hec_jax.runs import run_folder, save_figure, write_json, write_text

NOISE_PX = (0.0, 0.25, 0.5, 1.0, 2.0)


@dataclass(frozen=True)
class EyeBenchmark:
    """What the benchmark draws and measures, and where it writes."""

    out: Path = Path("runs/eye_benchmark")  # run folder

    overwrite: bool = False  # replace an existing non-empty out (else refused up front)
    seed: int = 0  # draws the scenes
    scenes: int = 2000  # scenes per noise level
    batch: int = 10000  # batch size for throughput
    repeats: int = 500  # calls for the latency timing
    docs: Path | None = None  # also write the table here

    def __post_init__(self):
        require(self, "count", "scenes", "batch", "repeats")
        require(self, "seed", "seed")


def timing(scenes, config: SceneConfig, batch: int, repeats: int) -> dict:
    """Latency and throughput of the jitted JAX estimate vs the OpenCV per-problem loop."""
    core = jax.jit(estimate_motion_core)
    one = (scenes.points_before[0], scenes.points_after[0], config.edge)
    many = (tile_batch(scenes.points_before, batch), tile_batch(scenes.points_after, batch))
    one = [jnp.asarray(x) for x in one]
    many = [*map(jnp.asarray, many), jnp.full(batch, config.edge)]
    run = lambda args: core(*args).rotation.block_until_ready()  # noqa: E731
    run(one)
    jax_latency = call_times(lambda: run(one), repeats).mean()
    compile_s = call_times(lambda: run(many), 1)[0]
    jax_batched = batch / call_times(lambda: run(many), 3).mean()
    faces = [frontal_face(c) for c in scenes.corners_before]
    n_cv = min(len(scenes.pair), repeats)
    k, pb, pa = config.intrinsics, scenes.pixels_before, scenes.pixels_after
    loop = lambda: [opencv_pnp(pb[i], pa[i], faces[i], k, config.edge) for i in range(n_cv)]  # noqa: E731
    cv_latency = call_times(loop, 1)[0] / n_cv
    return {
        "jax_single_latency_us": jax_latency * 1e6,
        "opencv_pnp_two_frame_latency_us": cv_latency * 1e6,
        "latency_ratio_jax_over_opencv": jax_latency / cv_latency,
        "jax_batched_problems_per_s": jax_batched,
        "opencv_loop_problems_per_s": 1.0 / cv_latency,
        "throughput_ratio_jax_batched_over_opencv_loop": jax_batched * cv_latency,
        "batch": batch,
        "jax_batched_first_call_s": compile_s,
    }


def table(metrics: dict, t: dict, n: int) -> str:
    """The Markdown table of accuracy per method and noise level, and the timings."""
    timings = [
        ("JAX jitted, one problem", f"{t['jax_single_latency_us']:.1f} us"),
        ("OpenCV IPPE_SQUARE, two frames, one problem", f"{t['opencv_pnp_two_frame_latency_us']:.1f} us"),
        ("latency ratio JAX / OpenCV", f"{t['latency_ratio_jax_over_opencv']:.2f}"),
        (f"JAX jitted, batch {t['batch']}", f"{t['jax_batched_problems_per_s']:.3g} problems/s"),
        ("OpenCV per-problem loop", f"{t['opencv_loop_problems_per_s']:.3g} problems/s"),
        ("throughput ratio JAX batched / OpenCV loop", f"{t['throughput_ratio_jax_batched_over_opencv_loop']:.1f}"),
    ]  # fmt: skip
    lines = [
        f"Rotation error [deg], translation error [mm] (Gamma of Eq. 1) and failure rate over {n}"
        " scenes per noise level (0.1 m cube, 0.5-2 m, 640x480, f = 600 px, half small, half large"
        " motions).",
        "",
        *error_table(metrics, "noise [px]"),
        "",
        *markdown_table(["timing (CPU, same run)", "value"], timings),
    ]
    return "\n".join(lines) + "\n"


def plot(metrics: dict, path: Path) -> None:
    """Rotation error against pixel noise per method (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for name in METHODS:
        med = [per_method[name]["rotation_median_deg"] for per_method in metrics.values()]
        med = [np.nan if m is None else m for m in med]
        ax.plot([float(x) for x in metrics], med, "o-", label=name)
    ax.set_xlabel("pixel noise sigma [px]")
    ax.set_ylabel("median rotation error [deg]")
    ax.set_yscale("symlog", linthresh=1e-3)
    ax.legend()
    ax.grid(True, alpha=0.3)
    save_figure(fig, path)
    plt.close(fig)


@command
def main(argv=None) -> dict:
    """Runs the benchmark (flags: ``--help``); returns its metrics."""
    args = parse(EyeBenchmark(), argv, __doc__)
    jax.config.update("jax_enable_x64", True)
    config = SceneConfig()
    settings = {"scenes_per_noise": args.scenes, "noise_px": NOISE_PX, "batch": args.batch}
    settings |= {"repeats": args.repeats, "scene_config": asdict(config), "dtype": "float64"}
    with run_folder(args.out, args.seed, settings, args.overwrite) as folder:
        rng = np.random.default_rng(args.seed)
        metrics = {}
        for noise in NOISE_PX:
            scenes = make_cube_scenes(rng, args.scenes, config, motion="mixed", noise_px=noise)
            metrics[str(noise)] = motion_errors(scenes, config)
            summary = ", ".join(
                f"{m} {fmt(v['rotation_median_deg'])} deg ({v['failure_rate']:.0%} failed)"
                for m, v in metrics[str(noise)].items()
            )
            print(f"noise {noise} px: {summary}", flush=True)
        scenes = make_cube_scenes(rng, args.scenes, config, motion="mixed", noise_px=0.5)
        timings = timing(scenes, config, args.batch, args.repeats)
        text = table(metrics, timings, args.scenes)
        write_json(folder / "metrics.json", {"accuracy": metrics, "timing": timings})
        write_text(folder / "table.md", text)
        plot(metrics, folder / "rotation_error.png")
        if args.docs is not None:
            command = f"python benchmarks/eye.py --out {args.out} --seed {args.seed}"
            write_text(args.docs, f"# Eye benchmark\n\nCommand: `{command}`\n\n" + text)
        print(text)
        return {"accuracy": metrics, "timing": timings}


if __name__ == "__main__":
    main()
