"""The tracker's opt-in search options of issue 24 point 3 (``TrackConfig.search_keep``,
``blob_required``, ``low_contrast``) and the detectors under them, against synthetic truth and
against the one-stage search they shorten."""

import dataclasses

import cv2
import numpy as np
import pytest

from hec_jax.geometry import BoxTracker, TrackConfig, detect, track_box
from hec_jax.mjx_scene.render import render_swing

FPS = 30.0
EDGE = 0.1


@pytest.fixture(scope="module")
def seq():
    return render_swing(0.4, 4, FPS)


def _flat(shape, rgb, noise, seed):
    rng = np.random.default_rng(seed)
    img = np.broadcast_to(np.asarray(rgb, float), (*shape, 3)) + rng.normal(0, noise, (*shape, 3))
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_faint_regions_find_a_box_near_the_background_colour(seed):
    # a 30 px square 12 grey levels off the wall in one channel, sensor noise sigma 4: the usual
    # threshold (20) sees nothing, the blurred difference over its noise level finds the square
    bg = _flat((240, 320), (150, 110, 120), 4.0, seed)
    img = _flat((240, 320), (150, 110, 120), 4.0, seed + 100)
    x0, y0 = 100 + 20 * seed, 80
    img[y0 : y0 + 30, x0 : x0 + 30] = _flat((30, 30), (150, 122, 120), 4.0, seed + 200)
    assert detect.foreground_regions(img, bg) == []
    regions = detect.faint_foreground_regions(img, bg)
    assert regions, "no faint blob found"
    (bx0, by0, bx1, by1), area = regions[0]
    np.testing.assert_allclose([bx0, by0, bx1, by1], [x0, y0, x0 + 30, y0 + 30], atol=3)
    assert 0.8 * 900 <= area <= 1.2 * 900


@pytest.mark.parametrize("seed", [0, 1])
def test_faint_regions_find_nothing_in_noise(seed):
    bg = _flat((240, 320), (90, 140, 60), 4.0, seed)
    img = _flat((240, 320), (90, 140, 60), 4.0, seed + 50)
    assert detect.faint_foreground_regions(img, bg) == []


def test_stretched_lsd_finds_a_faint_edge():
    # a vertical step of 4 grey levels at x = 40 with noise: LSD's absolute gradient threshold
    # misses it; in the stretched window it is found on the true line
    rng = np.random.default_rng(3)
    patch = np.full((80, 80), 120.0)
    patch[:, 40:] += 4.0
    gray = np.clip(np.round(patch + rng.normal(0, 0.7, patch.shape)), 0, 255).astype(np.uint8)
    gray = cv2.GaussianBlur(gray, (3, 3), 0.6)
    roi = (0, 0, 80, 80)

    def on_line_px(seg):  # length of the segments on the step's line x = 40
        return sum(np.ptp(s[:, 1]) for s in seg if np.abs(s[:, 0] - 40).max() < 1.0)

    assert on_line_px(detect.detect_segments(gray, roi)) == 0
    seg = detect.detect_segments(gray, roi, stretch=True)
    assert on_line_px(seg) > 60, seg  # of the 80 px edge
    assert len(seg) <= 6  # the stretched noise gives no clutter


def test_stretch_leaves_a_contrasted_window_alone():
    rng = np.random.default_rng(4)
    patch = rng.integers(0, 256, (50, 60)).astype(np.uint8)
    assert detect.stretch_contrast(patch) is patch
    faint = (100 + rng.integers(0, 10, (50, 60))).astype(np.uint8)
    out = detect.stretch_contrast(faint)
    lo, hi = np.percentile(out, (1, 99))
    assert hi - lo >= 0.9 * detect.STRETCH_RANGE


@pytest.mark.slow  # its own compilation of the 96-start search (~20 s on the 2 CI cores)
def test_two_stage_search_keeping_every_start_is_the_one_stage_search(seq):
    # search_keep = init_starts runs every start through every round, in two calls: the same
    # tracker to round-off
    one = track_box(seq.frames, seq.intrinsics, EDGE, FPS)
    cfg = TrackConfig(search_keep=TrackConfig().init_starts)
    two = track_box(seq.frames, seq.intrinsics, EDGE, FPS, cfg)
    np.testing.assert_array_equal(one.valid, two.valid)
    np.testing.assert_allclose(two.measured_position, one.measured_position, atol=1e-9)
    np.testing.assert_allclose(two.pose_rotation, one.pose_rotation, atol=1e-9)


# slow (28 s of the CI's time, most of it compiling): the unbatched two-stage search, which no
# preset runs (the benchmark's is batched: tests/test_eye_randomized.py's threads test searches
# with it in the default suite)
@pytest.mark.slow
def test_two_stage_search_of_eight_starts_acquires(seq):
    tracker = BoxTracker(seq.intrinsics, EDGE, FPS, TrackConfig(search_keep=8))
    st = tracker.update(seq.frames[0])  # the first frame: a search from scratch
    assert st.valid
    assert np.linalg.norm(st.measured_position - seq.position[0]) < 0.005


@pytest.mark.parametrize("required", [True, False])
def test_blob_required_skips_the_search_without_a_moving_blob(seq, required):
    # the background is the frame itself: nothing moves. With blob_required no search runs (and
    # nothing is detected); without it the segments of the whole image are searched
    frame = seq.frames[0]
    cfg = dataclasses.replace(TrackConfig(), blob_required=required)
    tracker = BoxTracker(seq.intrinsics, EDGE, FPS, cfg, background=frame)
    calls = []
    search = tracker._search
    tracker._search = lambda *a, _f=search: calls.append(1) or _f(*a)
    st = tracker.update(frame)
    assert calls == ([] if required else [1])
    if required:
        assert not st.valid and not st.initialised


def test_blob_core_cuts_a_thick_rod_off_the_box():
    # a 40 px square hanging from a 9 px wide rod to the top of the image: the 5 px opening keeps
    # the rod, so the blob's box is the rod's and the square's; its compact core is the square
    bg = np.zeros((200, 200, 3), np.uint8)
    img = bg.copy()
    img[110:150, 80:120] = 200
    img[0:110, 96:105] = 200
    (box, area), *_ = detect.foreground_regions(img, bg)
    assert box[1] == 0  # the rod is in the plain blob
    (box, area), *_ = detect.foreground_regions(img, bg, core=0.4)
    # the core's disk (8 px radius here) keeps a stub of the rod a few px long
    np.testing.assert_allclose(box, (80, 110, 120, 150), atol=4)
    assert abs(area - 1600) < 0.1 * 1600
    # a compact blob keeps its box (the disk rounds its corners: a few % of its area)
    img2 = bg.copy()
    img2[50:90, 60:100] = 200
    [(box, area)] = detect.foreground_regions(img2, bg, core=0.4)
    assert box == (60, 50, 100, 90) and 0.9 * 1600 <= area <= 1600


@pytest.mark.parametrize("seed", [0, 1])
def test_outside_foreground_tells_a_fit_inside_the_box_from_the_box(seed):
    """A 60 px square (the box's silhouette) with a 2 px rod on a noisy background: the ring
    outside the true outline is background (the rod opened away), the ring outside a square
    shrunk by 30% about the same centre (a box fitted too far away) lies on the box; pixels
    ignored (a known occluder) or outside the image are not counted."""
    bg = _flat((240, 320), (90, 100, 110), 3.0, seed)
    img = _flat((240, 320), (90, 100, 110), 3.0, seed + 10)
    x0, y0 = 120 + 10 * seed, 90
    img[y0 : y0 + 60, x0 : x0 + 60] = _flat((60, 60), (170, 60, 40), 3.0, seed + 20)
    img[:y0, x0 + 29 : x0 + 31] = (200, 200, 200)  # the rod, from the top of the image
    square = lambda a, b, n: np.array([[a, b], [a + n, b], [a + n, b + n], [a, b + n]], float)  # noqa: E731
    true = square(x0, y0, 60)
    inner = square(x0 + 9, y0 + 9, 42)  # its ring (2-8.3 px out) on the box
    assert detect.outside_foreground_fraction(img, bg, true) < 0.05
    assert detect.outside_foreground_fraction(img, bg, inner) > 0.9
    ignore = np.zeros((240, 320), bool)
    ignore[y0 - 10 : y0 + 70, x0 - 10 : x0 + 70] = True
    assert np.isnan(detect.outside_foreground_fraction(img, bg, inner, ignore=ignore))
    partly = ignore.copy()
    partly[:, x0 + 30 :] = False  # the right half of the ring counted: on the box
    assert detect.outside_foreground_fraction(img, bg, inner, ignore=partly) > 0.9
    # a box at the image's left edge: the ring's part outside the image is not counted
    edge = _flat((240, 320), (90, 100, 110), 3.0, seed + 30)
    edge[y0 : y0 + 60, 0:40] = (170, 60, 40)
    assert detect.outside_foreground_fraction(edge, bg, square(-20, y0, 60)) < 0.05
    assert np.isnan(detect.outside_foreground_fraction(img, bg, true * np.nan))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_faint_masks_see_a_box_a_few_grey_levels_off(seed):
    """A 40 px square 9 grey levels off the wall in one channel, sensor noise sigma 3: the usual
    mask (3x3 blur over 12 grey levels) covers little of it, the mask with the frame's faint
    threshold (:func:`detect.faint_threshold`, the faint search's) most of it and almost
    nothing of the noise around; the silhouette checks follow."""
    bg = _flat((240, 320), (120, 100, 90), 3.0, seed)
    img = _flat((240, 320), (120, 100, 90), 3.0, seed + 100)
    x0, y0 = 110 + 15 * seed, 90
    img[y0 : y0 + 40, x0 : x0 + 40] = _flat((40, 40), (120, 109, 90), 3.0, seed + 200)
    thr = detect.faint_threshold(img, bg)
    assert 6.0 <= thr < 7.0
    roi = (x0 - 40, y0 - 40, x0 + 80, y0 + 80)
    usual, (wx, wy, _, _) = detect.foreground_mask(img, bg, roi)
    faint, _ = detect.foreground_mask(img, bg, roi, faint_threshold=thr)
    inside = np.zeros(usual.shape, bool)
    inside[y0 - wy + 3 : y0 - wy + 37, x0 - wx + 3 : x0 - wx + 37] = True  # 3 px in: blur
    outside = np.ones(usual.shape, bool)
    outside[y0 - wy - 5 : y0 - wy + 45, x0 - wx - 5 : x0 - wx + 45] = False
    assert usual[inside].mean() < 0.2 and faint[inside].mean() > 0.9
    assert faint[outside].mean() < 0.01
    assert np.all(faint >= usual)  # the faint foreground is added, nothing taken away
    square = np.array([[x0, y0], [x0 + 40, y0], [x0 + 40, y0 + 40], [x0, y0 + 40]], float)
    assert detect.foreground_fraction(img, bg, square) < 0.2
    assert detect.foreground_fraction(img, bg, square, faint_threshold=thr) > 0.8
    assert detect.foreground_iou(img, bg, square, faint_threshold=thr) > 0.8
