"""``face_foreground``: each face of a fitted box must lie on the object, not on the background
beside it (``TrackConfig.min_face_foreground``).

Independent truth: a cube drawn with OpenCV at a known pose, each visible face one flat colour
far from the grey background, and the empty grey image as the background. Every face of the
true pose lies on drawn pixels; a fit shifted sideways by half an edge has a face beside the
drawn cube, on the background, while most of its whole silhouette still covers the
cube (the whole silhouette's check, ``min_foreground`` at 0.5, passes it).
"""

import dataclasses

import cv2
import numpy as np
import pytest

from hec_jax.geometry import BoxTracker, TrackConfig, detect
from hec_jax.geometry.box_model import FACES, face_visibility_np, project_corners_np
from hec_jax.geometry.synthetic import rotation_from_axis_angle
from hec_jax.geometry.track import RANDOMIZED_BENCHMARK, face_foreground

K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
SIZE = 0.08  # [m]
GREY = 128
FACE_GREYS = (40, 70, 200, 230, 20, 250)  # each far from the background's grey


def _pose(yaw_deg, tilt_deg, t):
    """The box turned ``yaw_deg`` about the camera's vertical and tilted ``tilt_deg`` toward
    the camera: two side faces and the top in view."""
    yaw = rotation_from_axis_angle(np.array([0.0, 1.0, 0.0]), np.deg2rad(yaw_deg))
    tilt = rotation_from_axis_angle(np.array([1.0, 0.0, 0.0]), np.deg2rad(-tilt_deg))
    return tilt @ yaw, np.asarray(t, float)


def _draw(rotation, translation):
    """(480, 640, 3) uint8 RGB: the visible faces filled with their greys on the background."""
    image = np.full((480, 640, 3), GREY, np.uint8)
    px = project_corners_np(rotation, translation, SIZE, K) - 0.5  # OpenCV pixel centres
    for f in np.flatnonzero(face_visibility_np(rotation, translation, SIZE)):
        pts = np.round(px[FACES[f]] * 256).astype(np.int32)
        cv2.fillConvexPoly(image, pts, (FACE_GREYS[f],) * 3, cv2.LINE_8, 8)
    return image


BACKGROUND = np.full((480, 640, 3), GREY, np.uint8)


def _least(image, rotation, translation, thickness_px=6.0):
    return face_foreground(image, BACKGROUND, rotation, translation, SIZE, K, thickness_px, 12)


def _silhouette_fraction(image, rotation, translation):
    corners = project_corners_np(rotation, translation, SIZE, K)
    return detect.foreground_fraction(image, BACKGROUND, corners, 12, shadows=False)


POSES = [
    (30.0, 25.0, (0.0, 0.0, 0.7)),
    (-50.0, 15.0, (0.05, -0.03, 0.9)),
    (10.0, 40.0, (-0.1, 0.05, 0.6)),
]


@pytest.mark.parametrize("yaw, tilt, t", POSES)
def test_the_true_pose_s_faces_lie_on_the_cube_and_a_wrong_fit_has_one_beside_it(yaw, tilt, t):
    rot, t = _pose(yaw, tilt, t)
    image = _draw(rot, t)
    assert _least(image, rot, t) > 0.95
    # shifted sideways by half an edge: its face on that side lies on the background beside
    # the cube, while over half of its whole silhouette still covers the cube
    shifted = t + np.array([0.5 * SIZE, 0.0, 0.0])
    assert _silhouette_fraction(image, rot, shifted) > 0.5  # the whole-box check passes it
    assert _least(image, rot, shifted) < 0.3


def test_a_face_thinner_than_the_floor_is_not_counted():
    """A fit moved so that its thin face lies beside the cube: that face counts at a floor
    below its thickness, not at one above it (only the thick face is left, mostly on the cube)."""
    rot, t = _pose(0.0, 8.0, (0.0, 0.0, 0.7))  # the top face a few px thick
    image = _draw(rot, t)
    px = project_corners_np(rot, t, SIZE, K)
    faces = np.flatnonzero(face_visibility_np(rot, t, SIZE))
    quads = px[FACES[faces]]
    sides = np.linalg.norm(np.roll(quads, -1, axis=1) - quads, axis=-1).max(1)
    area = np.array([cv2.contourArea(q.astype(np.float32)) for q in quads])  # [px^2]
    thickness = area / sides
    thin = int(np.argmin(thickness))
    assert 2.0 < thickness[thin] < 10.0 < np.max(thickness)
    # moved a third of an edge toward the thin face's side: that face off the drawn cube
    away = quads[thin].mean(0) - px.mean(0)
    moved = t + np.append(away / np.linalg.norm(away), 0.0) * SIZE / 3
    assert _least(image, rot, moved, thickness_px=0.5 * thickness[thin]) < 0.5
    assert _least(image, rot, moved, thickness_px=2.0 * thickness[thin]) > 0.6


def test_a_thin_true_face_is_measured_on_the_box_s_window():
    """The top face 3 px thick, its own window 5 px tall (under ``detect.clip_roi``'s 8 px,
    where ``foreground_fraction`` of that face alone read 0 before session 75; its window is
    now widened to 8 px): measured alone or on the mask over the whole box's window, it lies
    on the cube."""
    rot, t = _pose(0.0, 6.0, (0.0, 0.0, 0.7))
    image = _draw(rot, t)
    px = project_corners_np(rot, t, SIZE, K)
    faces = np.flatnonzero(face_visibility_np(rot, t, SIZE))
    heights = np.ptp(px[FACES[faces]][..., 1], axis=1)
    top = px[FACES[faces[np.argmin(heights)]]]
    assert np.max(np.ceil(top[:, 1] - 0.5)) + 1 - np.min(np.floor(top[:, 1] - 0.5)) < 8
    assert detect.foreground_fraction(image, BACKGROUND, top) > 0.9  # its own window, widened
    assert detect.foreground_fractions(image, BACKGROUND, top[None])[0] > 0.9
    assert _least(image, rot, t, thickness_px=1.0) > 0.9


@pytest.mark.parametrize("t", [(0.0, 0.0, 14.0), (-9.5, -7.1, 18.0)])
def test_a_box_a_few_pixels_across_is_measured(t):
    """A cube about 4 px across (before session 75 its window, under 8 px, read 0, and every
    silhouette check refused it): its window is widened to 8 px inside the image, also where
    the cube sits in the image's corner; the same box moved off the drawn cube reads 0."""
    rot, t = _pose(30.0, 20.0, t)
    image = _draw(rot, t)
    px = project_corners_np(rot, t, SIZE, K)
    assert np.all(np.ceil(px.max(0) - 0.5) + 1 - np.floor(px.min(0) - 0.5) < 8)  # its window
    assert np.all(px > 0.0) and np.all(px < (640.0, 480.0))
    if t[0] < 0:  # against the image's corner: the widened window is clamped to the image
        lo, hi = np.floor(px.min(0) - 0.5), np.ceil(px.max(0) - 0.5) + 1
        assert detect._widened_roi((*lo, *hi), 640, 480) == (0, 0, 8, 8)
    assert _silhouette_fraction(image, rot, t) > 0.8
    assert _silhouette_fraction(image, rot, t + (0.3, 0.3, 0.0)) == 0.0


def test_the_preset_passes_a_nearer_box_with_a_face_beside_the_cube_that_the_check_refuses():
    """The randomized benchmark's preset checks (silhouette, ring, face split and seam) pass a
    tracked fit 1.2x nearer, moved so that its outline meets the cube's on one side: the ring
    outside it is background, most of its silhouette is the cube, its faces are flat. One of
    its faces lies on the background beside the cube, which ``min_face_foreground`` refuses;
    the true pose passes both, tracked and from scratch."""
    yaw, tilt, t = POSES[2]
    rot, t = _pose(yaw, tilt, t)
    image = _draw(rot, t)
    gray = detect.to_gray(image)
    near = t / 1.2
    dx_px = project_corners_np(rot, t, SIZE, K)[:, 0].min()
    dx_px -= project_corners_np(rot, near, SIZE, K)[:, 0].min()  # the left outlines meet
    near = near + np.array([dx_px * near[2] / K[0, 0], 0.0, 0.0])
    # the face check on every fit (min_face_foreground), without the preset's tracked-only one
    preset = dataclasses.replace(RANDOMIZED_BENCHMARK, threads=1, min_face_foreground_tracked=None)
    for share, near_passes in ((None, True), (0.2, False)):
        cfg = dataclasses.replace(preset, min_face_foreground=share)
        tracker = BoxTracker(K, SIZE, 30.0, cfg, BACKGROUND)
        tracker._frame_rgb = image
        assert tracker._confirmed(gray, rot, t, tracked=True)
        assert tracker._confirmed(gray, rot, t, acquire=True)
        assert tracker._confirmed(gray, rot, near, tracked=True) == near_passes
    # min_face_foreground_tracked alone: the same box refused while the filter runs, passed to a
    # search from scratch (the filter not running); the true pose passes both
    cfg = dataclasses.replace(preset, min_face_foreground=None, min_face_foreground_tracked=0.2)
    tracker = BoxTracker(K, SIZE, 30.0, cfg, BACKGROUND)
    tracker._frame_rgb = image
    assert not tracker._confirmed(gray, rot, near, tracked=True)
    assert tracker._confirmed(gray, rot, near, acquire=True)
    assert tracker._confirmed(gray, rot, near)
    assert tracker._confirmed(gray, rot, t, tracked=True)
    assert tracker._confirmed(gray, rot, t, acquire=True)
    # the benchmark's preset as it is (the tracked-only check at 0.5): the same
    assert RANDOMIZED_BENCHMARK.min_face_foreground is None
    cfg = dataclasses.replace(RANDOMIZED_BENCHMARK, threads=1)
    tracker = BoxTracker(K, SIZE, 30.0, cfg, BACKGROUND)
    tracker._frame_rgb = image
    assert not tracker._confirmed(gray, rot, near, tracked=True)
    assert tracker._confirmed(gray, rot, near, acquire=True)
    assert tracker._confirmed(gray, rot, t, tracked=True)
    # and with both set, the tracked bar replaces the other while the filter runs
    cfg = dataclasses.replace(preset, min_face_foreground=0.2, min_face_foreground_tracked=0.0)
    tracker = BoxTracker(K, SIZE, 30.0, cfg, BACKGROUND)
    tracker._frame_rgb = image
    assert tracker._confirmed(gray, rot, near, tracked=True)
    assert not tracker._confirmed(gray, rot, near, acquire=True)


@pytest.mark.parametrize(
    "changes, message",
    [
        ({"min_face_foreground": 1.5}, "min_face_foreground must be in [0, 1] or None"),
        ({"min_face_foreground": True}, "min_face_foreground must be in [0, 1] or None"),
        (
            {"min_face_foreground_tracked": -0.1},
            "min_face_foreground_tracked must be in [0, 1] or None",
        ),
        ({"face_foreground_px": -1.0}, "face_foreground_px must be finite and >= 0"),
        ({"face_foreground_px": float("inf")}, "face_foreground_px must be finite and >= 0"),
        ({"face_foreground_px": True}, "face_foreground_px must be finite and >= 0"),
    ],
)
def test_bad_face_foreground_settings_are_refused(changes, message):
    with pytest.raises(ValueError, match=message.replace("[", r"\[").replace("]", r"\]")):
        BoxTracker(K, SIZE, 30.0, TrackConfig(**changes))
