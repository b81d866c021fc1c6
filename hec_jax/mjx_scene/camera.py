"""The fixed calibrated camera of Sec. 6.1: intrinsics and pose in the pinhole convention.

Pinhole convention used by the eye: camera frame x right, y down, z forward (optical axis); pixel
(u, v) with u to the right and v down, origin at the top-left corner of the top-left pixel, so the
image centre is (W/2, H/2). MuJoCo cameras look along their local -z with y up; the conversion is
R_world_cam = R_world_mjcam @ diag(1, -1, -1).
"""

from __future__ import annotations

import mujoco
import numpy as np

from hec_jax.geometry.camera import intrinsics_from_fovy

IMAGE_WIDTH = 640  # [px] intended resolution of the TV camera
IMAGE_HEIGHT = 480  # [px]


def intrinsics(fovy_deg: float, width: int = IMAGE_WIDTH, height: int = IMAGE_HEIGHT) -> np.ndarray:
    """3x3 intrinsic matrix K from MuJoCo's vertical field of view (square pixels, centred).

    f = (H / 2) / tan(fovy / 2) [px], K = [[f, 0, W/2], [0, f, H/2], [0, 0, 1]]
    (:func:`hec_jax.geometry.intrinsics_from_fovy`).
    """
    return intrinsics_from_fovy(fovy_deg, width, height)


def camera_intrinsics(
    m: mujoco.MjModel, cam_id: int, width: int = IMAGE_WIDTH, height: int = IMAGE_HEIGHT
) -> np.ndarray:
    """K of camera ``cam_id`` from its MJCF fovy at the given resolution."""
    return intrinsics(float(m.cam_fovy[cam_id]), width, height)


def camera_pose_world(
    m: mujoco.MjModel, d: mujoco.MjData, cam_id: int
) -> tuple[np.ndarray, np.ndarray]:
    """(R_world_cam (3, 3), p_world_cam [m] (3,)) in the pinhole convention
    (x right, y down, z forward).

    A world point X has camera coordinates R_world_cam.T @ (X - p_world_cam). Needs mj_kinematics
    (or mj_forward) to have been run on ``d``.
    """
    R_mj = d.cam_xmat[cam_id].reshape(3, 3)
    R = R_mj @ np.diag([1.0, -1.0, -1.0])
    return R, d.cam_xpos[cam_id].copy()


def project(K: np.ndarray, R_world_cam: np.ndarray, p_world_cam: np.ndarray, X_world: np.ndarray):
    """Pixel coordinates (N, 2) and depth [m] (N,) of world points (N, 3) (NumPy, for checks)."""
    Xc = (np.asarray(X_world).reshape(-1, 3) - p_world_cam[None, :]) @ R_world_cam
    uvw = Xc @ K.T
    return uvw[:, :2] / uvw[:, 2:3], Xc[:, 2]
