"""Render a swing of the scene's cube, track it with ``track_box``, plot estimated vs true state
and write a video with the associated segments drawn on the frames.

Outputs in --out: config.json, metrics.json, track.npz, state.png, rotation_error.png, eye.mp4
(cv2.VideoWriter, mp4v).
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")  # headless rendering (before mujoco is imported)

import cv2  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from hec_jax.geometry import rotation_error_deg  # noqa: E402
from hec_jax.geometry.render import render_rollout  # noqa: E402
from hec_jax.runs import save_figure, start_run, write_json, write_npz  # noqa: E402

FPS = 30.0
EDGE = 0.1


def render_swing(angle: float, n_frames: int):
    """Frames and ground truth of the pendulum released at ``angle`` [rad], arm held still."""
    from hec_jax.mjx_scene import SCENE_XML

    m = mujoco.MjModel.from_xml_path(str(SCENE_XML))
    d = mujoco.MjData(m)
    d.qpos[m.jnt_qposadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, "hinge")]] = angle
    arm = [
        m.jnt_dofadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, j)]
        for j in ("shoulder", "elbow", "wrist")
    ]
    return render_rollout(m, d, n_frames, FPS, "eye", "cube", hold_dofs=arm)


def write_video(path: Path, frames: np.ndarray, track) -> bool:
    h, w = frames.shape[1:3]
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), FPS, (w, h))
    if not vw.isOpened():
        return False
    for i, f in enumerate(frames):
        img = np.ascontiguousarray(f[..., ::-1])
        for s in track.segments[i]:
            if np.all(np.isfinite(s)):
                a, b = (s - 0.5).round().astype(int)  # intrinsics -> OpenCV pixel coordinates
                cv2.line(img, tuple(a), tuple(b), (0, 255, 0) if track.valid[i] else (0, 0, 255), 1)
        vw.write(img)
    vw.release()
    return True


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=Path("runs/eye"))
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--seconds", type=float, default=5.0)
    p.add_argument("--release", type=float, default=None, help="release angle [rad]")
    a = p.parse_args(argv)
    import jax

    jax.config.update("jax_enable_x64", True)
    from hec_jax.geometry.track import track_box

    angle = (
        a.release
        if a.release is not None
        else float(np.random.default_rng(a.seed).uniform(0.3, 0.6))
    )
    folder = start_run(a.out, a.seed, {"seconds": a.seconds, "release_rad": angle, "fps": FPS})
    seq = render_swing(angle, int(round(a.seconds * FPS)))
    # the first call compiles (tens of seconds on 2 cores): track twice and report the latency of
    # the warm second pass, as benchmarks/eye_pipeline.py does
    t0 = time.perf_counter()
    track_box(seq.frames, seq.intrinsics, EDGE, FPS)
    first_call_s = time.perf_counter() - t0
    tr = track_box(seq.frames, seq.intrinsics, EDGE, FPS)
    phi = seq.rotation @ seq.rotation[0].T
    rot_err = rotation_error_deg(tr.rotation, phi)
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        "eye_pipeline", Path(__file__).resolve().parents[1] / "benchmarks" / "eye_pipeline.py"
    )
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    summarise = mod.summarise

    metrics = summarise(seq, tr) | {"first_call_s": first_call_s}
    write_json(folder / "metrics.json", metrics)
    write_npz(
        folder / "track.npz",
        position=tr.position,
        velocity=tr.velocity,
        acceleration=tr.acceleration,
        rotation=tr.rotation,
        valid=tr.valid,
        true_position=seq.position,
        true_velocity=seq.velocity,
        true_acceleration=seq.acceleration,
        true_rotation=phi,
        causal_position=tr.causal_position,
        causal_velocity=tr.causal_velocity,
        causal_acceleration=tr.causal_acceleration,
        causal_rotation=tr.causal_rotation,
    )
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 3, figsize=(12, 8), sharex=True)
    for row, (name, est, causal, true) in enumerate(
        [
            ("position [m]", tr.position, tr.causal_position, seq.position),
            ("velocity [m/s]", tr.velocity, tr.causal_velocity, seq.velocity),
            ("acceleration [m/s^2]", tr.acceleration, tr.causal_acceleration, seq.acceleration),
        ]
    ):
        for ax_i in range(3):
            ax = axes[row, ax_i]
            ax.plot(seq.times, true[:, ax_i], "k-", label="true")
            ax.plot(
                seq.times, np.where(tr.valid, causal[:, ax_i], np.nan), "b.", ms=2, label="causal"
            )
            ax.plot(seq.times, est[:, ax_i], "r-", lw=1, label="smoothed")
            ax.set_title(f"{name} {'xyz'[ax_i]} (camera)")
    axes[0, 0].legend()
    save_figure(fig, folder / "state.png")
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(6, 3))
    causal_err = rotation_error_deg(tr.causal_rotation, phi)
    ax.plot(seq.times, np.where(tr.valid, causal_err, np.nan), "b.", ms=3, label="causal")
    ax.plot(seq.times, np.where(tr.valid, rot_err, np.nan), "r.", ms=3, label="smoothed")
    ax.legend()
    ax.set_xlabel("t [s]")
    ax.set_ylabel("rotation error [deg]")
    save_figure(fig, folder / "rotation_error.png")
    plt.close(fig)
    metrics["video"] = write_video(folder / "eye.mp4", seq.frames, tr)
    print(metrics)
    return metrics


if __name__ == "__main__":
    main()
