"""A box drawn at a known pose, for the tracker's edge tests: each visible face one flat grey on
a flat background, each pixel its area coverage (independent of the tracker's own projection
and edge code but for the pinhole corners)."""

import cv2
import numpy as np

from hec_jax.geometry import BoxTracker
from hec_jax.geometry.box_model import FACES, face_visibility_np, project_corners_np
from hec_jax.geometry.synthetic import rotation_from_axis_angle

K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
SIZE = 0.06  # [m]
DEPTH = 2.0  # [m]: the box 18 px across
FACE_GREYS = (150, 200, 60, 90, 40, 110)  # each face its own grey, all far from the background


def nearly_face_on(yaw_deg: float, pitch_deg: float, depth: float = DEPTH):
    """(rotation, translation [m]): a box seen nearly face on, its front face square to the
    camera but for a yaw and a pitch, which show two side faces."""
    yaw = rotation_from_axis_angle(np.array([0.0, 1.0, 0.0]), np.deg2rad(yaw_deg))
    pitch = rotation_from_axis_angle(np.array([1.0, 0.0, 0.0]), np.deg2rad(pitch_deg))
    return pitch @ yaw, np.array([0.01, -0.02, depth])


def draw_box(rotation, translation, background=230, scale=8):
    """(480, 640) uint8: the visible faces filled with their greys, each pixel the mean over
    ``scale`` x ``scale`` sub-pixels (area coverage; OpenCV's anti-aliased fill spreads an
    outline a pixel wide around a polygon, which moves its edges outward)."""
    image = np.full((480 * scale, 640 * scale), background, np.uint8)
    # intrinsics convention (pixel i covers [i, i + 1)) at the sub-pixel scale, OpenCV centres
    px = project_corners_np(rotation, translation, SIZE, K) * scale - 0.5
    for f in np.flatnonzero(face_visibility_np(rotation, translation, SIZE)):
        pts = np.round(px[FACES[f]] * 16).astype(np.int32)
        cv2.fillConvexPoly(image, pts, FACE_GREYS[f], cv2.LINE_8, 4)
    return cv2.resize(image, (640, 480), interpolation=cv2.INTER_AREA)


def tracked_fits(rotation, translation, config, frames: int = 3) -> np.ndarray:
    """(frames, 3) the fitted centres [m] of a fresh ``BoxTracker`` with ``config`` (the empty
    background given) on the drawn box, the same frame repeated; every frame must be valid."""
    rgb = np.repeat(draw_box(rotation, translation)[..., None], 3, axis=2)
    background = np.full_like(rgb, 230)
    tracker = BoxTracker(K, SIZE, 30.0, config, background)
    steps = [tracker.update(rgb) for _ in range(frames)]
    assert all(bool(st.valid) for st in steps)
    return np.stack([st.measured_position for st in steps])
