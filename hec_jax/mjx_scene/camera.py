"""The fixed calibrated camera of Sec. 6.1 read from a MuJoCo model: intrinsics and pose.

The convention (pinhole K, camera frame x right, y down, z forward, pixel origin at the image
corner) and the conversion from MuJoCo's camera axes are defined once, in
:mod:`hec_jax.geometry.camera`; this module only reads a camera's fovy and pose from MuJoCo.
"""

from __future__ import annotations

import mujoco
import numpy as np

from hec_jax.geometry.camera import intrinsics_from_fovy, pinhole_rotation_from_mujoco

IMAGE_WIDTH = 640  # [px] intended resolution of the TV camera
IMAGE_HEIGHT = 480  # [px]


def camera_id(m: mujoco.MjModel, camera: int | str) -> int:
    """The id of ``camera`` (a name or an id) in ``m``.

    Raises:
        ValueError: no such camera.
    """
    if isinstance(camera, str):
        cam = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_CAMERA, camera)
    else:
        cam = int(camera)
    if not 0 <= cam < m.ncam:
        raise ValueError(f"model has no camera {camera!r}")
    return cam


def camera_intrinsics(
    m: mujoco.MjModel, camera: int | str, width: int = IMAGE_WIDTH, height: int = IMAGE_HEIGHT
) -> np.ndarray:
    """K (3, 3) of ``camera`` (name or id) from its MJCF fovy at the given resolution [px]
    (:func:`hec_jax.geometry.intrinsics_from_fovy`).
    """
    return intrinsics_from_fovy(float(m.cam_fovy[camera_id(m, camera)]), width, height)


def camera_pose_world(
    m: mujoco.MjModel, d: mujoco.MjData, camera: int | str
) -> tuple[np.ndarray, np.ndarray]:
    """(R_world_cam (3, 3), p_world_cam [m] (3,)) in the pinhole convention
    (x right, y down, z forward).

    A world point X has camera coordinates R_world_cam.T @ (X - p_world_cam). Needs mj_kinematics
    and then mj_camlight (or mj_forward, which runs both) to have been run on ``d``: mj_kinematics
    alone leaves the cameras' poses unset.
    """
    cam = camera_id(m, camera)
    return pinhole_rotation_from_mujoco(d.cam_xmat[cam]), d.cam_xpos[cam].copy()


def project(K: np.ndarray, R_world_cam: np.ndarray, p_world_cam: np.ndarray, X_world: np.ndarray):
    """Pixel coordinates (N, 2) and depth [m] (N,) of world points (N, 3) (NumPy, for checks)."""
    Xc = (np.asarray(X_world).reshape(-1, 3) - p_world_cam[None, :]) @ R_world_cam
    uvw = Xc @ K.T
    return uvw[:, :2] / uvw[:, 2:3], Xc[:, 2]
