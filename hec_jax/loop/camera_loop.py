"""The closed hand-eye loop: the object's state comes only from rendered camera frames.

Wires the world (``hec_jax.mjx_scene``: MJX physics, C rendering), the eye (``hec_jax.geometry``:
the online :class:`~hec_jax.geometry.BoxTracker`, ``eye="camera"``, or the paper's two-frame
method :class:`~hec_jax.geometry.PaperEye`, ``eye="paper"``) and the hand with its learner
(:mod:`hec_jax.loop.policy`) together at the NumPy boundary:

* The camera takes a frame every 1/fps [s] (30 fps default), rounded to a whole number of 1 ms
  control steps (33 ms, i.e. 30.3 fps, for 30 fps; the eye is told the rounded rate), the first
  ``frame_offset_s`` after each release (the trigger phase; 0 by default: at the release), or
  at a phase drawn for each release (``frame_offset_random``: a free-running camera). A frame
  shows the state at the middle of its exposure (``exposure_s``). The camera is perfect unless
  ``cam.applied_defects`` (:class:`~hec_jax.loop.config.CameraDefects`) says otherwise: motion blur
  (renders averaged over the exposure), defocus, sensor noise (:func:`camera_frame`), intrinsics
  known to the eye with an error (:func:`eye_intrinsics`) and jittered time stamps. The camera
  sees (``cam.scene = "lab"``, the default) a room with shadows from an oblique pose
  (:func:`hec_jax.mjx_scene.lab.lab_model`), or scene.xml in front of a black void
  (``"void"``); rendering only: the simulated model is ``loop``'s either way, and the eye's K
  and pose are read from the model rendered. ``CameraConfig()`` is the lab through the
  industrial camera (``CameraDefects.industrial()``).
* Each frame goes through the eye (box tracker: LSD segments, box fit, constant-acceleration
  Kalman filter; paper's eye: a face's parallel edges, Eqs. 1-38 on this and the previous frame,
  the same kind of filter); its estimate reaches the controller ``latency_s`` after the end of
  the exposure. Both eyes see the same frames (self-mask and inpainting included).
* Between estimates the controller predicts the object's state from the last one with the filter's
  constant-acceleration model (``object_state.eye_object_state``), every 1 ms, inside the jitted
  ``lax.scan`` of one inter-frame segment; the learner runs in the same scan.
* Frames where the estimator fails (hand occluding the cube, no fit, lost track) leave the filter
  coasting on its prediction; they are counted. Before the first estimate of a swing the virtual
  force and learning are off (nothing has been seen).

Seeds (network initialisations) are ``vmap``-ed in the physics; each seed has its own world, camera
frames and tracker. Successive swings restart the world at the release and carry the learner's
weights over (as :mod:`hec_jax.loop.episodes`); the tracker is reset at each release (a new throw).
"""

from __future__ import annotations

import time

import cv2
import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from hec_jax.geometry import BoxTracker, PaperEye
from hec_jax.geometry.box_model import project_corners_np
from hec_jax.geometry.paper_eye import STATUSES
from hec_jax.geometry.track import FIT_SOURCES
from hec_jax.loop.config import CameraConfig, CameraDefects
from hec_jax.loop.episodes import _float_dtype, run_conditions
from hec_jax.loop.object_state import EyeInput
from hec_jax.loop.policy import Loop, PolicyState, Switches, switches
from hec_jax.mjx_scene import CUBE_EDGE, PendulumConditions, rollout
from hec_jax.mjx_scene.lab import scene_model
from hec_jax.mjx_scene.render import SceneCamera, render_model_like, sensor, with_plane_grid
from hec_jax.progress import ProgressBar

_AX = np.array([0, 2])  # task axes (x, z) of the world frame


def steps_per_frame(cam: CameraConfig, dt: float) -> int:
    """Control steps between frames: 1 / (fps dt) rounded (at least 1)."""
    return max(int(round(1.0 / (cam.fps * dt))), 1)


def frame_offset_steps(cam: CameraConfig, dt: float) -> int:
    """Control steps from each release to the first frame's exposure end (the camera's trigger
    phase, ``CameraConfig.frame_offset_s``, rounded).

    Raises:
        ValueError: the offset rounds to a whole frame period or more.
    """
    offset = int(round(cam.frame_offset_s / dt))
    if offset >= steps_per_frame(cam, dt):
        raise ValueError(
            f"frame_offset_s {cam.frame_offset_s!r} rounds to {offset} control steps, not below "
            f"the frame period's {steps_per_frame(cam, dt)}"
        )
    return offset


def frame_steps(
    cam: CameraConfig, dt: float, steps: int, swing: int | str | None = None
) -> np.ndarray:
    """Simulation steps at which the frames' exposures end (state at the start of that step) in
    an episode of ``steps`` control steps, :func:`steps_per_frame` apart: from
    :func:`frame_offset_steps` on, or with ``cam.frame_offset_random`` from a phase drawn
    uniformly from the frame period's steps for episode ``swing`` (its index, or ``"final"``;
    :func:`defects_rng`'s ``"phase"`` stream, the same for every seed of a batch), keeping the
    frame count of the latest phase (every episode of a length has the same count).

    Raises:
        ValueError: ``cam.frame_offset_random`` without ``swing``; see :func:`frame_offset_steps`.
    """
    period = steps_per_frame(cam, dt)
    if not cam.frame_offset_random:
        return np.arange(frame_offset_steps(cam, dt), steps, period)
    if swing is None:
        raise ValueError("frame_offset_random draws each episode's phase: pass its swing")
    offset = int(defects_rng(cam.applied_defects, 0, swing, "phase").integers(period))
    count = len(np.arange(period - 1, steps, period))
    return np.arange(offset, steps, period)[:count]


def mid_exposure_steps(cam: CameraConfig, dt: float) -> int:
    """Steps from a frame's mid-exposure (the state the frame shows: its time) to the end of its
    exposure, ``round(exposure_s / (2 dt))``: the one offset the simulated loop, the real-time
    camera (:func:`hec_jax.realtime.workers.frame_state_step`) and the twin's latency
    (:func:`hec_jax.realtime.runner.twin_camera_latency_s`) share.
    """
    return int(round(0.5 * cam.exposure_s / dt))


def exposure_offsets(cam: CameraConfig, dt: float) -> np.ndarray:
    """Steps before the end of a frame's exposure at which the frame is rendered, the one
    nearest mid-exposure (the frame's time) last: one, at mid-exposure, with
    ``defects.blur_renders`` = 1, else the midpoints of that many equal parts of the exposure on
    the control grid (motion blur).
    """
    mid = mid_exposure_steps(cam, dt)
    n = cam.applied_defects.blur_renders
    if n == 1:
        return np.array([mid])
    back = np.array([int(round((k + 0.5) / n * cam.exposure_s / dt)) for k in range(n)])
    return back[np.argsort(np.abs(back - mid), kind="stable")[::-1]]


def camera_frame(
    camera: SceneCamera, qpos: np.ndarray, defects: CameraDefects, rng: np.random.Generator
) -> np.ndarray:
    """One (H, W, 3) uint8 frame from the renders at joint positions ``qpos`` (n, nq) (the
    exposure's, :func:`exposure_offsets`; more than one: their mean, rounded, as motion blur),
    with ``defects``' defocus and sensor noise (:func:`~hec_jax.mjx_scene.render.sensor`).
    ``camera.data`` is left at the last row's kinematics. Without defects: ``camera.render``'s
    frame itself.
    """
    if len(qpos) == 1:
        frame = camera.render(qpos[0])
    else:
        shots = [camera.render(q).astype(np.float32) for q in qpos]
        frame = np.round(np.mean(shots, axis=0)).astype(np.uint8)
    return sensor(frame, rng, defects.noise_grey, defects.defocus_px)


def eye_intrinsics(k: np.ndarray, defects: CameraDefects) -> np.ndarray:
    """The eye's (3, 3) K: the true ``k`` with fx, fy times (1 + ``focal_error``) and cx, cy
    moved by ``centre_error_px`` (a calibration error; the renderer keeps ``k``).
    """
    out = np.array(k, dtype=float)
    out[0, 0] *= 1.0 + defects.focal_error
    out[1, 1] *= 1.0 + defects.focal_error
    out[:2, 2] += defects.centre_error_px
    return out


DEFECT_STREAMS = ("noise", "jitter", "phase")


def defects_rng(
    defects: CameraDefects, seed_index: int, swing: int | str, stream: str = "noise"
) -> np.random.Generator:
    """The generator of one seed's frames in one swing (``"final"``: the continuous run;
    ``"background"``: the calibration shot of the empty scene): seeded by
    ``defects.defect_seed``, the seed's index in the batch and the swing. ``stream``: the sensor
    noise's (``"noise"``), the time stamps' (``"jitter"``) or the free-running camera's phase
    (``"phase"``, :func:`frame_steps`) own generator, so that turning
    one defect on or off leaves the other's draws as they were (since session 67: before, one
    generator served both, and a jitter ablation also changed the noise). The noise stream's
    seed is the one the single generator had, so runs without jitter give the same frames.

    Raises:
        ValueError: ``stream`` not one of ``DEFECT_STREAMS``.
    """
    if stream not in DEFECT_STREAMS:
        raise ValueError(f"stream must be one of {DEFECT_STREAMS}, got {stream!r}")
    swing_id = {"final": 1_000_000, "background": 1_000_001}.get(swing, swing)
    key = [defects.defect_seed, seed_index, swing_id]
    return np.random.default_rng(key if stream == "noise" else key + [DEFECT_STREAMS.index(stream)])


def stamp_jitter(defects: CameraDefects, rng: np.random.Generator) -> float:
    """One frame's time-stamp error [s]: uniform in [-jitter_s, jitter_s] (0 without a draw
    when ``jitter_s`` is 0).
    """
    return float(rng.uniform(-defects.jitter_s, defects.jitter_s)) if defects.jitter_s > 0 else 0.0


def frames_per_condition(loop: Loop, cam: CameraConfig | None = None) -> int:
    """Frames of one seed under one condition: every swing's, and the continuous run's."""
    cam = CameraConfig() if cam is None else cam
    dt = loop.ids.timestep
    n = loop.config.swings * len(frame_steps(cam, dt, loop.swing_steps, 0))
    final = frame_steps(cam, dt, loop.final_steps, "final") if loop.final_steps else ()
    return n + len(final)


class _Estimate:
    """One frame's estimate in world task coordinates, and when the controller gets it
    (``seen`` False: the eye has lost the object; the controller drops it).
    """

    __slots__ = ("t_avail", "t_stamp", "x", "xd", "xdd", "seen")

    def __init__(self, t_avail, t_stamp, x, xd, xdd, seen=True):
        self.t_avail, self.t_stamp, self.x, self.xd, self.xdd = t_avail, t_stamp, x, xd, xdd
        self.seen = seen


def _eye_input(
    queue: list[_Estimate], t0: float, t1: float, touch_guard: float, touch_memory: float
) -> EyeInput:
    """The estimates in force during [t0, t1): the newest that arrived by t0 and the first that
    arrives inside the segment (if any); ``touch_guard``, ``touch_memory`` [s] as in
    :class:`~hec_jax.loop.object_state.EyeInput`.
    """
    eps = 1e-9
    old = [e for e in queue if e.t_avail <= t0 + eps]
    new = [e for e in queue if t0 + eps < e.t_avail < t1 - eps]
    if not old or not old[-1].seen:
        # nothing seen yet or the track is lost (an estimate arriving mid-segment counts from
        # the next segment on)
        z = np.zeros((2, 2))
        return EyeInput(1.0, 0.0, np.zeros(2), np.inf, z, z, z, touch_guard, touch_memory)
    a = old[-1]
    b = new[0] if new and new[0].seen else a  # a loss reported mid-segment: from the next one
    return EyeInput(
        use=1.0,
        seen=1.0,
        t_stamp=np.array([a.t_stamp, b.t_stamp]),
        t_switch=b.t_avail if new else np.inf,
        x=np.stack([a.x, b.x]),
        xd=np.stack([a.xd, b.xd]),
        xdd=np.stack([a.xdd, b.xdd]),
        touch_guard=touch_guard,
        touch_memory=touch_memory,
    )


def _stack_eye(inputs: list[EyeInput]) -> EyeInput:
    return jax.tree_util.tree_map(lambda *x: jnp.asarray(np.stack(x), float), *inputs)


def make_segment(loop: Loop):
    """``segment(d, cs, ls, touch, f_prev, switches, active, conditions) -> (d, cs, ls, touch,
    rows)`` for a
    batch of seeds (``touch``: :class:`~hec_jax.loop.object_state.TouchMemory`):
    ``len(active)`` control steps of the closed loop from ``d`` in one ``lax.scan``, of which the
    ``active`` ones advance the state (so a shorter last segment shares the compiled function);
    ``switches`` carries each seed's :class:`~hec_jax.loop.object_state.EyeInput` (leading seed axis).
    """

    def one(d, cs, ls, touch, f_prev, sw, active, conditions):
        m = loop.model_for(conditions)
        ps0 = PolicyState(cs, ls, sw, touch)
        f_ext = jnp.zeros((active.shape[0], 3), f_prev.dtype)
        (d, ps), traj = rollout(m, loop.ids, d, loop.policy, ps0, f_ext, conditions, f_prev, active)
        rows = dict(traj.aux, f_contact=traj.f_contact, t=traj.t, qpos=traj.qpos, qvel=traj.qvel)
        return d, ps.controller, ps.learner, ps.touch, rows

    sw_axes = Switches(None, None, EyeInput(*(0,) * 9))
    return jax.jit(jax.vmap(one, in_axes=(0, 0, 0, 0, 0, sw_axes, None, None)))


def make_start(loop: Loop):
    """``start(ls, switches, conditions) -> (d0, cs0, touch0)`` at the release, for a batch of
    seeds.
    """

    def one(ls, sw, conditions):
        m = loop.model_for(conditions)
        d0 = loop.data_for(m, conditions)
        ps0 = loop.initial_policy_state(m, d0, ls, sw)
        return d0, ps0.controller, ps0.touch

    return jax.jit(jax.vmap(one, in_axes=(0, None, None)))


def robot_geoms(m, hand_body: int) -> np.ndarray:
    """Geom ids of the robot: every geom in the body subtree that holds the hand."""
    root = hand_body
    while m.body_parentid[root] != 0:
        root = m.body_parentid[root]
    return np.flatnonzero(m.body_rootid[m.geom_bodyid] == root)


def robot_mask(shape, camera: SceneCamera, geoms, margin: float, intrinsics=None) -> np.ndarray:
    """(H, W) uint8, 255 on the robot's own image, from its forward kinematics (``camera.data``)
    and the calibrated camera (``intrinsics``, the eye's K; None: ``camera.intrinsics``).

    Each sphere, capsule or cylinder of ``geoms`` is drawn at its pose: a disc, or a thick line
    between the axis end points with round ends, of the geom's radius + ``margin`` [m] at that
    depth (+1 px; conservative for the perspective silhouette at this camera's angles). The
    silhouette ignores occlusion: a geom behind another object covers that object's image too.
    """
    mask = np.zeros(shape[:2], np.uint8)
    r_wc, t_wc = camera.world_from_camera
    k = camera.intrinsics if intrinsics is None else intrinsics
    m, d = camera.model, camera.data

    def px(p_world):
        p = r_wc.T @ (p_world - t_wc)
        return (k @ (p / p[2]))[:2], p[2]

    for g in geoms:
        kind, size = int(m.geom_type[g]), m.geom_size[g]
        centre = d.geom_xpos[g]
        axis = d.geom_xmat[g].reshape(3, 3)[:, 2]
        if kind == int(mujoco.mjtGeom.mjGEOM_SPHERE):
            ends = (centre, centre)
        elif kind in (int(mujoco.mjtGeom.mjGEOM_CAPSULE), int(mujoco.mjtGeom.mjGEOM_CYLINDER)):
            ends = (centre - size[1] * axis, centre + size[1] * axis)
        else:
            continue
        (u0, z0), (u1, z1) = px(ends[0]), px(ends[1])
        if min(z0, z1) <= size[0]:
            continue
        r_px = k[0, 0] * (size[0] + margin) / min(z0, z1) + 1.0
        a, b = tuple(int(round(v)) for v in u0), tuple(int(round(v)) for v in u1)
        cv2.line(mask, a, b, 255, int(np.ceil(2 * r_px)))
        cv2.circle(mask, a, int(np.ceil(r_px)), 255, -1)
        cv2.circle(mask, b, int(np.ceil(r_px)), 255, -1)
    return mask


def mask_robot_and_replaced(
    frame: np.ndarray,
    camera: SceneCamera,
    geoms,
    margin: float,
    inpaint_geoms=(),
    intrinsics=None,
    keep=None,
) -> tuple[np.ndarray, np.ndarray]:
    """(``frame`` with the robot's own image (:func:`robot_mask`) painted black (the backdrop
    colour), except ``inpaint_geoms``, whose image is filled from its surroundings (OpenCV Telea,
    radius 3 px, in the bounding box of their mask + 8 px); (H, W) bool, the pixels replaced,
    painted or inpainted: what the eye cannot see there is unobservable, not missing
    (``BoxTracker.update``'s ``occluded``)).

    Inpainting is for the hand: its silhouette ignores occlusion, so next to a held cube it cuts
    a notch into the cube's image (the cube's nearer front face covers part of the hand's disc),
    and a black notch adds strong false edges across the cube's side (measured, short catching
    run: the eye lost the held cube on up to 52% of a swing's frames; inpainted, on none). A
    filled notch keeps the cube's colour inside and the backdrop's outside. ``intrinsics``: as
    :func:`robot_mask`. ``keep``: optional (H, W) bool, pixels left as rendered (an object in
    front of the robot there: :func:`front_object_mask`).
    """
    rest = [g for g in geoms if g not in set(inpaint_geoms)]
    arm = robot_mask(frame.shape, camera, rest, margin, intrinsics)
    if keep is not None:
        arm[keep] = 0
    # black where the mask is set (OpenCV's masked AND; NumPy's boolean assignment is slower)
    out = cv2.bitwise_and(frame, frame, mask=cv2.bitwise_not(arm))
    replaced = arm
    if len(inpaint_geoms):
        hand = robot_mask(frame.shape, camera, inpaint_geoms, margin, intrinsics)
        if keep is not None:
            hand[keep] = 0
        bx, by, bw, bh = cv2.boundingRect(hand)  # of the nonzero pixels
        if bw > 0:
            h, w = hand.shape
            y0, y1 = max(by - 8, 0), min(by + bh + 8, h)
            x0, x1 = max(bx - 8, 0), min(bx + bw + 8, w)
            out[y0:y1, x0:x1] = cv2.inpaint(
                out[y0:y1, x0:x1], hand[y0:y1, x0:x1], 3, cv2.INPAINT_TELEA
            )
            replaced = cv2.bitwise_or(arm, hand)
    return out, replaced.astype(bool)


def front_object_mask(shape, prediction, camera: SceneCamera, hand_geoms, intrinsics, size):
    """(H, W) bool: the box's predicted silhouette where the box is nearer the camera than the
    hand (centre depths), else None (no prediction, or the hand in front).

    The robot's mask (:func:`robot_mask`) ignores occlusion: drawn over a box held in front of
    the hand, it inpaints part of the box's own image. The eye's prediction for this frame
    (``prediction``: a :class:`~hec_jax.geometry.track.BoxPrediction` in the camera frame of
    ``intrinsics``) says where the box is; there the mask is not applied. A depth test per
    object, not per pixel: for a hand sphere touching a box, the nearer centre is the one in
    front where their images overlap.
    """
    if prediction is None or not bool(prediction.initialised) or not len(hand_geoms):
        return None
    r_wc, t_wc = camera.world_from_camera
    hand_depth = min(float((r_wc.T @ (camera.data.geom_xpos[g] - t_wc))[2]) for g in hand_geoms)
    if float(prediction.position[2]) >= hand_depth:
        return None
    corners = project_corners_np(prediction.pose_rotation, prediction.position, size, intrinsics)
    keep = np.zeros(shape[:2], np.uint8)
    cv2.fillConvexPoly(keep, cv2.convexHull(np.round(corners).astype(np.int32)), 1)
    return keep.astype(bool)


def _draw_overlay(frame: np.ndarray, step, k: np.ndarray, r_cam_world, t_cam_world, x_true_world):
    """The frame with the detected edges (green), the estimated centre (red) and the true centre
    (blue, for reference) drawn on it; BGR for OpenCV's writer.
    """
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


def make_eye(eye: str, intrinsics, fps: float, cam: CameraConfig, background):
    """One seed's eye on the loop's camera: ``"camera"``, the box tracker
    (:class:`~hec_jax.geometry.BoxTracker`, ``cam.tracker``), or ``"paper"``, the paper's two-frame
    method (:class:`~hec_jax.geometry.PaperEye`, ``cam.paper``); both take the RGB background.
    """
    if eye == "camera":
        return BoxTracker(intrinsics, CUBE_EDGE, fps, cam.tracker, background)
    if eye == "paper":
        return PaperEye(intrinsics, CUBE_EDGE, fps, cam.paper, background)
    raise ValueError(f"eye must be 'camera' or 'paper', got {eye!r}")


def _first_segment_line(ms: float) -> str:
    return f"camera loop: compile and first control segment {ms / 1e3:.1f} s"


def run_camera(
    loop: Loop,
    conditions: PendulumConditions,
    keys: jax.Array,
    condition: str,
    cam: CameraConfig | None = None,
    video_swing: int | str | None = None,
    progress: bool | ProgressBar = True,
    corrupt=None,
    compiled: tuple | None = None,
    eye_source: str = "camera",
    observe=None,
):
    """One condition with the object's state from the camera, for a batch of seeds.

    Args:
        loop: the task's loop (:func:`~hec_jax.loop.policy.build_loop`).
        conditions: scalar :class:`~hec_jax.mjx_scene.PendulumConditions`.
        keys: (n_seeds, 2) PRNG keys (network initialisations).
        condition: "plain", "frozen" or "learned".
        cam: camera timing, resolution and defects.
        video_swing: swing whose frames of seed 0 are kept with overlays ("final": the
            continuous run; None: none).
        progress: True: a progress bar over this condition's frames (:class:`~hec_jax.progress.
            ProgressBar`: elapsed and remaining time); an open bar: advanced by each frame of each
            seed (one bar across conditions, :func:`run_conditions_camera`); False: none.
        corrupt: optional ``(seed, swing, frame, image) -> image`` applied to each rendered frame
            before the eye sees it (occluders, dropped frames, noise: robustness tests).
        compiled: ``(make_start(loop), make_segment(loop))`` to reuse across calls (one compile).
        eye_source: ``"camera"`` (the box tracker) or ``"paper"`` (the paper's two-frame
            method), :func:`make_eye`.
        observe: optional ``(seed, swing, frame, image, occluded, camera, eye) -> None``, called
            with each frame as the eye gets it (after the robot's mask and ``corrupt``), the
            occluded pixels it is told (None where it is told none), the camera posed at mid-exposure
            (its ``data`` holds the simulator's poses then) and the eye, before the eye sees
            the frame: recording frames with their truth (``benchmarks/eye_depth.py``).

    Returns:
        (logs, eye, video): ``logs`` as :func:`~hec_jax.loop.episodes.make_episodes` (arrays (n_seeds, swings,
        steps, ...)); ``eye``: per-frame arrays (n_seeds, swings, frames): ``t_stamp`` [s],
        ``valid``, ``initialised``, ``x_est``/``x_true`` [m] (..., 2) task-plane centre at the
        frame's time, ``xd_est`` [m/s], ``status`` (the paper's eye: index into
        :data:`~hec_jax.geometry.paper_eye.STATUSES`, else -1), ``fit_source`` (the box
        tracker: index into :data:`~hec_jax.geometry.track.FIT_SOURCES`, else -1), and per-frame ``eye_ms``,
        ``render_ms`` (defects included), ``stamp_error_s`` (the time stamp's jitter) plus
        ``sim_ms`` per segment and the wall time; ``video``: BGR frames with overlays.
    """
    cam = CameraConfig() if cam is None else cam
    defects = cam.applied_defects  # resolved once (camera_model's values over the flags)
    config = loop.config
    dt = loop.ids.timestep
    period = steps_per_frame(cam, dt)
    fps = 1.0 / (period * dt)  # the camera's rate on the control grid [1/s]
    e_off = mid_exposure_steps(cam, dt)
    backs = exposure_offsets(cam, dt)  # the renders of one frame, mid-exposure (e_off) last
    guard = cam.touch_guard_frames * period * dt  # [s]
    memory = guard + cam.latency_s + cam.max_coast_frames * period * dt  # [s]
    n_seeds = keys.shape[0]
    m_c = scene_model(cam.scene)  # what the camera sees (the simulated model: ``loop``'s)
    m_render = with_plane_grid(render_model_like(m_c, loop.model_for(conditions)), cam.plane_grid_m)
    if cam.msaa is not None:
        m_render.vis.quality.offsamples = cam.msaa
    shadows = cam.scene == "lab"  # the lab's lights cast shadows, also with fast_render
    dtype = _float_dtype()
    sw0 = switches(condition)
    start, segment = (make_start(loop), make_segment(loop)) if compiled is None else compiled
    ls = jax.vmap(lambda k: loop.learner_init(k, dtype))(keys)
    q0 = np.asarray(start(ls, sw0, conditions)[0].qpos[0])
    with SceneCamera(
        m_render, "eye", cam.width, cam.height, cam.fast_render, ("cube", "rod"), shadows
    ) as bg:
        background = bg.render(q0)  # the static scene without the pendulum (a calibration shot)
    # taken by the same camera: its defocus and one shot's noise
    background = sensor(
        background,
        defects_rng(defects, 0, "background"),
        defects.noise_grey,
        defects.defocus_px,
    )
    camera = SceneCamera(m_render, "eye", cam.width, cam.height, cam.fast_render, (), shadows)
    k_eye = eye_intrinsics(camera.intrinsics, defects)  # what the eye believes
    r_wc, t_wc = camera.world_from_camera
    robot = robot_geoms(m_render, loop.ids.hand_body)
    hand = robot[m_render.geom_bodyid[robot] == loop.ids.hand_body]
    trackers = [make_eye(eye_source, k_eye, fps, cam, background) for _ in range(n_seeds)]
    own_bar = not isinstance(progress, ProgressBar)
    if own_bar:
        total = n_seeds * frames_per_condition(loop, cam)
        bar = ProgressBar(total, "frames", enabled=bool(progress))
    else:
        bar = progress

    def episode(ls, steps: int, index, keep_video: bool):
        """One release: ``steps`` control steps, the tracker reset at the release."""
        t_ep = time.perf_counter()
        fs = frame_steps(cam, dt, steps, index)
        if not len(fs):
            raise ValueError(f"an episode of {steps} steps ends before its first frame")
        bounds = np.append(fs, steps)
        n_f = len(fs)
        rec = {
            "t_stamp": np.zeros((n_seeds, n_f)),
            "valid": np.zeros((n_seeds, n_f), bool),
            "initialised": np.zeros((n_seeds, n_f), bool),
            "x_est": np.full((n_seeds, n_f, 2), np.nan),
            "xd_est": np.full((n_seeds, n_f, 2), np.nan),
            "x_true": np.zeros((n_seeds, n_f, 2)),
            "eye_ms": np.zeros((n_seeds, n_f)),
            "render_ms": np.zeros((n_seeds, n_f)),
            "sim_ms": np.zeros(n_f),
            "stamp_error_s": np.zeros((n_seeds, n_f)),
            # the paper's eye: why a frame is (in)valid, index into geometry.paper_eye.STATUSES
            # (-1: the box tracker, which gives none)
            "status": np.full((n_seeds, n_f), -1, np.int8),
            # the box tracker: which hypothesis gave the frame's fit, index into
            # geometry.track.FIT_SOURCES (0: not valid; -1: the paper's eye)
            "fit_source": np.full((n_seeds, n_f), -1, np.int8),
        }
        frames_out = []
        d, cs, touch = start(ls, sw0, conditions)
        f_prev = jnp.zeros((n_seeds, 3), dtype)
        for tr in trackers:
            tr.reset()
        rngs = [defects_rng(defects, i, index) for i in range(n_seeds)]  # the sensor noise's
        jitter_rngs = [defects_rng(defects, i, index, "jitter") for i in range(n_seeds)]
        queues: list[list[_Estimate]] = [[] for _ in range(n_seeds)]
        misses = np.zeros(n_seeds, int)  # frames since the last valid fit
        qpos_hist = np.zeros((n_seeds, steps, m_c.nq))
        rows_all = []
        d_qpos = np.asarray(d.qpos)
        swing = "final run" if index == "final" else f"swing {index + 1}/{config.swings}"
        bar.update(description=f"{condition} {swing}")

        def advance(start: int, end: int) -> float:
            """The closed loop from step ``start`` to ``end``, in segments of at most a frame
            period, each with the estimates in force during it; its wall time [ms].
            """
            nonlocal d, cs, ls, touch, f_prev, d_qpos
            t0 = time.perf_counter()
            while start < end:
                stop = min(start + period, end)
                eyes = _stack_eye(
                    [_eye_input(q, start * dt, stop * dt, guard, memory) for q in queues]
                )
                n = stop - start
                d, cs, ls, touch, rows = segment(
                    d,
                    cs,
                    ls,
                    touch,
                    f_prev,
                    Switches(sw0.use_virtual, sw0.learn, eyes),
                    np.arange(period) < n,
                    conditions,
                )
                rows = jax.tree_util.tree_map(lambda x, n=n: x[:, :n], jax.device_get(rows))
                f_prev = rows["f_contact"][:, -1]
                qpos_hist[:, start:stop] = rows["qpos"]
                d_qpos = np.asarray(d.qpos)
                rows_all.append(rows)
                start = stop
            return 1e3 * (time.perf_counter() - t0)

        # the steps before the first frame (a trigger phase): nothing seen yet; counted in the
        # first frame's sim_ms
        lead_ms = advance(0, int(fs[0]))
        for j, s in enumerate(fs):
            s_img = max(s - e_off, 0)  # mid-exposure
            for i in range(n_seeds):
                at = np.maximum(s - backs, 0)  # the exposure's steps
                qpos = np.stack([d_qpos[i] if t == s else qpos_hist[i, t] for t in at])
                t0 = time.perf_counter()
                frame = camera_frame(camera, qpos, defects, rngs[i])
                if at[-1] != s_img:  # motion blur without a render at mid-exposure
                    camera.pose(d_qpos[i] if s_img == s else qpos_hist[i, s_img])
                x_true = camera.data.xpos[loop.ids.cube_body].copy()  # mid-exposure kinematics
                shown = frame  # the video shows the camera's frame
                occluded = None  # the pixels the mask replaced, if the eye is told them
                if cam.self_mask_margin_m is not None:
                    keep = None
                    if cam.occlusion_aware_mask and isinstance(trackers[i], BoxTracker):
                        ahead = trackers[i].predict(1.0 / fps)  # this frame, from the last
                        keep = front_object_mask(frame.shape, ahead, camera, hand, k_eye, CUBE_EDGE)
                    frame, replaced = mask_robot_and_replaced(
                        frame,
                        camera,
                        robot,
                        cam.self_mask_margin_m,
                        hand if cam.inpaint_hand else (),
                        k_eye,
                        keep,
                    )
                    if cam.mask_aware_coverage and isinstance(trackers[i], BoxTracker):
                        occluded = replaced
                if corrupt is not None:
                    frame = corrupt(i, index, j, frame)
                if observe is not None:
                    observe(i, index, j, frame, occluded, camera, trackers[i])
                t1 = time.perf_counter()
                if occluded is None:
                    st = trackers[i].update(frame)
                else:  # the box tracker, told the pixels the mask replaced
                    st = trackers[i].update(frame, occluded)
                rec["render_ms"][i, j] = 1e3 * (t1 - t0)
                rec["eye_ms"][i, j] = 1e3 * (time.perf_counter() - t1)
                rec["t_stamp"][i, j] = s_img * dt
                jitter = stamp_jitter(defects, jitter_rngs[i])
                rec["stamp_error_s"][i, j] = jitter
                rec["valid"][i, j] = bool(st.valid)
                rec["initialised"][i, j] = bool(st.initialised)
                if eye_source == "paper":
                    rec["status"][i, j] = STATUSES.index(st.status)
                else:
                    rec["fit_source"][i, j] = FIT_SOURCES.index(st.fit_source)
                rec["x_true"][i, j] = x_true[_AX]
                misses[i] = 0 if st.valid else misses[i] + 1
                if st.initialised:
                    p, v, a = camera.to_world(st.position, st.velocity, st.acceleration)
                    rec["x_est"][i, j] = p[_AX]
                    rec["xd_est"][i, j] = v[_AX]
                    seen = misses[i] <= cam.max_coast_frames
                    queues[i].append(
                        _Estimate(
                            s * dt + cam.latency_s,
                            s_img * dt + jitter,
                            p[_AX],
                            v[_AX],
                            a[_AX],
                            seen,
                        )
                    )
                elif queues[i]:  # lost after having been seen
                    z = np.zeros(2)
                    queues[i].append(
                        _Estimate(s * dt + cam.latency_s, s_img * dt + jitter, z, z, z, False)
                    )
                if i == 0 and keep_video:
                    frames_out.append(_draw_overlay(shown, st, k_eye, r_wc.T, t_wc, x_true))
            rec["sim_ms"][j] = advance(int(s), int(bounds[j + 1])) + (lead_ms if j == 0 else 0.0)
            if j == 0 and index == 0 and compiled is None:  # compiled by this first call
                bar.log(_first_segment_line(rec["sim_ms"][0]))
            bar.update(n_seeds)
        ls = ls._replace(was_inside=jnp.zeros_like(ls.was_inside))
        logs = {k: np.concatenate([r[k] for r in rows_all], axis=1) for k in rows_all[0]}
        rec["wall_s"] = time.perf_counter() - t_ep
        bar.log(f"{condition} {swing}: {100 * rec['valid'].mean():5.1f}% frames valid")
        return ls, logs, rec, frames_out

    video: list[np.ndarray] = []
    runs = []
    try:
        if own_bar:
            bar.start()
        for swing in range(config.swings):
            ls, lg, rec, frames = episode(ls, loop.swing_steps, swing, swing == video_swing)
            runs.append((lg, rec))
            video += frames
        logs = {k: np.stack([lg[k] for lg, _ in runs], axis=1) for k in runs[0][0]}
        eye = {
            k: np.stack([rec[k] for _, rec in runs], axis=1)
            for k in runs[0][1]
            if k not in ("sim_ms", "wall_s")
        }
        eye["sim_ms"] = np.stack([rec["sim_ms"] for _, rec in runs])
        eye["wall_s"] = np.array([rec["wall_s"] for _, rec in runs])
        if loop.final_steps:
            ls, lg, rec, frames = episode(ls, loop.final_steps, "final", video_swing == "final")
            logs["final"] = {k: v[:, None] for k, v in lg.items()}
            eye["final"] = {
                k: v[:, None] if k not in ("sim_ms", "wall_s") else v for k, v in rec.items()
            }
            video += frames
    finally:
        camera.close()
        if own_bar:
            bar.stop()
    eye["fps"] = fps
    return logs, eye, video


def run_conditions_camera(
    loop: Loop,
    conditions: PendulumConditions,
    seed: int,
    n_seeds: int,
    cam: CameraConfig | None = None,
    video_condition: str = "learned",
    progress: bool = True,
    eye_source: str = "camera",
    camera_conditions: tuple[str, ...] = ("frozen", "learned"),
    compiled: tuple | None = None,
):
    """The three conditions with the camera in the loop, and with ground truth for comparison.

    ``plain`` (F_o = 0) does not use the object's state at all, so its camera run is the ground-
    truth run; ``frozen`` and ``learned`` run :func:`run_camera` (one compile for both). Returns
    ``(camera_logs, truth_logs, timing, eye_by_condition, video)``: logs per condition as
    :func:`~hec_jax.loop.episodes.run_conditions`; ``video``: seed 0 of ``video_condition``, its
    last swing (or the continuous run when the task has one). ``progress``: one bar over the
    frames of both camera conditions (:class:`~hec_jax.progress.ProgressBar`), the ground-truth
    runs' compile and run times on their own line. ``eye_source``: as :func:`run_camera`.
    ``camera_conditions``: which of ``frozen`` and ``learned`` run with the camera (the others
    have ground-truth logs only; ``camera_logs`` and ``eye_by_condition`` leave them out).
    ``compiled``: as :func:`run_camera` (one compile shared with other calls).

    Raises:
        ValueError: ``camera_conditions`` empty or naming another condition, or
            ``video_condition`` (when not None) not among them.
    """
    camera_conditions = tuple(camera_conditions)
    unknown = set(camera_conditions) - {"frozen", "learned"}
    if not camera_conditions or unknown or len(set(camera_conditions)) < len(camera_conditions):
        raise ValueError(
            "camera_conditions must be distinct names among 'frozen' and 'learned', "
            f"got {camera_conditions!r}"
        )
    if video_condition is not None and video_condition not in camera_conditions:
        raise ValueError(
            f"video_condition {video_condition!r} is not among camera_conditions "
            f"{camera_conditions!r}"
        )
    total = len(camera_conditions) * n_seeds * frames_per_condition(loop, cam)
    with ProgressBar(total, "frames", enabled=progress) as bar:
        bar.update(description="ground truth (compiling, then 3 conditions)")
        truth, timing = run_conditions(loop, conditions, seed, n_seeds)
        run_s = sum(timing[c] for c in ("plain", "frozen", "learned"))
        bar.log(f"ground truth: compile {timing['compile']:.1f} s, run {run_s:.1f} s")
        keys = jax.random.split(jax.random.PRNGKey(seed), n_seeds)
        camera_logs, eyes, video = {"plain": truth["plain"]}, {}, []
        shown = "final" if loop.final_steps else loop.config.swings - 1
        if compiled is None:
            compiled = (make_start(loop), make_segment(loop))
        for condition in ("frozen", "learned"):
            if condition not in camera_conditions:
                continue
            want = condition == video_condition
            logs, eye, frames = run_camera(
                loop,
                conditions,
                keys,
                condition,
                cam,
                shown if want else None,
                bar,
                compiled=compiled,
                eye_source=eye_source,
            )
            camera_logs[condition], eyes[condition] = logs, eye
            if condition == camera_conditions[0]:  # its first call compiled the shared ones
                bar.log(_first_segment_line(float(eye["sim_ms"][0, 0])))
            timing[f"{condition}_camera"] = float(
                np.sum(eye["wall_s"]) + (np.sum(eye["final"]["wall_s"]) if "final" in eye else 0.0)
            )
            video = frames if want else video
    return camera_logs, truth, timing, eyes, video
