"""Eye benchmark: the paper's two-segment motion estimate against OpenCV on the same synthetic data.

Scenes: a 0.1 m cube 0.5-2 m from a 640x480, f = 600 px camera, random small and large motions
(``hec_jax.geometry.make_cube_scenes``), Gaussian pixel noise on every corner. Methods, all on the
same noisy corners:

* ``paper``: ``estimate_motion`` (Eqs. 7-38) on one pair of parallel cube edges, metric via |AB|.
* ``pnp_ippe_square``: ``cv2.solvePnP(SOLVEPNP_IPPE_SQUARE)`` on the most frontal face (chosen by
  ground truth) in each frame; Phi = R2 R1^T, Gamma = t2 - Phi t1.
* ``homography``: ``cv2.findHomography`` on the same face between the frames,
  ``cv2.decomposeHomographyMat``, the candidate closest to the truth (oracle choice); rotation only.
* ``essential``: ``cv2.findEssentialMat`` (LMedS) on all 8 corners + ``cv2.recoverPose``; rotation only.

Rotation error: angle of R_est^T R_true [deg]. Translation error: |Gamma_est - Gamma_true| [mm]
(Gamma of Eq. 1, camera frame). Failure: the method reports no valid solution (``valid == False``
for the paper's method, no solution from OpenCV). Errors are over the non-failed problems.

Timing (CPU, same run): single-problem latency of the jitted JAX estimate against the OpenCV PnP
two-frame call, and batched throughput of the jitted estimate against the OpenCV per-problem loop,
as ratios. Writes ``config.json``, ``metrics.json``, ``table.md`` and a plot to ``--out``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import jax
import jax.numpy as jnp
import numpy as np

from hec_jax.geometry import SceneConfig, estimate_motion, make_cube_scenes, rotation_error_deg
from hec_jax.geometry.parallel_motion import estimate_motion_core
from hec_jax.geometry.synthetic import CUBE_FACES
from hec_jax.runs import save_figure, start_run, write_json, write_text

NOISE_PX = (0.0, 0.25, 0.5, 1.0, 2.0)
METHODS = ("paper", "pnp_ippe_square", "homography", "essential")


def _frontal_face(corners_before: np.ndarray) -> tuple[int, ...]:
    """Corner indices (cyclic) of the face whose outward normal points most towards the camera."""
    centre = corners_before.mean(0)
    best, best_score = None, -np.inf
    for idx, _ in CUBE_FACES:
        face_centre = corners_before[list(idx)].mean(0)
        normal = face_centre - centre
        score = -normal @ face_centre / (np.linalg.norm(normal) * np.linalg.norm(face_centre))
        if score > best_score:
            best, best_score = idx, score
    return best


def _square_object_points(edge: float) -> np.ndarray:
    h = edge / 2.0
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


def opencv_pnp(pix_b, pix_a, face, k, edge):
    """Two-frame IPPE_SQUARE on one face -> (rotation, translation) or None."""
    obj = _square_object_points(edge)
    poses = []
    for pix in (pix_b, pix_a):
        ok, rvec, tvec = cv2.solvePnP(
            obj, pix[list(face)].astype(np.float64), k, None, flags=cv2.SOLVEPNP_IPPE_SQUARE
        )
        if not ok:
            return None
        poses.append((cv2.Rodrigues(rvec)[0], tvec.ravel()))
    (r1, t1), (r2, t2) = poses
    rot = r2 @ r1.T
    return rot, t2 - rot @ t1


def opencv_homography(pix_b, pix_a, face, k, true_rot):
    """Homography between the frames on one face, decomposed; oracle choice of the candidate."""
    h, _ = cv2.findHomography(pix_b[list(face)], pix_a[list(face)], 0)
    if h is None:
        return None
    n, rots, _, _ = cv2.decomposeHomographyMat(h, k)
    if n == 0:
        return None
    errs = [rotation_error_deg(np.asarray(r), true_rot) for r in rots]
    return np.asarray(rots[int(np.argmin(errs))]), None


def opencv_essential(pix_b, pix_a, k):
    """Essential matrix on all 8 corners (LMedS) and recoverPose; rotation only."""
    e, _ = cv2.findEssentialMat(pix_b, pix_a, k, method=cv2.LMEDS)
    if e is None or e.shape != (3, 3):
        return None
    _, rot, _, _ = cv2.recoverPose(e, pix_b, pix_a, k)
    return rot, None


def evaluate(scenes, config: SceneConfig) -> dict:
    """Errors and failure rates of every method on one batch of scenes."""
    n = len(scenes.pair)
    k = config.intrinsics
    est = estimate_motion(scenes.points_before, scenes.points_after, config.edge)
    valid = np.asarray(est.valid)
    rot_err = {"paper": rotation_error_deg(np.asarray(est.rotation), scenes.rotation)}
    tr_err = {"paper": np.linalg.norm(np.asarray(est.translation) - scenes.translation, axis=-1)}
    ok = {"paper": valid}
    for name in METHODS[1:]:
        rot_err[name], tr_err[name], ok[name] = (
            np.full(n, np.nan),
            np.full(n, np.nan),
            np.zeros(n, bool),
        )
    for i in range(n):
        pb, pa = scenes.pixels_before[i], scenes.pixels_after[i]
        face = _frontal_face(scenes.corners_before[i])
        results = {
            "pnp_ippe_square": opencv_pnp(pb, pa, face, k, config.edge),
            "homography": opencv_homography(pb, pa, face, k, scenes.rotation[i]),
            "essential": opencv_essential(pb, pa, k),
        }
        for name, res in results.items():
            if res is None:
                continue
            ok[name][i] = True
            rot_err[name][i] = rotation_error_deg(res[0], scenes.rotation[i])
            if res[1] is not None:
                tr_err[name][i] = np.linalg.norm(res[1] - scenes.translation[i])
    out = {}
    for name in METHODS:
        r, t, good = rot_err[name][ok[name]], tr_err[name][ok[name]], ok[name]
        has_t = np.any(np.isfinite(t))
        out[name] = {
            "rotation_median_deg": float(np.median(r)) if r.size else None,
            "rotation_p90_deg": float(np.percentile(r, 90)) if r.size else None,
            "translation_median_mm": float(np.median(t) * 1e3) if has_t else None,
            "translation_p90_mm": float(np.percentile(t, 90) * 1e3) if has_t else None,
            "failure_rate": float(1.0 - good.mean()),
        }
    return out


def timing(scenes, config: SceneConfig, batch: int, repeats: int) -> dict:
    """Latency and throughput of the jitted JAX estimate vs the OpenCV per-problem loop."""
    k = config.intrinsics
    core = jax.jit(estimate_motion_core)
    one_b, one_a = jnp.asarray(scenes.points_before[0]), jnp.asarray(scenes.points_after[0])
    one_len = jnp.asarray(config.edge)
    core(one_b, one_a, one_len).rotation.block_until_ready()
    t0 = time.perf_counter()
    for _ in range(repeats):
        core(one_b, one_a, one_len).rotation.block_until_ready()
    jax_latency = (time.perf_counter() - t0) / repeats

    reps = -(-batch // len(scenes.pair))
    bb = jnp.asarray(np.tile(scenes.points_before, (reps, 1, 1))[:batch])
    ba = jnp.asarray(np.tile(scenes.points_after, (reps, 1, 1))[:batch])
    bl = jnp.full((batch,), config.edge)
    t_compile = time.perf_counter()
    core(bb, ba, bl).rotation.block_until_ready()
    compile_s = time.perf_counter() - t_compile
    t0 = time.perf_counter()
    for _ in range(3):
        core(bb, ba, bl).rotation.block_until_ready()
    jax_batched = 3 * batch / (time.perf_counter() - t0)

    faces = [_frontal_face(c) for c in scenes.corners_before]
    n_cv = min(len(scenes.pair), repeats)
    t0 = time.perf_counter()
    for i in range(n_cv):
        opencv_pnp(scenes.pixels_before[i], scenes.pixels_after[i], faces[i], k, config.edge)
    cv_latency = (time.perf_counter() - t0) / n_cv
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


def table(metrics: dict, timings: dict, n: int) -> str:
    fmt = lambda x, f="{:.3g}": "-" if x is None else f.format(x)  # noqa: E731
    lines = [
        f"Rotation error [deg], translation error [mm] (Gamma of Eq. 1) and failure rate over {n}"
        " scenes per noise level (0.1 m cube, 0.5-2 m, 640x480, f = 600 px, half small, half large"
        " motions).",
        "",
        "| noise [px] | method | rot median | rot p90 | trans median | trans p90 | failures |",
        "|---|---|---|---|---|---|---|",
    ]
    for noise, per_method in metrics.items():
        for name, m in per_method.items():
            lines.append(
                f"| {noise} | {name} | {fmt(m['rotation_median_deg'])} | {fmt(m['rotation_p90_deg'])}"
                f" | {fmt(m['translation_median_mm'])} | {fmt(m['translation_p90_mm'])}"
                f" | {m['failure_rate']:.1%} |"
            )
    t = timings
    lines += [
        "",
        "| timing (CPU, same run) | value |",
        "|---|---|",
        f"| JAX jitted, one problem | {t['jax_single_latency_us']:.1f} us |",
        f"| OpenCV IPPE_SQUARE, two frames, one problem | {t['opencv_pnp_two_frame_latency_us']:.1f} us |",
        f"| latency ratio JAX / OpenCV | {t['latency_ratio_jax_over_opencv']:.2f} |",
        f"| JAX jitted, batch {t['batch']} | {t['jax_batched_problems_per_s']:.3g} problems/s |",
        f"| OpenCV per-problem loop | {t['opencv_loop_problems_per_s']:.3g} problems/s |",
        f"| throughput ratio JAX batched / OpenCV loop | {t['throughput_ratio_jax_batched_over_opencv_loop']:.1f} |",
    ]
    return "\n".join(lines) + "\n"


def plot(metrics: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    noises = [float(x) for x in metrics]
    for name in METHODS:
        med = [metrics[k][name]["rotation_median_deg"] for k in metrics]
        ax.plot(noises, [np.nan if m is None else m for m in med], "o-", label=name)
    ax.set_xlabel("pixel noise sigma [px]")
    ax.set_ylabel("median rotation error [deg]")
    ax.set_yscale("symlog", linthresh=1e-3)
    ax.legend()
    ax.grid(True, alpha=0.3)
    save_figure(fig, path)
    plt.close(fig)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("runs/eye_benchmark"))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--scenes", type=int, default=2000, help="scenes per noise level")
    parser.add_argument("--batch", type=int, default=10000, help="batch size for throughput")
    parser.add_argument("--repeats", type=int, default=500, help="calls for the latency timing")
    parser.add_argument("--docs", type=Path, default=None, help="also write the table here")
    args = parser.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    config = SceneConfig()
    folder = start_run(
        args.out,
        args.seed,
        {
            "scenes_per_noise": args.scenes,
            "noise_px": NOISE_PX,
            "batch": args.batch,
            "repeats": args.repeats,
            "scene_config": config.__dict__,
            "dtype": "float64",
        },
    )
    rng = np.random.default_rng(args.seed)
    metrics = {}
    for noise in NOISE_PX:
        scenes = make_cube_scenes(rng, args.scenes, config, motion="mixed", noise_px=noise)
        metrics[str(noise)] = evaluate(scenes, config)
        print(
            f"noise {noise} px: "
            + ", ".join(
                f"{m} {v['rotation_median_deg']:.3g} deg ({v['failure_rate']:.0%} failed)"
                for m, v in metrics[str(noise)].items()
                if v["rotation_median_deg"] is not None
            ),
            flush=True,
        )
    scenes = make_cube_scenes(rng, args.scenes, config, motion="mixed", noise_px=0.5)
    timings = timing(scenes, config, args.batch, args.repeats)
    text = table(metrics, timings, args.scenes)
    write_json(folder / "metrics.json", {"accuracy": metrics, "timing": timings})
    write_text(folder / "table.md", text)
    plot(metrics, folder / "rotation_error.png")
    if args.docs is not None:
        write_text(
            args.docs,
            "# Eye benchmark\n\nCommand: `python benchmarks/eye.py "
            f"--out {args.out} --seed {args.seed}`\n\n" + text,
        )
    print(text)
    return {"accuracy": metrics, "timing": timings}


if __name__ == "__main__":
    main()
