"""Camera frames and ground truth from any MuJoCo model (NumPy boundary; scene independent).

``mujoco.Renderer`` renders headless with ``MUJOCO_GL=egl``. Intrinsics follow the MJCF camera
(fovy, resolution) in the pinhole convention of :mod:`hec_jax.geometry.camera`; MuJoCo cameras look
along their local -z with y up, so R_world_cam = R_world_mjcam diag(1, -1, -1).
"""

from __future__ import annotations

from typing import NamedTuple

import mujoco
import numpy as np

from hec_jax.geometry.camera import intrinsics_from_fovy


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


def camera_intrinsics(model: mujoco.MjModel, camera: str, width: int, height: int) -> np.ndarray:
    cam = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
    if cam < 0:
        raise ValueError(f"model has no camera {camera!r}")
    return intrinsics_from_fovy(float(model.cam_fovy[cam]), width, height)


def body_in_camera(
    model: mujoco.MjModel, data: mujoco.MjData, body: str, camera: str
) -> tuple[np.ndarray, np.ndarray]:
    """(position (3,), rotation (3, 3)) of ``body`` in the pinhole camera frame (after mj_forward)."""
    cam = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
    bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, body)
    r_wc = data.cam_xmat[cam].reshape(3, 3) @ np.diag([1.0, -1.0, -1.0])
    p = r_wc.T @ (data.xpos[bid] - data.cam_xpos[cam])
    r = r_wc.T @ data.xmat[bid].reshape(3, 3)
    return p, r


def render_rollout(
    model: mujoco.MjModel,
    data: mujoco.MjData,
    n_frames: int,
    fps: float,
    camera: str,
    body: str,
    width: int = 640,
    height: int = 480,
    hold_dofs=(),
) -> RenderedSequence:
    """Simulate from ``data`` and render ``n_frames`` frames at ``fps``.

    The model's time step is shrunk (at most to the next integer number of steps per frame) so that
    frames fall exactly on simulation steps. ``hold_dofs``: dof addresses held still by
    compensating their bias forces (e.g. an arm that should stay in place). ``model.opt.timestep``
    is changed in place.
    """
    steps = int(np.ceil(1.0 / (fps * model.opt.timestep) - 1e-9))
    model.opt.timestep = 1.0 / (fps * steps)
    dt = model.opt.timestep
    hold = np.asarray(hold_dofs, dtype=int)
    k = camera_intrinsics(model, camera, width, height)
    frames = np.empty((n_frames, height, width, 3), np.uint8)
    rot = np.empty((n_frames, 3, 3))
    # positions at every simulation step; frame i sits at step 1 + i * steps (one step after the
    # start, so that every frame has a central difference).
    track = np.empty((n_frames * steps + 2, 3))
    renderer = mujoco.Renderer(model, height, width)
    try:
        mujoco.mj_forward(model, data)
        for s in range(len(track)):
            p, r = body_in_camera(model, data, body, camera)
            track[s] = p
            if s % steps == 1 and (s - 1) // steps < n_frames:
                i = (s - 1) // steps
                renderer.update_scene(data, camera=camera)
                frames[i] = renderer.render()
                rot[i] = r
            if len(hold):
                data.qfrc_applied[hold] = data.qfrc_bias[hold]
            mujoco.mj_step(model, data)
            mujoco.mj_forward(model, data)
    finally:
        renderer.close()
    at = 1 + steps * np.arange(n_frames)
    pos = track[at]
    vel = (track[at + 1] - track[at - 1]) / (2 * dt)
    acc = (track[at + 1] - 2 * pos + track[at - 1]) / (dt * dt)
    return RenderedSequence(frames, k, np.arange(n_frames) / fps, pos, rot, vel, acc)
