"""The closed hand-eye loop: the object's state comes only from rendered camera frames.

Wires the world (``hec_jax.mjx_scene``: MJX physics, C rendering), the eye (``hec_jax.geometry``:
the online :class:`~hec_jax.geometry.BoxTracker`) and the hand with its learner
(``experiments.task_loop``) together at the NumPy boundary:

* The camera takes a frame every 1/fps [s] (30 fps default), rounded to a whole number of 1 ms
  control steps (33 ms, i.e. 30.3 fps, for 30 fps; the eye is told the rounded rate). A frame
  shows the state at the middle of its exposure (``exposure_s``; motion blur is not modelled).
* Each frame goes through the eye (LSD segments, box fit, constant-acceleration Kalman filter);
  its estimate reaches the controller ``latency_s`` after the end of the exposure.
* Between estimates the controller predicts the object's state from the last one with the filter's
  constant-acceleration model (``task_loop.eye_object_state``), every 1 ms, inside the jitted
  ``lax.scan`` of one inter-frame segment; the learner runs in the same scan.
* Frames where the estimator fails (hand occluding the cube, no fit, lost track) leave the filter
  coasting on its prediction; they are counted. Before the first estimate of a swing the virtual
  force and learning are off (nothing has been seen).

Seeds (network initialisations) are ``vmap``-ed in the physics; each seed has its own world, camera
frames and tracker. Successive swings restart the world at the release and carry the learner's
weights over (as ``task_loop``); the tracker is reset at each release (a new throw).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import jax
import jax.numpy as jnp
import numpy as np

from experiments import task_loop as tl
from hec_jax.geometry import BoxTracker, TrackConfig
from hec_jax.mjx_scene import CUBE_EDGE, load_mj_model, rollout
from hec_jax.mjx_scene.frames import SceneCamera, render_model_like

_AX = np.array([0, 2])  # task axes (x, z) of the world frame


@dataclass(frozen=True)
class CameraConfig:
    """Timing and resolution of the eye in the loop."""

    fps: float = 30.0  # frame rate [1/s]
    latency_s: float = 1.0 / 30.0  # end of exposure -> estimate at the controller [s]
    exposure_s: float = 0.004  # the frame shows the state at mid-exposure [s]
    width: int = 640  # [px]
    height: int = 480  # [px]
    fast_render: bool = True  # no shadows/reflections (3x faster software rendering)
    track: TrackConfig = field(default_factory=TrackConfig)

    def __post_init__(self):
        for name in ("fps", "width", "height"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        for name in ("latency_s", "exposure_s"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {v}")


def steps_per_frame(cam: CameraConfig, dt: float) -> int:
    """Control steps between frames: 1 / (fps dt) rounded (at least 1)."""
    return max(int(round(1.0 / (cam.fps * dt))), 1)


def frame_steps(cam: CameraConfig, dt: float, steps: int) -> np.ndarray:
    """Simulation steps at which the frames' exposures end (state at the start of that step)."""
    return np.arange(0, steps, steps_per_frame(cam, dt))


class _Estimate:
    """One frame's estimate in world task coordinates, and when the controller gets it."""

    __slots__ = ("t_avail", "t_stamp", "x", "xd", "xdd")

    def __init__(self, t_avail, t_stamp, x, xd, xdd):
        self.t_avail, self.t_stamp, self.x, self.xd, self.xdd = t_avail, t_stamp, x, xd, xdd


def _eye_input(queue: list[_Estimate], t0: float, t1: float) -> tl.EyeInput:
    """The estimates in force during [t0, t1): the newest that arrived by t0 and the first that
    arrives inside the segment (if any)."""
    eps = 1e-9
    old = [e for e in queue if e.t_avail <= t0 + eps]
    new = [e for e in queue if t0 + eps < e.t_avail < t1 - eps]
    if not old:  # nothing seen yet (one arriving mid-segment counts from the next segment)
        z = np.zeros((2, 2))
        return tl.EyeInput(1.0, 0.0, np.zeros(2), np.inf, z, z, z)
    a = old[-1]
    b = new[0] if new else a
    return tl.EyeInput(
        use=1.0,
        seen=1.0,
        t_stamp=np.array([a.t_stamp, b.t_stamp]),
        t_switch=b.t_avail if new else np.inf,
        x=np.stack([a.x, b.x]),
        xd=np.stack([a.xd, b.xd]),
        xdd=np.stack([a.xdd, b.xdd]),
    )


def _stack_eye(inputs: list[tl.EyeInput]) -> tl.EyeInput:
    return jax.tree_util.tree_map(lambda *x: jnp.asarray(np.stack(x), float), *inputs)


def make_segment(config: tl.TaskConfig, loop: tl.Loop, pendulum):
    """``segment(d, cs, ls, f_prev, switches, active) -> (d, cs, ls, rows)`` for a batch of seeds:
    ``len(active)`` control steps of the closed loop from ``d`` in one ``lax.scan``, of which the
    ``active`` ones advance the state (so a shorter last segment shares the compiled function);
    ``switches`` carries each seed's :class:`~task_loop.EyeInput` (leading seed axis)."""

    def one(d, cs, ls, f_prev, sw, active):
        ps0 = (cs, ls, sw)
        f_ext = jnp.zeros((active.shape[0], 3), f_prev.dtype)
        (d, (cs, ls, _)), traj = rollout(
            loop.mx, loop.ids, d, loop.policy, ps0, f_ext, pendulum, f_prev, active
        )
        rows = dict(traj.aux, f_contact=traj.f_contact, t=traj.t, qpos=traj.qpos, qvel=traj.qvel)
        return d, cs, ls, rows

    sw_axes = tl.Switches(None, None, tl.EyeInput(*(0,) * 7))
    return jax.jit(jax.vmap(one, in_axes=(0, 0, 0, 0, sw_axes, None)))


def make_start(loop: tl.Loop):
    """``start(ls, switches) -> (d0, cs0)`` at the release, for a batch of seeds."""

    def one(ls, sw):
        d0 = loop.initial_data()
        cs0, _, _ = loop.initial_policy_state(d0, ls, sw)
        return d0, cs0

    return jax.jit(jax.vmap(one, in_axes=(0, None)))


def _draw_overlay(frame: np.ndarray, step, k: np.ndarray, r_cam_world, t_cam_world, x_true_world):
    """The frame with the detected edges (green), the estimated centre (red) and the true centre
    (blue, for reference) drawn on it; BGR for OpenCV's writer."""
    img = np.ascontiguousarray(frame[..., ::-1])
    for seg in np.asarray(step.segments):
        if np.all(np.isfinite(seg)):
            p0, p1 = (tuple(int(round(v)) for v in pt) for pt in seg)
            cv2.line(img, p0, p1, (0, 255, 0), 2, cv2.LINE_AA)

    def dot(p_cam, colour):
        if p_cam[2] > 1e-6:
            u = k @ (p_cam / p_cam[2])
            cv2.circle(img, (int(round(u[0])), int(round(u[1]))), 4, colour, -1, cv2.LINE_AA)

    if bool(step.initialised):
        dot(np.asarray(step.position), (0, 0, 255))
    dot(r_cam_world @ (x_true_world - t_cam_world), (255, 0, 0))
    return img


def write_video(path: Path, frames_bgr: list[np.ndarray], fps: float) -> None:
    """MP4 (mp4v) written next to its final name and renamed (atomic)."""
    if not frames_bgr:
        return
    h, w = frames_bgr[0].shape[:2]
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
    try:
        for f in frames_bgr:
            writer.write(f)
    finally:
        writer.release()
    os.replace(tmp, path)


def run_camera(
    config: tl.TaskConfig,
    pendulum,
    keys: jax.Array,
    condition: str,
    cam: CameraConfig = CameraConfig(),
    video_swing: int | None = None,
    progress: bool = True,
    corrupt=None,
):
    """One condition with the object's state from the camera, for a batch of seeds.

    Args:
        config: the task (catching or hitting); ``config.final_steps`` is not supported here.
        pendulum: scalar :class:`~hec_jax.mjx_scene.PendulumConditions`.
        keys: (n_seeds, 2) PRNG keys (network initialisations).
        condition: "plain", "frozen" or "learned".
        cam: camera timing and resolution.
        video_swing: swing whose frames of seed 0 are kept with overlays (None: none).
        progress: print one line per swing.
        corrupt: optional ``(seed, swing, frame, image) -> image`` applied to each rendered frame
            before the eye sees it (occluders, dropped frames, noise: robustness tests).

    Returns:
        (logs, eye, video): ``logs`` as ``task_loop.make_experiment`` (arrays (n_seeds, swings,
        steps, ...)); ``eye``: per-frame arrays (n_seeds, swings, frames): ``t_stamp`` [s],
        ``valid``, ``initialised``, ``x_est``/``x_true`` [m] (..., 2) task-plane centre at the
        frame's time, ``xd_est`` [m/s], and per-frame ``eye_ms``, ``render_ms`` plus
        ``sim_ms`` per segment and the wall time; ``video``: BGR frames with overlays.
    """
    if config.final_steps:
        raise ValueError("camera runs do not support final_steps")
    loop = tl.build_loop(config, pendulum)
    dt = config.controller.dt
    steps = config.swing_steps
    period = steps_per_frame(cam, dt)
    fps = 1.0 / (period * dt)  # the camera's rate on the control grid [1/s]
    fs = frame_steps(cam, dt, steps)
    bounds = np.append(fs, steps)
    e_off = int(round(0.5 * cam.exposure_s / dt))
    n_seeds = keys.shape[0]
    m_c = load_mj_model()
    m_render = render_model_like(m_c, loop.mx)
    camera = SceneCamera(m_render, "eye", cam.width, cam.height, cam.fast_render)
    r_wc, t_wc = camera.world_from_camera
    dtype = jnp.float64 if jax.config.jax_enable_x64 else jnp.float32
    ls = jax.vmap(lambda k: loop.learner_init(k, dtype))(keys)
    sw0 = tl.switches(condition)
    start = make_start(loop)
    segment = make_segment(config, loop, pendulum)
    d_first, _ = start(ls, sw0)
    q0 = np.asarray(d_first.qpos[0])
    with SceneCamera(
        m_render, "eye", cam.width, cam.height, cam.fast_render, ("cube", "rod")
    ) as bg:
        background = bg.render(q0)
    trackers = [
        BoxTracker(camera.intrinsics, CUBE_EDGE, fps, cam.track, background) for _ in range(n_seeds)
    ]
    n_f = len(fs)
    eye = {
        "t_stamp": np.zeros((n_seeds, config.swings, n_f)),
        "valid": np.zeros((n_seeds, config.swings, n_f), bool),
        "initialised": np.zeros((n_seeds, config.swings, n_f), bool),
        "x_est": np.full((n_seeds, config.swings, n_f, 2), np.nan),
        "xd_est": np.full((n_seeds, config.swings, n_f, 2), np.nan),
        "x_true": np.zeros((n_seeds, config.swings, n_f, 2)),
        "eye_ms": np.zeros((n_seeds, config.swings, n_f)),
        "render_ms": np.zeros((n_seeds, config.swings, n_f)),
        "sim_ms": np.zeros((config.swings, n_f)),
        "swing_wall_s": np.zeros(config.swings),
    }
    video: list[np.ndarray] = []
    swing_logs = []
    t_wall = time.perf_counter()
    try:
        for swing in range(config.swings):
            d, cs = start(ls, sw0)
            f_prev = jnp.zeros((n_seeds, 3), dtype)
            for tr in trackers:
                tr.reset()
            queues: list[list[_Estimate]] = [[] for _ in range(n_seeds)]
            qpos_hist = np.zeros((n_seeds, steps, m_c.nq))
            rows_all = []
            d_qpos = np.asarray(d.qpos)
            for j, s in enumerate(fs):
                s_img = max(s - e_off, 0)
                for i in range(n_seeds):
                    qpos = d_qpos[i] if s_img == s else qpos_hist[i, s_img]
                    t0 = time.perf_counter()
                    frame = camera.render(qpos)
                    if corrupt is not None:
                        frame = corrupt(i, swing, j, frame)
                    t1 = time.perf_counter()
                    st = trackers[i].update(frame)
                    eye["render_ms"][i, swing, j] = 1e3 * (t1 - t0)
                    eye["eye_ms"][i, swing, j] = 1e3 * (time.perf_counter() - t1)
                    x_true = camera.data.xpos[
                        loop.ids.cube_body
                    ].copy()  # after render's kinematics
                    eye["t_stamp"][i, swing, j] = s_img * dt
                    eye["valid"][i, swing, j] = bool(st.valid)
                    eye["initialised"][i, swing, j] = bool(st.initialised)
                    eye["x_true"][i, swing, j] = x_true[_AX]
                    if st.initialised:
                        p, v, a = camera.to_world(st.position, st.velocity, st.acceleration)
                        eye["x_est"][i, swing, j] = p[_AX]
                        eye["xd_est"][i, swing, j] = v[_AX]
                        queues[i].append(
                            _Estimate(s * dt + cam.latency_s, s_img * dt, p[_AX], v[_AX], a[_AX])
                        )
                    if i == 0 and swing == video_swing:
                        video.append(
                            _draw_overlay(frame, st, camera.intrinsics, r_wc.T, t_wc, x_true)
                        )
                t0s, t1s = s * dt, bounds[j + 1] * dt
                eyes = _stack_eye([_eye_input(q, t0s, t1s) for q in queues])
                sw = tl.Switches(sw0.use_virtual, sw0.learn, eyes)
                t0 = time.perf_counter()
                n = int(bounds[j + 1] - s)
                d, cs, ls, rows = segment(d, cs, ls, f_prev, sw, np.arange(period) < n)
                rows = jax.tree_util.tree_map(lambda x, n=n: x[:, :n], jax.device_get(rows))
                eye["sim_ms"][swing, j] = 1e3 * (time.perf_counter() - t0)
                f_prev = rows["f_contact"][:, -1]
                qpos_hist[:, s : bounds[j + 1]] = rows["qpos"]
                d_qpos = np.asarray(d.qpos)
                rows_all.append(rows)
            ls = ls._replace(was_inside=jnp.zeros_like(ls.was_inside))
            eye["swing_wall_s"][swing] = time.perf_counter() - t_wall - eye["swing_wall_s"].sum()
            swing_logs.append(
                {k: np.concatenate([r[k] for r in rows_all], axis=1) for k in rows_all[0]}
            )
            if progress:
                ok = eye["valid"][:, swing].mean()
                print(
                    f"  {condition:8s} swing {swing + 1:2d}/{config.swings}: "
                    f"{100 * ok:5.1f}% frames valid, {time.perf_counter() - t_wall:6.1f} s",
                    flush=True,
                )
    finally:
        camera.close()
    eye["wall_s"] = time.perf_counter() - t_wall
    eye["fps"] = fps
    logs = {k: np.stack([sl[k] for sl in swing_logs], axis=1) for k in swing_logs[0]}
    return logs, eye, video


def eye_metrics(eye: dict, logs: dict, swing_s: float, n_seeds: int) -> dict:
    """Counts and accuracy of the eye in the loop, and the real-time factor."""
    init = eye["initialised"]
    lost = init[..., :-1] & ~init[..., 1:]  # a track held on one frame and gone on the next
    err = eye["x_est"] - eye["x_true"]
    on = logs["object_seen"]  # steps where the controller had an estimate
    used = (logs["x_o"] - logs["x_o_true"])[on]
    used_v = (logs["xd_o"] - logs["xd_o_true"])[on]
    seen = np.isfinite(eye["x_est"][..., 0])
    sim_s = swing_s * logs["x_o"].shape[1]
    wall = float(eye["wall_s"])
    per_frame = eye["eye_ms"].ravel()
    return {
        "frames": int(init.size),
        "frames_valid": int(eye["valid"].sum()),
        "frames_failed": int((~eye["valid"]).sum()),
        "frames_failed_while_tracking": int((~eye["valid"] & init).sum()),
        "tracks_lost": int(lost.sum()),
        "position_rms_at_frames_m": float(np.sqrt(np.mean(err[seen] ** 2))),
        "controller_position_rms_m": float(np.sqrt(np.mean(used**2))),
        "controller_velocity_rms_m_s": float(np.sqrt(np.mean(used_v**2))),
        "eye_ms_median": float(np.median(per_frame)),
        "eye_ms_p95": float(np.percentile(per_frame, 95)),
        "render_ms_median": float(np.median(eye["render_ms"])),
        "sim_ms_per_segment_median": float(np.median(eye["sim_ms"])),
        "wall_s": wall,
        "real_time_factor": sim_s / wall,  # simulated time of one world / wall time
        "real_time_factor_all_worlds": n_seeds * sim_s / wall,
        # without the first swing (compilation)
        "real_time_factor_warm": float(
            swing_s * (len(eye["swing_wall_s"]) - 1) / max(eye["swing_wall_s"][1:].sum(), 1e-9)
        ),
    }


def run_conditions_camera(
    config: tl.TaskConfig,
    pendulum,
    seed: int,
    n_seeds: int,
    cam: CameraConfig = CameraConfig(),
    video_condition: str = "learned",
):
    """The three conditions with the camera in the loop, and with ground truth for comparison.

    ``plain`` (F_o = 0) does not use the object's state at all, so its camera run is the ground-
    truth run; ``frozen`` and ``learned`` run :func:`run_camera`. Returns
    ``(camera_logs, truth_logs, timing, eye_by_condition, video)``: logs per condition as
    ``task_loop.run_conditions``; ``video`` the last swing of seed 0 of ``video_condition``.
    """
    truth, timing = tl.run_conditions(config, pendulum, seed, n_seeds)
    keys = jax.random.split(jax.random.PRNGKey(seed), n_seeds)
    camera_logs, eyes, video = {"plain": truth["plain"]}, {}, []
    for condition in ("frozen", "learned"):
        want = condition == video_condition
        logs, eye, frames = run_camera(
            config, pendulum, keys, condition, cam, config.swings - 1 if want else None
        )
        camera_logs[condition], eyes[condition] = logs, eye
        timing[f"{condition}_camera"] = eye["wall_s"]
        video = frames if want else video
    return camera_logs, truth, timing, eyes, video


# ---------------------------------------------------------------------------------------------
# Command line and report shared by catching.py and hitting.py (NumPy boundary).


def add_camera_args(parser, default: str = "camera") -> None:
    """``--eye camera|truth`` and the camera's timing."""
    parser.add_argument(
        "--eye",
        choices=("camera", "truth"),
        default=default,
        help="object state from rendered camera frames through the eye, or from the simulator",
    )
    parser.add_argument("--fps", type=float, default=30.0, help="camera frame rate [1/s]")
    parser.add_argument(
        "--latency-ms", type=float, default=1e3 / 30.0, help="exposure end -> controller [ms]"
    )
    parser.add_argument("--exposure-ms", type=float, default=4.0, help="exposure time [ms]")


def camera_from_args(args) -> CameraConfig:
    return CameraConfig(
        fps=args.fps, latency_s=1e-3 * args.latency_ms, exposure_s=1e-3 * args.exposure_ms
    )


def run_task(args, config: tl.TaskConfig, pendulum):
    """All three conditions with the object state from ``args.eye``.

    Returns ``(logs, extra)``: ``logs`` {condition: logs} as ``task_loop.run_conditions``;
    ``extra`` holds ``timing`` and, for camera runs, ``truth`` (the ground-truth-state logs of
    the same seeds), ``eyes`` (per-frame eye records of frozen and learned) and ``video``.
    """
    if args.eye == "truth":
        logs, timing = tl.run_conditions(config, pendulum, args.seed, args.seeds)
        return logs, {"timing": timing}
    cam = camera_from_args(args)
    logs, truth, timing, eyes, video = run_conditions_camera(
        config, pendulum, args.seed, args.seeds, cam
    )
    return logs, {"timing": timing, "truth": truth, "eyes": eyes, "video": video}


def camera_report(folder: Path, config: tl.TaskConfig, logs: dict, extra: dict, peak_of) -> dict:
    """Metrics of a camera run against its ground-truth twin; writes ``hand_eye.mp4``.

    ``peak_of(logs, condition) -> (n_seeds,)`` is the task's peak-force measure. Returns
    {"eye": per-condition :func:`eye_metrics`, "truth_peak_force": mean/std per condition,
    "camera_over_truth_peak": ratio of the means per condition}.
    """
    if "eyes" not in extra:
        return {}
    swing_s = config.swing_steps * config.controller.dt
    truth = extra["truth"]
    n_seeds = logs["learned"]["x_e"].shape[0]
    out = {"eye": {}, "truth_peak_force": {}, "camera_over_truth_peak": {}}
    for condition in tl.CONDITIONS:
        pt, pc = peak_of(truth[condition], condition), peak_of(logs[condition], condition)
        out["truth_peak_force"][condition] = tl.mean_std(pt)
        out["camera_over_truth_peak"][condition] = float(np.mean(pc) / np.mean(pt))
        if condition in extra["eyes"]:
            out["eye"][condition] = eye_metrics(
                extra["eyes"][condition], logs[condition], swing_s, n_seeds
            )
    out["eye"]["fps"] = float(extra["eyes"]["learned"]["fps"])
    write_video(folder / "hand_eye.mp4", extra["video"], out["eye"]["fps"])
    return out
