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

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import cv2
import jax
import jax.numpy as jnp
import numpy as np


def _load(path: Path, name: str):
    """Import a script by path (benchmarks/eye.py and experiments/eye.py share a module name)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


_ROOT = Path(__file__).resolve().parents[1]
_bench_eye = _load(_ROOT / "benchmarks" / "eye.py", "bench_eye")
_frontal_face, opencv_pnp = _bench_eye._frontal_face, _bench_eye.opencv_pnp

from hec_jax.geometry import SceneConfig, make_cube_scenes, rotation_error_deg  # noqa: E402
from hec_jax.geometry.refine import two_frame_motion  # noqa: E402
from hec_jax.runs import start_run, write_json, write_text  # noqa: E402


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor()


def _time_batched(f, pb, pa, dtype, transfer: bool) -> dict:
    """Per-problem time [us] of the jitted batched core on inputs already on the device (minimum
    of 3 after a warm-up call that compiles); with ``transfer``, also from host arrays to the
    rotations back on the host."""
    batch = len(pb)
    bb, ba = jnp.asarray(pb, dtype), jnp.asarray(pa, dtype)
    f(bb, ba).rotation.block_until_ready()
    times = []
    for _ in range(3):
        t0 = time.perf_counter()
        f(bb, ba).rotation.block_until_ready()
        times.append(time.perf_counter() - t0)
    out = {"us_per_problem": min(times) / batch * 1e6}
    if transfer:
        hb, ha = np.asarray(pb, dtype), np.asarray(pa, dtype)
        times = []
        for _ in range(3):
            t0 = time.perf_counter()
            np.asarray(f(jnp.asarray(hb), jnp.asarray(ha)).rotation)
            times.append(time.perf_counter() - t0)
        out["with_transfer_us_per_problem"] = min(times) / batch * 1e6
    return out


def synthetic(rng, n: int, batch, transfer: bool = False) -> dict:
    """Accuracy against IPPE_SQUARE and per-problem cost of the batched JAX core against the
    OpenCV loop, in one run. The JAX core is timed in two settings: float64 with the default 10
    LM iterations, and float32 with 5 (the same median error here: LM has converged by then).
    ``batch``: one size or a sequence of sizes (the top-level timings are the first size's; all
    are under ``sweep``)."""
    batches = [int(batch)] if np.ndim(batch) == 0 else [int(b) for b in batch]
    sweep = {str(b): {} for b in batches}
    cfg = SceneConfig()
    k = cfg.intrinsics
    sc = make_cube_scenes(rng, n, cfg, motion="mixed", noise_px=0.5)
    t0 = time.perf_counter()
    ippe = []
    for i in range(n):
        r = opencv_pnp(
            sc.pixels_before[i],
            sc.pixels_after[i],
            _frontal_face(sc.corners_before[i]),
            k,
            cfg.edge,
        )
        ippe.append(rotation_error_deg(r[0], sc.rotation[i]))
    cv_us = (time.perf_counter() - t0) / n * 1e6  # includes the frontal-face choice
    out = {"ippe_rotation_median_deg": float(np.median(ippe)), "opencv_loop_us_per_problem": cv_us}
    for name, dtype, iters in (("f64_iters10", np.float64, 10), ("f32_iters5", np.float32, 5)):
        f = jax.jit(
            jax.vmap(lambda a, b, it=iters: two_frame_motion(a, b, cfg.edge, k, it), (0, 0))
        )
        res = f(jnp.asarray(sc.pixels_before, dtype), jnp.asarray(sc.pixels_after, dtype))
        ours = rotation_error_deg(np.asarray(res.rotation, np.float64), sc.rotation)
        for b in batches:
            reps = -(-b // n)
            t = _time_batched(
                f,
                np.tile(sc.pixels_before, (reps, 1, 1))[:b],
                np.tile(sc.pixels_after, (reps, 1, 1))[:b],
                dtype,
                transfer,
            )
            sweep[str(b)] |= {f"jax_batched_{name}_{key}": val for key, val in t.items()}
            print(f"batch {b} {name}: {t}", flush=True)
        jax_us = sweep[str(batches[0])][f"jax_batched_{name}_us_per_problem"]
        out |= {
            f"ours_{name}_rotation_median_deg": float(np.median(ours)),
            f"ours_{name}_valid_rate": float(np.asarray(res.valid).mean()),
            f"jax_batched_{name}_us_per_problem": jax_us,
            f"speedup_jax_batched_{name}_over_opencv": cv_us / jax_us,
        }
    # after the JAX runs too: the OpenCV loop again, the faster of the two (contention)
    t0 = time.perf_counter()
    for i in range(n):
        opencv_pnp(
            sc.pixels_before[i],
            sc.pixels_after[i],
            _frontal_face(sc.corners_before[i]),
            k,
            cfg.edge,
        )
    cv_us = min(cv_us, (time.perf_counter() - t0) / n * 1e6)
    out["opencv_loop_us_per_problem"] = cv_us
    for name in ("f64_iters10", "f32_iters5"):
        out[f"speedup_jax_batched_{name}_over_opencv"] = (
            cv_us / out[f"jax_batched_{name}_us_per_problem"]
        )
        for d in sweep.values():
            d[f"speedup_jax_batched_{name}_over_opencv"] = (
                cv_us / d[f"jax_batched_{name}_us_per_problem"]
            )
    if len(batches) > 1 or transfer:
        out["sweep"] = sweep
    out["opencv_cpu"] = _cpu_model()
    out["opencv_threads"] = cv2.getNumThreads()
    out["jax_device"] = str(jax.devices()[0])
    out["ours_rotation_median_deg"] = out["ours_f64_iters10_rotation_median_deg"]
    out["ratio_ours_over_ippe"] = out["ours_rotation_median_deg"] / out["ippe_rotation_median_deg"]
    return out


def rendered(seed: int, seconds: float) -> dict:
    render_swing = _load(_ROOT / "experiments" / "eye.py", "experiment_eye").render_swing

    from hec_jax.geometry.track import track_box

    rng = np.random.default_rng(seed)
    angle = float(rng.uniform(0.3, 0.6))
    seq = render_swing(angle, int(round(seconds * 30)))
    # compile on the same sequence: a short warm-up may never reach the tracked path (or the
    # smoother's padded length), and the timed run would include compilation
    t0 = time.perf_counter()
    track_box(seq.frames, seq.intrinsics, 0.1, 30.0)
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    tr = track_box(seq.frames, seq.intrinsics, 0.1, 30.0)
    wall = time.perf_counter() - t0
    return {"release_rad": angle, "first_call_s": compile_s, "wall_s": wall, **summarise(seq, tr)}


def summarise(seq, tr) -> dict:
    v = tr.valid
    rms = lambda a, b: float(np.sqrt(np.mean(np.sum((a - b) ** 2, -1)[v])))  # noqa: E731
    phi = seq.rotation @ seq.rotation[0].T
    rot = rotation_error_deg(tr.rotation, phi)[v]
    return {
        "frames": int(len(v)),
        "valid_rate": float(v.mean()),
        "position_rms_mm": 1e3 * rms(tr.position, seq.position),
        "measured_position_rms_mm": 1e3 * rms(tr.measured_position, seq.position),
        "velocity_rms_m_s": rms(tr.velocity, seq.velocity),
        "acceleration_rms_m_s2": rms(tr.acceleration, seq.acceleration),
        "rotation_median_deg": float(np.median(rot)),
        "rotation_p90_deg": float(np.percentile(rot, 90)),
        "causal_position_rms_mm": 1e3 * rms(tr.causal_position, seq.position),
        "causal_velocity_rms_m_s": rms(tr.causal_velocity, seq.velocity),
        "causal_acceleration_rms_m_s2": rms(tr.causal_acceleration, seq.acceleration),
        "causal_rotation_median_deg": float(
            np.median(rotation_error_deg(tr.causal_rotation, phi)[v])
        ),
        "latency_ms": tr.timing_ms,
    }


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=Path("runs/eye_pipeline"))
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--scenes", type=int, default=1000)
    p.add_argument("--batch", type=int, nargs="+", default=[10000])
    p.add_argument("--seconds", type=float, default=5.0)
    p.add_argument("--synthetic-only", action="store_true", help="skip the rendered swing")
    p.add_argument("--transfer", action="store_true", help="also time with host<->device copies")
    a = p.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    settings = {"scenes": a.scenes, "batch": a.batch[0] if len(a.batch) == 1 else a.batch}
    settings |= {"seconds": a.seconds, "synthetic_only": a.synthetic_only}
    settings |= {"opencv": cv2.__version__, "cpu": _cpu_model(), "os_cpu_count": os.cpu_count()}
    folder = start_run(a.out, a.seed, settings)
    syn = synthetic(np.random.default_rng(a.seed), a.scenes, a.batch, a.transfer)
    print("synthetic:", syn, flush=True)
    metrics = {"synthetic_two_frame_0.5px": syn}
    if not a.synthetic_only:
        ren = rendered(a.seed, a.seconds)
        print("rendered:", ren, flush=True)
        metrics["rendered_swing"] = ren
    write_json(folder / "metrics.json", metrics)
    lines = ["| quantity | value |", "|---|---|"]
    for part, d in metrics.items():
        for key, val in d.items():
            txt = val if isinstance(val, (dict, str)) else f"{val:.4g}"
            lines.append(f"| {part}: {key} | {txt} |")
    sweep = syn.get("sweep")
    if sweep:
        cv_us = syn["opencv_loop_us_per_problem"]
        lines += [
            "",
            f"Batch sweep ({syn['jax_device']}; OpenCV loop {cv_us:.1f} us per problem)",
            "",
        ]
        lines += ["| batch | dtype, LM iterations | JAX us/problem | with transfer | speedup |"]
        lines += ["|---|---|---|---|---|"]
        for b, d in sweep.items():
            for name in ("f64_iters10", "f32_iters5"):
                us = d[f"jax_batched_{name}_us_per_problem"]
                tr = d.get(f"jax_batched_{name}_with_transfer_us_per_problem", float("nan"))
                lines.append(f"| {b} | {name} | {us:.4g} | {tr:.4g} | {cv_us / us:.3g}x |")
    write_text(folder / "table.md", "\n".join(lines) + "\n")
    print("\n".join(lines))
    return metrics


if __name__ == "__main__":
    main()
