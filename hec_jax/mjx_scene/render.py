"""Scene camera frames (NumPy boundary, MuJoCo C renderer) and the ground truth beside them.

* :class:`SceneCamera` renders one camera of a model at any ``qpos``; :func:`render_model_like`
  copies the kinematic geometry of an MJX model (pendulum conditions, moved hinge) into a C model
  for it: the closed hand-eye loop simulates in MJX and renders with MuJoCo C.
* :func:`render_rollout` simulates a C model and renders frames at a fixed rate with the true
  state of one body in the camera frame; :func:`render_swing` is that for the scene's pendulum
  released from an angle with the arm held still.

Intrinsics and poses follow :mod:`hec_jax.geometry.camera` (through :mod:`.camera`). Frames are
(H, W, 3) uint8 RGB. Headless rendering needs ``MUJOCO_GL=egl`` (or osmesa) set before MuJoCo is
first imported.
"""

from __future__ import annotations

import copy
from typing import NamedTuple

import cv2
import mujoco
import numpy as np

from hec_jax.mjx_scene.camera import (
    IMAGE_HEIGHT,
    IMAGE_WIDTH,
    camera_id,
    camera_intrinsics,
    camera_pose_world,
)
from hec_jax.mjx_scene.model import ARM_JOINTS, load_mj_model

# what decides where things are and how big they look (everything ``apply_conditions`` and a moved
# hinge change, and the rest of the kinematic tree for good measure)
_GEOMETRY_FIELDS = ("body_pos", "body_quat", "geom_pos", "geom_quat", "geom_size", "site_pos")

# software (Mesa) rendering is 3x faster without these, and the eye does not need them
_SLOW_FLAGS = ("mjRND_SHADOW", "mjRND_REFLECTION", "mjRND_SKYBOX", "mjRND_FOG", "mjRND_HAZE")


def with_plane_grid(m_c: mujoco.MjModel, spacing_m: float | None) -> mujoco.MjModel:
    """A copy of the C model ``m_c`` whose planes are drawn with grid lines ``spacing_m`` [m]
    apart (None: ``m_c`` itself).

    MuJoCo draws a plane as a grid of quads, the third ``geom_size`` of a plane being their
    spacing (its lighting is per vertex); it is a rendering parameter only (a plane collides as
    an infinite half-space), so the physics of the copy is ``m_c``'s. A coarser grid draws fewer
    quads and changes only the planes' shading (docs/realtime.md, "The floor's render grid").

    Raises:
        ValueError: ``spacing_m`` not None and not finite and > 0.
    """
    if spacing_m is None:
        return m_c
    if not (np.isfinite(spacing_m) and spacing_m > 0):
        raise ValueError(f"plane grid spacing must be finite and > 0 [m], got {spacing_m!r}")
    out = copy.copy(m_c)
    planes = np.asarray(out.geom_type) == int(mujoco.mjtGeom.mjGEOM_PLANE)
    out.geom_size[planes, 2] = float(spacing_m)
    return out


def render_model_like(m_c: mujoco.MjModel, mx) -> mujoco.MjModel:
    """A copy of the C model ``m_c`` with the kinematic geometry of the MJX model ``mx`` (unbatched).

    ``m_c`` may have more bodies, geoms and sites than ``mx`` if they come after all of ``mx``'s
    (a visual-only scene around the simulated one, :func:`hec_jax.mjx_scene.lab.lab_model`):
    ``mx``'s rows are copied onto the first ones, the rest keep ``m_c``'s.

    Raises:
        ValueError: ``mx`` is batched, a field's rows do not match ``mx``'s own count, or ``m_c``
            has fewer.
    """
    out = copy.copy(m_c)
    for name in _GEOMETRY_FIELDS:
        src = np.asarray(getattr(mx, name))
        dst = getattr(out, name)
        rows = int(getattr(mx, "n" + name.split("_")[0]))  # mx.nbody, mx.ngeom, mx.nsite
        if src.shape[0] != rows or src.shape[1:] != dst.shape[1:] or rows > dst.shape[0]:
            raise ValueError(
                f"{name}: MJX model has shape {src.shape} ({rows} rows), C model {dst.shape}"
            )
        dst[:rows] = src
    return out


class SceneCamera:
    """Renders one camera of a model at given joint positions.

    Frames are (height, width, 3) uint8 RGB; ``intrinsics`` is K of the MJCF camera at that
    resolution and ``world_from_camera`` the camera pose in the pinhole convention (x right,
    y down, z forward), so that a camera-frame point p is ``R @ p + t`` in the world.

    Args:
        m_c: the C model to render (e.g. from :func:`render_model_like`).
        camera: camera name or id.
        width, height: [px].
        fast: drop shadows, reflections, skybox, fog and haze (3x faster in software rendering).
        hidden_geoms: names of geoms drawn fully transparent (e.g. to render a background); they
            cast no shadow either.
        shadows: keep the shadows when ``fast`` (a scene whose lights are meant to cast them,
            :func:`hec_jax.mjx_scene.lab.lab_model`).
    """

    def __init__(
        self,
        m_c: mujoco.MjModel,
        camera: int | str = "eye",
        width: int = IMAGE_WIDTH,
        height: int = IMAGE_HEIGHT,
        fast: bool = True,
        hidden_geoms: tuple[str, ...] = (),
        shadows: bool = False,
    ):
        self.camera_id = camera_id(m_c, camera)
        self.model = copy.copy(m_c)
        for name in hidden_geoms:
            gid = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_GEOM, name)
            if gid < 0:
                raise ValueError(f"model has no geom {name!r}")
            self.model.geom_rgba[gid, 3] = 0.0
        self.data = mujoco.MjData(self.model)
        self.intrinsics = camera_intrinsics(self.model, self.camera_id, width, height)
        mujoco.mj_kinematics(self.model, self.data)
        mujoco.mj_camlight(self.model, self.data)
        self.world_from_camera = camera_pose_world(self.model, self.data, self.camera_id)
        self._renderer = mujoco.Renderer(self.model, height, width)
        if fast:
            for flag in _SLOW_FLAGS[1:] if shadows else _SLOW_FLAGS:
                self._renderer.scene.flags[getattr(mujoco.mjtRndFlag, flag)] = False

    def pose(self, qpos) -> None:
        """Sets ``data`` to joint positions ``qpos`` (nq,) and runs the kinematics (no render)."""
        qpos = np.asarray(qpos, dtype=np.float64)
        if qpos.shape != (self.model.nq,):
            raise ValueError(f"qpos must have shape ({self.model.nq},), got {qpos.shape}")
        self.data.qpos[:] = qpos
        mujoco.mj_kinematics(self.model, self.data)
        mujoco.mj_camlight(self.model, self.data)

    def render(self, qpos) -> np.ndarray:
        """The frame (H, W, 3) uint8 at joint positions ``qpos`` (nq,)."""
        self.pose(qpos)
        self._renderer.update_scene(self.data, camera=self.camera_id)
        return self._renderer.render()

    def to_world(self, p_cam, v_cam=None, a_cam=None):
        """Camera-frame position [m] (and velocity, acceleration) of a point -> world frame."""
        r, t = self.world_from_camera
        out = [r @ np.asarray(p_cam) + t]
        out += [r @ np.asarray(x) for x in (v_cam, a_cam) if x is not None]
        return out[0] if len(out) == 1 else tuple(out)

    def close(self) -> None:
        """Frees the renderer (its OpenGL context)."""
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def sensor(
    frame: np.ndarray,
    rng: np.random.Generator,
    noise_sigma: float = 0.0,
    blur_px: float = 0.0,
    gain: float = 1.0,
) -> np.ndarray:
    """A camera's imperfections on one rendered (H, W, 3) uint8 frame: exposure gain [-],
    Gaussian blur of sigma ``blur_px`` [px] (defocus; none under 0.05 px) and Gaussian sensor
    noise of standard deviation ``noise_sigma`` [grey levels], clipped and rounded to uint8.
    With none of them the frame itself is returned (no copy, no draw from ``rng``).
    """
    if gain == 1.0 and blur_px <= 0.05 and noise_sigma <= 0:
        return frame
    img = frame.astype(np.float32) * gain
    if blur_px > 0.05:
        img = cv2.GaussianBlur(img, (0, 0), blur_px)
    if noise_sigma > 0:
        img += rng.normal(0.0, noise_sigma, img.shape).astype(np.float32)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


class RenderedSequence(NamedTuple):
    """Frames and the true state of one body (camera frame: x right, y down, z forward).

    Attributes:
        frames: (T, H, W, 3) uint8 RGB.
        intrinsics: (3, 3) K from the MJCF camera.
        times: (T,) [s].
        position: (T, 3) body origin [m].
        rotation: (T, 3, 3) body axes in the camera frame (R_cam_body).
        velocity: (T, 3) [m/s], acceleration: (T, 3) [m/s^2] of the body origin (central
            differences over one simulation step; the camera is static).
    """

    frames: np.ndarray
    intrinsics: np.ndarray
    times: np.ndarray
    position: np.ndarray
    rotation: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray


def sampled_motion(
    track: np.ndarray, steps: int, n_frames: int, dt: float, at: np.ndarray | None = None
) -> tuple:
    """(position, velocity, acceleration) at frames 0 .. n_frames - 1 of a per-step track
    (T, 3) [m] sampled every ``steps`` steps of ``dt`` [s] from step 1 (central differences),
    or at the steps ``at`` (n_frames,) where given (each at least 1).
    """
    at = 1 + steps * np.arange(n_frames) if at is None else np.asarray(at, int)
    pos = track[at]
    vel = (track[at + 1] - track[at - 1]) / (2 * dt)
    acc = (track[at + 1] - 2 * pos + track[at - 1]) / (dt * dt)
    return pos, vel, acc


def body_in_camera(
    model: mujoco.MjModel, data: mujoco.MjData, body: str, camera: int | str
) -> tuple[np.ndarray, np.ndarray]:
    """(position (3,) [m], rotation R_cam_body (3, 3)) of ``body`` in the pinhole camera frame
    (after mj_forward).
    """
    bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, body)
    if bid < 0:
        raise ValueError(f"model has no body {body!r}")
    r_wc, p_wc = camera_pose_world(model, data, camera)
    return r_wc.T @ (data.xpos[bid] - p_wc), r_wc.T @ data.xmat[bid].reshape(3, 3)


def render_rollout(
    model: mujoco.MjModel,
    data: mujoco.MjData,
    n_frames: int,
    fps: float,
    camera: int | str,
    body: str,
    width: int = IMAGE_WIDTH,
    height: int = IMAGE_HEIGHT,
    hold_dofs=(),
) -> RenderedSequence:
    """Simulate from ``data`` and render ``n_frames`` frames at ``fps`` (full-quality renderer).

    The model's time step is shrunk (at most to the next integer number of steps per frame) so that
    frames fall exactly on simulation steps. Frame i is the state one step after i frame periods
    (so that every frame has a central difference); ``times`` holds each frame's simulated time,
    ``data.time`` at the start plus ``(1 + i * steps) * timestep`` (before session 90 it held
    ``i / fps``, a step early). ``hold_dofs``: dof addresses held still by compensating their
    bias forces (e.g. an arm that should stay in place). ``model.opt.timestep`` is changed in
    place.
    """
    steps = int(np.ceil(1.0 / (fps * model.opt.timestep) - 1e-9))
    model.opt.timestep = 1.0 / (fps * steps)
    dt = model.opt.timestep
    hold = np.asarray(hold_dofs, dtype=int)
    cam = camera_id(model, camera)
    k = camera_intrinsics(model, cam, width, height)
    frames = np.empty((n_frames, height, width, 3), np.uint8)
    rot = np.empty((n_frames, 3, 3))
    # positions at every simulation step; frame i sits at step 1 + i * steps (one step after the
    # start, so that every frame has a central difference).
    track = np.empty((n_frames * steps + 2, 3))
    renderer = mujoco.Renderer(model, height, width)
    start_s = float(data.time)  # [s] the simulated time at the start
    try:
        mujoco.mj_forward(model, data)
        for s in range(len(track)):
            p, r = body_in_camera(model, data, body, cam)
            track[s] = p
            if s % steps == 1 and (s - 1) // steps < n_frames:
                i = (s - 1) // steps
                renderer.update_scene(data, camera=cam)
                frames[i] = renderer.render()
                rot[i] = r
            if len(hold):
                data.qfrc_applied[hold] = data.qfrc_bias[hold]
            mujoco.mj_step(model, data)
            mujoco.mj_forward(model, data)
    finally:
        renderer.close()
    pos, vel, acc = sampled_motion(track, steps, n_frames, dt)
    times = start_s + (1 + steps * np.arange(n_frames)) * dt  # [s] each frame's state's time
    return RenderedSequence(frames, k, times, pos, rot, vel, acc)


def render_swing(
    release_rad: float,
    n_frames: int,
    fps: float = 30.0,
    width: int = IMAGE_WIDTH,
    height: int = IMAGE_HEIGHT,
) -> RenderedSequence:
    """The scene's pendulum released at rest from ``release_rad`` [rad] and swinging freely, seen
    by the camera ``eye``, with the cube's true state; the arm is held still (its bias forces
    compensated), so it stays where the model puts it.
    """
    m = load_mj_model()
    d = mujoco.MjData(m)
    d.qpos[m.jnt_qposadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, "hinge")]] = release_rad
    arm = [m.jnt_dofadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, j)] for j in ARM_JOINTS]
    return render_rollout(m, d, n_frames, fps, "eye", "cube", width, height, hold_dofs=arm)
