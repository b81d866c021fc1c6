"""``TrackConfig.tracked_without_shadow_test``: while the filter runs, the silhouette check
counts the pixels the colour difference's shadow test removes (issue 24).

Independent truth: a plain golden-brown wall (seeded sensor noise) as the background; a cube
drawn with OpenCV at a known pose, every face the wall's colour times one factor in every
channel (0.5-0.62: a cube of the wall's hue, darker, as development seed 3097's wood cube
is); its cast shadow drawn at another pose, the wall times 0.6. To ``detect.difference``'s
shadow test (factors 0.25-0.92, the channels alike) both are a shadow in every pixel.
"""

import dataclasses

import cv2
import numpy as np
import pytest

from hec_jax.geometry import BoxTracker, TrackConfig, detect
from hec_jax.geometry.box_model import FACES, face_visibility_np, project_corners_np
from hec_jax.geometry.synthetic import rotation_from_axis_angle
from hec_jax.geometry.track import RANDOMIZED_BENCHMARK

K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
SIZE = 0.08  # [m]
WALL_RGB = np.array([150.0, 112.0, 58.0])  # grey levels
FACE_FACTORS = (0.58, 0.5, 0.62, 0.55, 0.6, 0.52)  # each face: the wall's colour x this
SHADOW_FACTOR = 0.6
NOISE_GREY = 1.0
ROT = rotation_from_axis_angle(np.array([1.0, 0.0, 0.0]), np.deg2rad(-25.0)) @ (
    rotation_from_axis_angle(np.array([0.0, 1.0, 0.0]), np.deg2rad(30.0))
)
CUBE_T = np.array([0.0, -0.08, 0.7])  # [m], camera frame
SHADOW_T = np.array([0.12, -0.06, 0.75])  # the cast shadow, beside the cube on the wall
EMPTY_T = np.array([-0.15, 0.1, 0.7])  # a box on the plain wall: neither cube nor shadow


def _noisy(image: np.ndarray, seed: int) -> np.ndarray:
    noise = np.random.default_rng(seed).normal(0.0, NOISE_GREY, image.shape)
    return np.clip(np.round(image + noise), 0, 255).astype(np.uint8)


def _scene(seed: int = 0):
    """(frame, background): RGB uint8; the frame holds the cube and its cast shadow."""
    wall = np.broadcast_to(WALL_RGB, (480, 640, 3)).astype(float)
    background = _noisy(wall, seed)
    frame = wall.copy()
    shadow_px = project_corners_np(ROT, SHADOW_T, SIZE, K) - 0.5
    mask = np.zeros((480, 640), np.uint8)
    cv2.fillConvexPoly(mask, cv2.convexHull(np.round(shadow_px).astype(np.int32)), 1)
    frame[mask.astype(bool)] *= SHADOW_FACTOR
    px = project_corners_np(ROT, CUBE_T, SIZE, K) - 0.5
    for f in np.flatnonzero(face_visibility_np(ROT, CUBE_T, SIZE)):
        pts = np.round(px[FACES[f]] * 256).astype(np.int32)
        colour = tuple(float(c) for c in WALL_RGB * FACE_FACTORS[f])
        cv2.fillConvexPoly(frame, pts, colour, cv2.LINE_8, 8)
    return _noisy(frame, seed + 1), background


def _tracker(option: bool, background, **changes) -> BoxTracker:
    cfg = dataclasses.replace(
        RANDOMIZED_BENCHMARK, threads=1, tracked_without_shadow_test=option, **changes
    )
    return BoxTracker(K, SIZE, 30.0, cfg, background)


@pytest.mark.parametrize("seed", [0, 5])
def test_the_drawn_cube_is_a_shadow_to_the_test_and_foreground_without_it(seed):
    """The premise, on the drawn frame: under the cube's true silhouette almost nothing differs
    with the shadow test, almost everything without it."""
    frame, background = _scene(seed)
    corners = project_corners_np(ROT, CUBE_T, SIZE, K)
    thr = RANDOMIZED_BENCHMARK.foreground_threshold
    assert detect.foreground_fraction(frame, background, corners, thr) < 0.05
    assert detect.foreground_fraction(frame, background, corners, thr, shadows=False) > 0.9


@pytest.mark.parametrize("seed", [0, 5])
@pytest.mark.parametrize("where", ["cube", "cast shadow"])
def test_the_option_passes_the_cube_and_its_shadow_while_tracking_only(where, seed):
    """Without the option the preset refuses the cube's true pose in every check (the shadow
    test's pixels count only where a tenth of the silhouette differs with it: ``shadow_faces``).
    With it the tracked check passes it; the search's check (``acquire``) still refuses it (the
    IoU check too; the next test turns that off).
    The cast shadow, photometrically the same as the cube, goes the same way: the documented
    limit (while tracking, only the innovation gate keeps a fit off it)."""
    translation = CUBE_T if where == "cube" else SHADOW_T
    frame, background = _scene(seed)
    gray = detect.to_gray(frame)
    for option in (False, True):
        tracker = _tracker(option, background)
        tracker._frame_rgb = frame
        assert tracker._confirmed(gray, ROT, translation, tracked=True) == option
        assert not tracker._confirmed(gray, ROT, translation, acquire=True)


@pytest.mark.parametrize("acquire", [False, True])
def test_the_option_leaves_the_silhouette_check_of_an_untracked_fit_alone(acquire):
    """With the IoU check off (so the silhouette check alone decides), a fit checked without
    ``tracked`` (a search's fit, or any other) is refused with the option as without it: only
    the tracked check counts the shadow test's pixels."""
    frame, background = _scene()
    gray = detect.to_gray(frame)
    for option in (False, True):
        tracker = _tracker(option, background, min_iou_acquire=0.0)
        tracker._frame_rgb = frame
        assert not tracker._confirmed(gray, ROT, CUBE_T, acquire=acquire)
        assert tracker._confirmed(gray, ROT, CUBE_T, tracked=True) == option


def test_the_option_does_not_pass_a_box_on_the_plain_wall():
    """With the option, a box where the wall shows (no cube, no shadow) is still refused while
    tracking: the option counts the shadow test's pixels, not pixels that do not differ."""
    frame, background = _scene()
    tracker = _tracker(True, background)
    tracker._frame_rgb = frame
    assert not tracker._confirmed(detect.to_gray(frame), ROT, EMPTY_T, tracked=True)


def test_the_option_is_off_by_default_and_on_in_the_benchmark_s_preset():
    assert not TrackConfig().tracked_without_shadow_test
    assert RANDOMIZED_BENCHMARK.tracked_without_shadow_test
