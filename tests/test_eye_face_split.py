"""``face_split``: a fitted box's faces must each look like one face (``max_face_split``), and
``seam_step``: its inner edges must show a step (``face_seam_step``).

Independent truth: a cube drawn with OpenCV, each face one flat colour, at a known pose. On the
true pose every sampled point lies inside its own face (split 0 exactly, the step at each inner
edge the two faces' colour distance exactly); a fit turned about the box's vertical axis has
faces that span two drawn faces (split of the order of their contrast) and an inner edge inside
one drawn face (no step), as does the outline's Necker twin (the box reflected through the plane
across the line of sight: the same outline, its inner edges along the drawn faces' diagonals).
"""

import cv2
import numpy as np
import pytest

from hec_jax.geometry import BoxTracker, TrackConfig
from hec_jax.geometry.box_model import (
    FACE_NORMALS,
    FACES,
    face_visibility_np,
    project_corners_np,
)
from hec_jax.geometry.synthetic import rotation_from_axis_angle
from hec_jax.geometry.track import face_split, seam_step

K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
SIZE = 0.08  # [m]
GREY = (128, 128, 128)
# one flat colour per face (RGB), far apart: the least distance between two is about 170
COLOURS = [
    (220, 30, 30),
    (30, 220, 30),
    (30, 30, 220),
    (220, 220, 30),
    (220, 30, 220),
    (30, 220, 220),
]


def _draw(rotation, translation, colours=COLOURS, halves_on=None, second=(0, 0, 0)):
    """(480, 640, 3) uint8: the cube's visible faces filled with their colours on grey;
    ``halves_on``: a face index drawn as two halves (its colour and ``second``)."""
    image = np.full((480, 640, 3), GREY, np.uint8)
    px = project_corners_np(rotation, translation, SIZE, K) - 0.5  # OpenCV pixel centres
    shift = 8  # sub-pixel corners: 1/256 px
    for f in np.flatnonzero(face_visibility_np(rotation, translation, SIZE)):
        quad = px[FACES[f]]
        polys = [(quad, colours[f])]
        if f == halves_on:
            mid_a, mid_b = 0.5 * (quad[0] + quad[1]), 0.5 * (quad[3] + quad[2])
            polys = [
                (np.array([quad[0], mid_a, mid_b, quad[3]]), colours[f]),
                (np.array([mid_a, quad[1], quad[2], mid_b]), second),
            ]
        for poly, colour in polys:
            pts = np.round(poly * (1 << shift)).astype(np.int32)
            cv2.fillConvexPoly(image, pts, colour, cv2.LINE_8, shift)
    return image


def _pose(yaw_deg, tilt_deg, t):
    """The box turned ``yaw_deg`` about the camera's vertical, then tilted ``tilt_deg`` toward
    the camera about its horizontal: two side faces and the top face in view."""
    yaw = rotation_from_axis_angle(np.array([0.0, 1.0, 0.0]), np.deg2rad(yaw_deg))
    tilt = rotation_from_axis_angle(np.array([1.0, 0.0, 0.0]), np.deg2rad(-tilt_deg))
    rot, t = tilt @ yaw, np.asarray(t, float)
    assert face_visibility_np(rot, t, SIZE).sum() == 3 and _thicknesses(rot, t).min() > 20.0
    return rot, t


def _turned(rot, angle_deg):
    """``rot`` turned about the box's own axis nearest the image's vertical (the edge between
    the two side faces): the fit that sets that edge on a line inside a face."""
    axis = rot @ np.eye(3)[np.argmax(np.abs(rot.T @ np.array([0.0, 1.0, 0.0])))]
    return rotation_from_axis_angle(axis, np.deg2rad(angle_deg)) @ rot


def _twin(rot, t):
    """The Necker twin of the box at ``t``: its corners reflected through the plane across the
    line of sight at its centre (a proper rotation, as the cube is its own mirror image)."""
    v = np.asarray(t, float) / np.linalg.norm(t)
    return (np.eye(3) - 2.0 * np.outer(v, v)) @ rot @ np.diag([1.0, 1.0, -1.0])


def _thicknesses(rot, t):
    px = project_corners_np(rot, t, SIZE, K)
    out = []
    for f in np.flatnonzero(face_visibility_np(rot, t, SIZE)):
        q = px[FACES[f]]
        nxt = np.roll(q, -1, 0)
        area = 0.5 * abs(np.sum(q[:, 0] * nxt[:, 1] - q[:, 1] * nxt[:, 0]))
        out.append(area / np.max(np.linalg.norm(nxt - q, axis=1)))
    return np.array(out)


POSES = [
    (45.0, 25.0, (0.02, -0.01, 0.7)),
    (30.0, 35.0, (-0.04, 0.03, 0.8)),
    (60.0, 20.0, (0.0, 0.0, 0.6)),
]


@pytest.mark.parametrize(("yaw", "tilt", "t"), POSES)
def test_the_true_pose_s_faces_are_one_colour_and_a_turned_fit_s_are_not(yaw, tilt, t):
    rot, t = _pose(yaw, tilt, t)
    image = _draw(rot, t)
    gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    assert face_split(image, rot, t, SIZE, K, 12.0) == 0.0
    assert face_split(gray, rot, t, SIZE, K, 12.0) == 0.0
    # turned 30-40 deg about that edge: a side face of the fit spans both drawn side faces,
    # each of its halves mostly on one
    least_contrast = min(
        np.linalg.norm(np.subtract(a, b)) for i, a in enumerate(COLOURS) for b in COLOURS[i + 1 :]
    )
    for angle in (-40.0, -30.0, 30.0, 40.0):
        assert face_split(image, _turned(rot, angle), t, SIZE, K, 12.0) > 0.5 * least_contrast
    # the medians' price (they keep a thin occluder out): turned 10 deg, less than half of
    # either half lies on the other face, and the fit is not told apart
    for angle in (-10.0, 10.0):
        assert face_split(image, _turned(rot, angle), t, SIZE, K, 12.0) == 0.0


def _split_by_hand(image, rot, t, thickness_px):
    """face_split as its docstring states it, with ``np.median``: on each visible face at least
    ``thickness_px`` thick, a 12 x 12 grid over u, v in [0.15, 0.85] on the face plane,
    projected to the pixels it falls in; per direction, the colour distance between the
    medians of the samples below 0.45 and above 0.55."""
    corners = (
        np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)]) * SIZE
    ) @ rot.T + t
    colour = image.reshape(image.shape[0], image.shape[1], -1).astype(float)
    grid = np.linspace(0.15, 0.85, 12)
    u, v = (g.ravel() for g in np.meshgrid(grid, grid, indexing="ij"))
    thick = _thicknesses(rot, t) >= thickness_px
    worst = 0.0
    for f in np.flatnonzero(face_visibility_np(rot, t, SIZE))[thick]:
        q = corners[FACES[f]]
        pts = q[0] + u[:, None] * (q[1] - q[0]) + v[:, None] * (q[3] - q[0])
        px = pts[:, :2] / pts[:, 2:] @ K[:2, :2].T + K[:2, 2]
        cols = np.clip(np.floor(px[:, 0]).astype(int), 0, image.shape[1] - 1)
        rows = np.clip(np.floor(px[:, 1]).astype(int), 0, image.shape[0] - 1)
        samples = colour[rows, cols]
        for w in (u, v):
            gap = np.median(samples[w < 0.45], 0) - np.median(samples[w > 0.55], 0)
            worst = max(worst, float(np.linalg.norm(gap)))
    return worst


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_split_is_the_medians_difference_on_a_textured_box(seed):
    """On random texture (every sample a different colour, so every median counts) the split
    equals the docstring's medians computed by hand, RGB and gray, true and turned poses."""
    rng = np.random.default_rng(seed)
    rot, t = _pose(*POSES[seed])
    image = rng.integers(0, 256, (480, 640, 3), dtype=np.uint8)
    gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    for pose in (rot, _turned(rot, 20.0)):
        for img in (image, gray):
            got = face_split(img, pose, t, SIZE, K, 12.0)
            assert got > 0.0
            assert got == pytest.approx(_split_by_hand(img, pose, t, 12.0), rel=1e-12, abs=0)


def test_a_face_thinner_than_the_floor_is_not_sampled():
    # a face seen almost edge-on, drawn in two halves: counted only below its thickness
    rng = np.random.default_rng(7)
    for _ in range(2000):
        axis = rng.normal(size=3)
        rot = rotation_from_axis_angle(axis / np.linalg.norm(axis), rng.uniform(0.3, 2.8))
        t = np.array([0.0, 0.0, 0.7])
        vis = np.flatnonzero(face_visibility_np(rot, t, SIZE))
        thick = _thicknesses(rot, t)
        if len(vis) == 3 and 4.0 < thick.min() < 8.0 and np.sort(thick)[1] > 20.0:
            break
    else:
        raise AssertionError("no pose with one thin face")
    thin = vis[np.argmin(thick)]
    image = _draw(rot, t, halves_on=thin)
    assert face_split(image, rot, t, SIZE, K, 12.0) == 0.0  # the thin face is skipped
    assert face_split(image, rot, t, SIZE, K, 1.0) > 100.0  # taken, its halves differ


def test_the_tracker_s_checks_reject_a_turned_fit_only_with_max_face_split():
    rot, t = _pose(*POSES[0])
    image = _draw(rot, t)
    gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    turned = _turned(rot, 25.0)
    for limit, turned_passes in ((None, True), (115.0, False)):
        tracker = BoxTracker(K, SIZE, 30.0, TrackConfig(max_face_split=limit))
        tracker._frame_rgb = image  # the frame being processed (as in update)
        assert tracker._confirmed(gray, rot, t)
        assert tracker._confirmed(gray, turned, t) == turned_passes


def _least_inner_contrast(rot, t):
    """The least colour distance between two drawn faces in view that share an edge."""
    vis = np.flatnonzero(face_visibility_np(rot, t, SIZE))
    return min(
        np.linalg.norm(np.subtract(COLOURS[f], COLOURS[g]))
        for i, f in enumerate(vis)
        for g in vis[i + 1 :]
        if len(set(FACES[f]) & set(FACES[g])) == 2
    )


@pytest.mark.parametrize(("yaw", "tilt", "t"), POSES)
def test_the_true_pose_s_inner_edges_step_and_its_twin_s_do_not(yaw, tilt, t):
    rot, t = _pose(yaw, tilt, t)
    image = _draw(rot, t)
    # each strip lies inside its own drawn face: the faces' colour distance, exactly
    assert seam_step(image, rot, t, SIZE, K, 12.0) == pytest.approx(_least_inner_contrast(rot, t))
    # the twin: its faces span the drawn ones, its inner edges lie inside drawn faces
    twin = _twin(rot, t)
    assert face_visibility_np(twin, t, SIZE).sum() == 3 and _thicknesses(twin, t).min() > 20.0
    assert face_split(image, twin, t, SIZE, K, 12.0) > 100.0
    assert seam_step(image, twin, t, SIZE, K, 12.0) == 0.0
    # the same in grey levels (a grey frame)
    gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    assert seam_step(gray, twin, t, SIZE, K, 12.0) == 0.0
    assert seam_step(gray, rot, t, SIZE, K, 12.0) > 5.0


def test_a_seam_needs_two_thick_faces():
    rot, t = np.eye(3), np.array([0.0, 0.0, 0.7])  # face-on: one face in view
    assert np.isnan(seam_step(_draw(rot, t), rot, t, SIZE, K, 12.0))
    rot, t = _pose(*POSES[0])
    assert np.isnan(seam_step(_draw(rot, t), rot, t, SIZE, K, 1e3))  # none thick enough


def test_face_seam_step_passes_a_shadowed_true_pose_and_refuses_the_twin():
    # the true pose with a dark band over half of one side face (a shadow cast across it: the
    # face's own colour darkened): its split is large, but its inner edges keep their steps
    rot, t = _pose(*POSES[0])
    vis = np.flatnonzero(face_visibility_np(rot, t, SIZE))
    side = next(f for f in vis if abs((rot @ FACE_NORMALS[f])[1]) < 0.5)  # not the top face
    dark = tuple(int(0.35 * c) for c in COLOURS[side])
    image = _draw(rot, t, halves_on=side, second=dark)
    gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    twin = _twin(rot, t)
    assert face_split(image, rot, t, SIZE, K, 12.0) > 40.0
    assert seam_step(image, rot, t, SIZE, K, 12.0) > 5.0
    assert face_split(image, twin, t, SIZE, K, 12.0) > 40.0
    assert seam_step(image, twin, t, SIZE, K, 12.0) <= 5.0
    for seam, true_passes in ((None, False), (5.0, True)):
        tracker = BoxTracker(K, SIZE, 30.0, TrackConfig(max_face_split=40.0, face_seam_step=seam))
        tracker._frame_rgb = image  # the frame being processed (as in update)
        assert tracker._confirmed(gray, rot, t) == true_passes
        assert not tracker._confirmed(gray, twin, t)


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"face_seam_step": -1.0}, "face_seam_step must be >= 0 or None"),
        ({"face_seam_step": "5"}, "face_seam_step must be >= 0 or None"),
        ({"max_face_split": -1.0}, "max_face_split must be >= 0 or None"),
        ({"max_face_split": float("nan")}, "max_face_split must be >= 0 or None"),
        ({"max_face_split": "100"}, "max_face_split must be >= 0 or None"),
        ({"face_split_px": -2.0}, "face_split_px must be >= 0"),
    ],
)
def test_bad_face_split_settings_are_refused(changes, message):
    with pytest.raises(ValueError, match=message):
        BoxTracker(K, SIZE, 30.0, TrackConfig(**changes))
