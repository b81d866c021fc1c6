"""``TrackConfig.short_edge_margin_px``: ``detect.edge_points`` starts its points 3 px from each
corner, so a model edge shorter than 6 px + the spacing gets none; with the option such a short
edge is sampled from the given margin of its corners (``short_end_margin``).

Independent truth: a box drawn at a known pose with area coverage (``drawn_box``), whose
projected edges (the pinhole corners) the short edges' points must lie on.
"""

import dataclasses

import numpy as np
import pytest
from drawn_box import DEPTH, SIZE, K, draw_box, nearly_face_on, tracked_fits

from hec_jax.geometry import BoxTracker, TrackConfig, detect
from hec_jax.geometry.track import usable_edges

MARGIN = 1.6  # [px] the benchmark's value: two edge-blur sigmas (0.8 px)
# yaw, pitch [deg] of an 18 px box at 2 m whose narrower faces' receding edges are 4-7 px long
SHORT_EDGE_POSES = [(15.0, 10.0), (20.0, -12.0), (-18.0, 14.0), (12.0, -8.0)]


def _points(gray, edges, usable, margin):
    cfg = TrackConfig()
    return detect.edge_points(
        gray,
        edges,
        usable,
        spacing=cfg.edge_spacing_px,
        search=cfg.search_px,
        blur=cfg.edge_blur_px,
        short_end_margin=margin,
    )


@pytest.mark.parametrize("yaw_deg, pitch_deg", SHORT_EDGE_POSES)
def test_short_edges_are_sampled_on_their_own_lines_only_with_the_option(yaw_deg, pitch_deg):
    """Without the option the usable edges under 7 px get no point; with it each gets at least
    one, and their points lie on the drawn box's edges (median distance under 0.3 px; a point
    1.6 px from a corner can take the neighbouring edge's step, about 1.1 px off). The longer
    edges' points are the same to the bit."""
    rotation, t = nearly_face_on(yaw_deg, pitch_deg)
    cfg = TrackConfig()
    edges, usable = usable_edges(rotation, t, SIZE, K, cfg)
    length = np.linalg.norm(edges[:, 1] - edges[:, 0], axis=-1)
    short = usable & (length < 2 * 3.0 + cfg.edge_spacing_px)
    assert short.any()
    gray = draw_box(rotation, t)
    before, before_ids = _points(gray, edges, usable, None)
    after, after_ids = _points(gray, edges, usable, MARGIN)
    assert not np.isin(before_ids, np.flatnonzero(short)).any()
    on_long = ~np.isin(after_ids, np.flatnonzero(short))
    assert np.array_equal(after[on_long], before) and np.array_equal(after_ids[on_long], before_ids)
    offsets = []
    for j in np.flatnonzero(short):
        mine = after_ids == j
        assert mine.any()
        d = edges[j, 1] - edges[j, 0]
        normal = np.array([-d[1], d[0]]) / np.linalg.norm(d)
        offsets.append((after[mine] - edges[j, 0]) @ normal)
    assert np.median(np.abs(np.concatenate(offsets))) < 0.3


def test_an_edge_shorter_than_twice_the_margin_gets_no_point():
    """A 3 px edge: no point at a 1.6 px margin (3 < 3.2), one at 1.5 px (its midpoint)."""
    gray = np.full((40, 40), 200, np.uint8)
    gray[:, 20:] = 40  # a vertical step at x = 20 (the intrinsics convention's pixel edges)
    edges = np.array([[[20.0, 18.0], [20.0, 21.0]]])
    usable = np.array([True])
    assert len(_points(gray, edges, usable, None)[0]) == 0
    assert len(_points(gray, edges, usable, 1.6)[0]) == 0
    pts, _ = _points(gray, edges, usable, 1.5)
    assert len(pts) == 1
    assert pts[0, 1] == pytest.approx(19.5, abs=1e-9)  # the edge's midpoint
    assert abs(pts[0, 0] - 20.0) < 0.25  # on the step, within the search's 0.25 px grid


def _tracked_fits(rotation, t, margin) -> np.ndarray:
    """``drawn_box.tracked_fits`` with the default settings but ``short_edge_margin_px``."""
    return tracked_fits(rotation, t, TrackConfig(short_edge_margin_px=margin))


def test_the_tracker_s_fits_change_only_where_an_edge_is_short():
    """Through ``BoxTracker`` (search, then tracked frames): on a 36 px box turned well away from
    face on (every usable edge over 7 px) the option changes no fit, to the bit; on the 18 px
    box with 4-6 px receding edges the fits change (the tracker passes the option on)."""
    turned = nearly_face_on(35.0, -25.0, depth=DEPTH / 2)
    edges, usable = usable_edges(*turned, SIZE, K, TrackConfig())
    assert np.all(np.linalg.norm(edges[usable, 1] - edges[usable, 0], axis=-1) > 7.0)
    assert np.array_equal(_tracked_fits(*turned, None), _tracked_fits(*turned, MARGIN))
    short = nearly_face_on(*SHORT_EDGE_POSES[0])
    assert not np.allclose(_tracked_fits(*short, None), _tracked_fits(*short, MARGIN), atol=1e-4)


@pytest.mark.parametrize("margin", [0.0, -1.0, 3.0, True, "1.6"])
def test_bad_short_edge_margins_raise(margin):
    cfg = dataclasses.replace(TrackConfig(), short_edge_margin_px=margin)
    with pytest.raises(ValueError, match="short_edge_margin_px"):
        BoxTracker(K, SIZE, 30.0, cfg)


def test_edge_points_refuses_a_margin_that_is_not_positive():
    gray = np.full((20, 20), 100, np.uint8)
    with pytest.raises(ValueError, match="short_end_margin"):
        detect.edge_points(gray, np.zeros((1, 2, 2)), np.array([True]), short_end_margin=0.0)
