"""Coverage that knows the occluded pixels (``track.occluded_fraction``, ``track.associate``):
against the edges' geometry, and on a rendered swing with a known occluder.
"""

import cv2
import jax.numpy as jnp
import numpy as np
import pytest

from hec_jax.geometry import BoxTracker
from hec_jax.geometry.box_model import Pose, edge_visibility, face_visibility, project_edges
from hec_jax.geometry.detect import background_model
from hec_jax.geometry.synthetic import rotation_from_axis_angle
from hec_jax.geometry.track import TrackConfig, associate, occluded_fraction
from hec_jax.mjx_scene.render import render_swing


def test_occluded_fraction_against_the_edges_geometry():
    occluded = np.zeros((100, 200), bool)
    occluded[:, :50] = True  # columns x < 50
    edges = np.array(
        [
            [[10.0, 20.0], [90.0, 20.0]],  # half of it at x < 50
            [[60.0, 5.0], [60.0, 95.0]],  # right of the occluder
            [[5.0, 10.0], [45.0, 90.0]],  # inside
            [[250.0, 10.0], [300.0, 10.0]],  # outside the image: not occluded
            [[-30.0, 50.0], [30.0, 50.0]],  # half outside, half inside the occluder
            [[np.nan, 0.0], [1.0, 1.0]],  # a diverged pose: finite, not occluded
        ]
    )
    got = np.asarray(occluded_fraction(jnp.asarray(edges), jnp.asarray(occluded)))
    np.testing.assert_allclose(got, [0.5, 0.0, 1.0, 0.0, 0.5, 0.0])
    np.testing.assert_array_equal(occluded_fraction(jnp.asarray(edges), None), np.zeros(6))


def _view():
    """A cube seen with three faces (R, t in the camera frame), K, edge 0.1 m."""
    rot = rotation_from_axis_angle(np.array([1.0, 1.0, 0.3]), 0.7)
    k = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
    return Pose(jnp.asarray(rot), jnp.asarray([0.03, -0.02, 0.7])), k, 0.1


@pytest.mark.parametrize("hidden", [(0,), (1, 5), (2, 6, 8)])
def test_coverage_counts_only_the_edge_length_outside_the_occluded_pixels(hidden):
    pose, k, size = _view()
    cfg = TrackConfig()
    edges = np.asarray(project_edges(pose, size, jnp.asarray(k)))
    length = np.linalg.norm(edges[:, 1] - edges[:, 0], axis=-1)
    vis = np.asarray(edge_visibility(face_visibility(pose, size))) & (length > cfg.min_edge_px)
    hidden = list(np.flatnonzero(vis)[list(hidden)])  # of the 9 visible edges
    # the image shows every visible edge but the hidden ones, exactly
    shown = [e for e in np.flatnonzero(vis) if e not in hidden]
    segments = np.zeros((cfg.max_segments, 2, 2))
    segments[: len(shown)] = edges[shown]
    mask = np.arange(cfg.max_segments) < len(shown)
    # an occluder over the hidden edges (7 px wide: it also covers a few px of their
    # neighbours at the shared corners) and one far from the cube
    occluded = np.zeros((480, 640), np.uint8)
    for e in hidden:
        a, b = (tuple(int(round(v)) for v in p) for p in edges[e])
        cv2.line(occluded, a, b, 1, 7)
    far = np.zeros((480, 640), bool)
    far[:40, :40] = True

    def coverage(occ):
        gate_cos = np.cos(np.deg2rad(cfg.gate_deg))
        asc = associate(
            pose, jnp.asarray(segments), jnp.asarray(mask), size, jnp.asarray(k), 2.0,
            gate_cos, cfg.min_edge_px, None if occ is None else jnp.asarray(occ),
        )  # fmt: skip
        return float(asc.coverage)

    expected = np.sum(length[shown]) / np.sum(length[vis])
    np.testing.assert_allclose(coverage(None), expected, rtol=1e-9)
    np.testing.assert_allclose(coverage(far), expected, rtol=1e-9)  # nothing of the cube hidden
    # told the hidden edges' pixels, the coverage is of what could be seen: all of it (the
    # neighbours' covered corners make the observable length a little shorter: capped at 1)
    assert coverage(occluded.astype(bool)) == 1.0
    assert expected < 0.92


def test_tracker_takes_occluded_pixels_and_checks_their_shape():
    seq = render_swing(0.5, 8, 30.0)
    bg = background_model(seq.frames)
    far = np.zeros(seq.frames.shape[1:3], bool)
    far[:20, :20] = True  # pixels far from the cube: the same fits as without
    plain = BoxTracker(seq.intrinsics, 0.1, 30.0, background=bg)
    told = BoxTracker(seq.intrinsics, 0.1, 30.0, background=bg)
    for frame in seq.frames:
        a, b = plain.update(frame), told.update(frame, far)
        assert a.valid and b.valid
        np.testing.assert_array_equal(a.measured_position, b.measured_position)
        assert a.coverage == b.coverage
    with pytest.raises(ValueError, match="occluded"):
        told.update(seq.frames[0], far[:-1])
