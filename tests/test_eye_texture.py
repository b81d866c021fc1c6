"""Texture segments in the search from scratch (``TrackConfig.search_texture``, issue 24): the
segments with foreground on both sides and their grey steps (``detect.texture_segments``,
``detect.segment_steps``) against drawn images, the association that keeps them off the
silhouette edges against the outline's geometry, and the search on a rendered wood cube.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hec_jax.geometry import detect
from hec_jax.geometry.box_model import EDGES, Pose, corners_camera, project_corners_np
from hec_jax.geometry.synthetic import random_rotation
from hec_jax.geometry.track import RANDOMIZED_BENCHMARK, TrackConfig, associate


def test_texture_segments_are_those_with_foreground_on_both_sides():
    foreground = np.zeros((120, 160), bool)
    foreground[30:90, 40:120] = True  # a moving box's pixels: rows 30-89, columns 40-119
    segments = np.array(
        [
            [[60.0, 50.0], [100.0, 70.0]],  # inside: foreground 3 px to both sides
            [[40.0, 35.0], [40.0, 85.0]],  # the box's left outline: background on one side
            [[50.0, 33.5], [110.0, 33.5]],  # 3.5 px inside the top outline: both sides set
            [[50.0, 31.5], [110.0, 31.5]],  # 1.5 px inside: one side above the box
            [[10.0, 10.0], [30.0, 20.0]],  # outside the box
            [[20.0, 60.0], [80.0, 60.0]],  # its first quarter outside the box
        ]
    )
    np.testing.assert_array_equal(
        detect.texture_segments(segments, foreground), [True, False, True, False, False, False]
    )
    # a window of the frame whose top-left pixel is (x0, y0) gives the same flags
    x0, y0 = 25, 20
    window = foreground[y0:100, x0:140]
    np.testing.assert_array_equal(
        detect.texture_segments(segments, window, (x0, y0)),
        detect.texture_segments(segments, foreground),
    )
    assert detect.texture_segments(np.zeros((0, 2, 2)), foreground).shape == (0,)


def _line(angle_deg, offset_px, along_px=0.0, length_px=20.0, centre=(80.0, 60.0)):
    """A segment of ``length_px`` along ``angle_deg``, its mid point ``offset_px`` along the
    normal and ``along_px`` along the line from ``centre`` [px]."""
    a = np.deg2rad(angle_deg)
    u, n = np.array([np.cos(a), np.sin(a)]), np.array([-np.sin(a), np.cos(a)])
    mid = np.asarray(centre) + offset_px * n + along_px * u
    return np.stack([mid - 0.5 * length_px * u, mid + 0.5 * length_px * u])


def test_texture_families_are_three_distinct_parallel_lines_inside_the_box():
    # analytic cases; every segment inside the box's image unless said otherwise
    def flags(lines, inside=None, **kw):
        seg = np.array([_line(*x) for x in lines])
        inside = np.ones(len(seg), bool) if inside is None else np.asarray(inside)
        return detect.texture_families(seg, inside, **kw).tolist()

    grain = [(30.0, 0.0), (30.0, 3.0), (31.0, 6.0), (29.0, 9.0)]  # 4 lines 3 px apart
    assert flags(grain) == [True] * 4
    assert flags(grain[:2]) == [False] * 2  # two lines: one may be the box's inner edge
    # three lines, but one of them is the box's outline (background on one side): two inside
    assert flags(grain[:3], inside=[True, True, False]) == [False] * 3
    # three collinear pieces of one line are one line, with two other lines: three lines
    pieces = [(30.0, 0.0, -25.0), (30.0, 0.5, 0.0), (30.0, 0.0, 25.0)]
    assert flags(pieces) == [False] * 3
    assert flags([*pieces, (30.0, 4.0)]) == [False] * 4
    assert flags([*pieces, (30.0, 4.0), (30.0, 8.0)]) == [True] * 5
    # a line across the grain is not of its family; the directions wrap at 180 deg
    assert flags([*grain[:3], (120.0, 0.0)]) == [True, True, True, False]
    # (the normal turns with the direction: 180 deg at offset -6 lies 6 px below, as 0 deg at 6)
    assert flags([(178.0, 0.0), (1.0, 3.0), (180.0, -6.0)]) == [True] * 3
    assert flags([(0.0, 0.0), (6.0, 3.0), (12.0, 6.0)]) == [False, False, False]  # 6 deg apart
    assert flags(grain, least_lines=5) == [False] * 4
    assert flags([(0.0, 0.0), (0.0, 1.4), (0.0, 2.8)]) == [False] * 3  # within 1.5 px: one line
    assert detect.texture_families(np.zeros((0, 2, 2)), np.zeros(0, bool)).shape == (0,)
    # with the grey steps: the line of the family's largest step is kept, its pieces too
    family = [*pieces, (30.0, 4.0), (30.0, 8.0)]
    seg = np.array([_line(*x) for x in family])
    kept = ~detect.texture_families(seg, np.ones(5, bool), steps=np.array([1, 9, 1, 2, 3.0]))
    assert kept.tolist() == [True, True, True, False, False]
    kept = ~detect.texture_families(seg, np.ones(5, bool), steps=np.array([1, 1, 1, 2, 3.0]))
    assert kept.tolist() == [False, False, False, False, True]


def test_segment_steps_are_the_grey_step_across_a_segment():
    gray = np.full((100, 100), 60, np.uint8)
    gray[:, 50:] = 140  # a vertical step of 80 grey levels between columns 49 and 50
    gray[70:, :] = 100  # and below row 70, uniform
    on_step = [[50.0, 10.0], [50.0, 60.0]]  # x = 50 is the border of columns 49 and 50
    uniform = [[10.0, 20.0], [40.0, 40.0]]
    across_rows = [[10.0, 70.0], [40.0, 70.0]]  # rows 67-68 (60) above, 71-72 (100) below
    steps = detect.segment_steps(np.array([on_step, uniform, across_rows]), gray)
    np.testing.assert_allclose(steps, [80.0, 0.0, 40.0])


def _outline_edges(corners_px: np.ndarray) -> np.ndarray:
    """(12,) bool, independent of the box model's face visibility: the edges whose line has
    every corner of the projected cube on one side (the convex outline of the image)."""
    out = []
    for i, j in EDGES:
        a, b = corners_px[i], corners_px[j]
        n = np.array([-(b - a)[1], (b - a)[0]])
        side = (corners_px - a) @ n
        out.append(np.all(side >= -1e-6) or np.all(side <= 1e-6))
    return np.array(out)


@pytest.mark.parametrize("view", [0, 1, 2])
def test_texture_segments_are_kept_off_the_silhouette_edges(view):
    """A segment on each edge of a cube seen with three faces, all flagged as texture: those on
    the outline go unassigned, those on the three inner edges (creases) are assigned as without
    the flags, the same as associating them alone. The edges' roles come from the geometry:
    the outline's by the projected corners, the inner ones meet at the corner nearest the
    camera."""
    k = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
    t, size = np.array([0.03, -0.02, 0.7]), 0.1
    rng = np.random.default_rng(view)
    rot = random_rotation(rng)
    while not np.all(np.abs(rot.T @ -t) > size / 2):  # until three faces face the camera
        rot = random_rotation(rng)
    pose = Pose(jnp.asarray(rot), jnp.asarray(t))
    nearest = int(np.argmin(np.linalg.norm(np.asarray(corners_camera(pose, size)), axis=1)))
    inner = np.any(EDGES == nearest, axis=1)
    corners = project_corners_np(rot, t, size, k)
    outline = _outline_edges(corners)
    assert inner.sum() == 3 and outline.sum() == 6 and not np.any(inner & outline)
    edges = corners[EDGES]
    shrink = 0.1 * (edges[:, 1] - edges[:, 0])  # inside the edge, off the corners
    segments = np.stack([edges[:, 0] + shrink, edges[:, 1] - shrink], axis=1)
    cfg = TrackConfig()
    every = np.ones(12, bool)

    def run(texture, keep=every):
        return jax.jit(associate)(
            pose, jnp.asarray(segments), jnp.asarray(keep), size, jnp.asarray(k), 2.0,
            np.cos(np.deg2rad(cfg.gate_deg)), cfg.min_edge_px,
            texture=None if texture is None else jnp.asarray(texture),
        )  # fmt: skip

    plain = run(None)
    assigned = np.asarray(plain.weights) > 0
    np.testing.assert_array_equal(assigned, inner | outline)
    np.testing.assert_array_equal(np.asarray(plain.edge_ids)[assigned], np.flatnonzero(assigned))
    flagged = run(every)
    np.testing.assert_array_equal(np.asarray(flagged.weights) > 0, inner)
    np.testing.assert_array_equal(np.asarray(flagged.edge_ids)[inner], np.flatnonzero(inner))
    np.testing.assert_allclose(float(plain.coverage), 0.8)  # 10% off either end
    assert float(flagged.coverage) < float(plain.coverage)
    for a, b in zip(flagged, run(None, keep=inner), strict=True):  # the inner ones alone
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    for a, b in zip(run(~every), plain, strict=True):  # no flags: as without the argument
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


# slow (session 37, the suite's time): ``search_texture`` is off in every preset; the drawn-image
# tests above keep its flags, steps and association in the default suite
@pytest.mark.slow
def test_the_search_finds_a_wood_cube_whose_grain_it_fitted_without_the_rule():
    """Development seed 149 (wood, a 9.6 cm cube; not one of the seeds the rule was built on):
    a new tracker's search from scratch on frames 0 and 1 fits the cube within 1 cm and 2 deg
    with ``search_texture`` 0.25 (on ``RANDOMIZED_BENCHMARK``); without it, and with the texture
    segments only kept off the silhouette edges (0: no weak ones dropped), it sets the outline
    on grain lines (2.6-2.8 cm, 9 deg off)."""
    from hec_jax.geometry import BoxTracker
    from hec_jax.geometry.accuracy import symmetric_rotation_error_deg
    from hec_jax.mjx_scene.randomized import draw_scene, render_random_sequence

    scene = draw_scene(149)
    assert scene.look == "wood"
    seq, background = render_random_sequence(scene, 2, 30.0, 640, 480)
    for ratio in (0.25, None, 0.0):
        cfg = dataclasses.replace(RANDOMIZED_BENCHMARK, search_texture=ratio)
        for t in range(2):
            tracker = BoxTracker(seq.intrinsics, scene.edge_m, 30.0, cfg, background)
            step = tracker.update(seq.frames[t])
            err_m = np.linalg.norm(step.measured_position - seq.position[t])
            err_deg = symmetric_rotation_error_deg(step.pose_rotation[None], seq.rotation[t][None])
            close = bool(step.valid) and err_m < 0.01 and float(err_deg[0]) < 2.0
            assert close == (ratio == 0.25), (ratio, t, bool(step.valid), err_m, err_deg)
