"""The eye's one camera convention: pinhole K, pixel <-> normalised coordinates, projection.

Camera frame (the pinhole convention of an intrinsic matrix): x right, y down, z forward (optical
axis). Normalised image coordinates are x = X/Z, y = Y/Z (Eq. 3 of the paper). Pixel (u, v): u to
the right, v down, origin at the top-left corner of the top-left pixel, so the image centre is
(W/2, H/2) (OpenCV's integer pixel indices are u - 0.5, v - 0.5). A MuJoCo camera looks along
its local -z with y up: R_world_cam = R_world_mjcam @ diag(1, -1, -1)
(:func:`pinhole_rotation_from_mujoco`). Pure NumPy/JAX: no MuJoCo import here.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jax import Array


def check_intrinsics(intrinsics) -> None:
    """Raise ValueError unless ``intrinsics`` is a finite 3x3 pinhole matrix with positive focal lengths."""
    k = np.asarray(intrinsics)
    if k.shape != (3, 3):
        raise ValueError(f"intrinsics must have shape (3, 3), got {k.shape}")
    if not np.all(np.isfinite(k)):
        raise ValueError("intrinsics contain non-finite values")
    if k[0, 0] <= 0 or k[1, 1] <= 0:
        raise ValueError(f"focal lengths must be positive, got fx={k[0, 0]}, fy={k[1, 1]}")
    if not np.allclose(k[2], [0.0, 0.0, 1.0]) or k[1, 0] != 0:
        raise ValueError("intrinsics must be upper triangular with last row (0, 0, 1)")


def check_camera_args(intrinsics, size: float, fps: float) -> None:
    """Raise ValueError unless the intrinsics are valid (:func:`check_intrinsics`) and the
    object's edge ``size`` [m] and the frame rate ``fps`` [1/s] are finite and positive.
    """
    check_intrinsics(intrinsics)
    if not (np.isfinite(size) and size > 0):
        raise ValueError(f"size must be finite and positive, got {size}")
    if not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be finite and positive, got {fps}")


def intrinsics_from_fovy(fovy_deg: float, width: int, height: int) -> np.ndarray:
    """3x3 intrinsic matrix of an ideal pinhole camera (square pixels, centred principal point).

    MuJoCo's camera ``fovy`` is the full vertical field of view in degrees, so
    f = (H / 2) / tan(fovy / 2) [px] and K = [[f, 0, W/2], [0, f, H/2], [0, 0, 1]] (pixel origin
    at the corner of the image, see the module docstring).

    Raises:
        ValueError: fovy outside (0, 180) degrees or a non-positive image size.
    """
    if not (0.0 < fovy_deg < 180.0):
        raise ValueError(f"fovy must be in (0, 180) degrees, got {fovy_deg}")
    if width <= 0 or height <= 0:
        raise ValueError(f"image size must be positive, got {width}x{height}")
    f = 0.5 * height / np.tan(np.deg2rad(fovy_deg) / 2.0)
    return np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])


# MuJoCo camera axes (x right, y up, looking along -z) -> pinhole axes (x right, y down, z forward)
MUJOCO_TO_PINHOLE = np.diag([1.0, -1.0, -1.0])


def pinhole_rotation_from_mujoco(R_world_mjcam) -> np.ndarray:
    """R_world_cam (3, 3) in the pinhole convention from a MuJoCo camera's orientation.

    Args:
        R_world_mjcam: the camera's world orientation as MuJoCo stores it (``data.cam_xmat[i]``,
            (9,) or (3, 3)).
    """
    return np.asarray(R_world_mjcam, dtype=np.float64).reshape(3, 3) @ MUJOCO_TO_PINHOLE


def pixel_to_normalized(pixels: Array, intrinsics: Array) -> Array:
    """Pixel coordinates (..., 2) [px] -> normalised image coordinates (..., 2) (x = X/Z, y = Y/Z)."""
    k = jnp.asarray(intrinsics)
    fx, fy, skew, cx, cy = k[0, 0], k[1, 1], k[0, 1], k[0, 2], k[1, 2]
    v = pixels[..., 1]
    y = (v - cy) / fy
    x = (pixels[..., 0] - cx - skew * y) / fx
    return jnp.stack([x, y], axis=-1)


def normalized_to_pixel(normalized: Array, intrinsics: Array) -> Array:
    """Normalised image coordinates (..., 2) -> pixel coordinates (..., 2) [px]."""
    k = jnp.asarray(intrinsics)
    x, y = normalized[..., 0], normalized[..., 1]
    u = k[0, 0] * x + k[0, 1] * y + k[0, 2]
    v = k[1, 1] * y + k[1, 2]
    return jnp.stack([u, v], axis=-1)


def project_points(points_camera: Array) -> Array:
    """Perspective projection (Eq. 3): camera-frame points (..., 3) [m] -> normalised (..., 2).

    Points with Z <= 0 project to NaN-free values but are meaningless; callers check depth.
    """
    z = points_camera[..., 2]
    safe_z = jnp.where(jnp.abs(z) > 0, z, 1.0)
    return points_camera[..., :2] / safe_z[..., None]


def project_to_pixels(points_camera: Array, intrinsics: Array) -> Array:
    """Camera-frame points (..., 3) [m] -> pixel coordinates (..., 2) [px]."""
    return normalized_to_pixel(project_points(points_camera), intrinsics)
