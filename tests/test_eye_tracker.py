"""The online tracker (``BoxTracker``): same causal path as ``track_box``, extrapolation, reset."""

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from hec_jax.geometry import BoxTracker, TrackConfig, TrackStep, track_box
from hec_jax.geometry import filter as kf
from hec_jax.geometry.detect import background_model
from hec_jax.geometry.synthetic import rotation_from_axis_angle
from hec_jax.mjx_scene.render import render_swing

FPS = 30.0
EDGE = 0.1


@pytest.fixture(scope="module")
def seq():
    return render_swing(0.5, 24, FPS)


@pytest.fixture(scope="module")
def steps(seq):
    tracker = BoxTracker(seq.intrinsics, EDGE, FPS, background=background_model(seq.frames))
    return tracker, [tracker.update(f) for f in seq.frames]


def _fit_error_without_gaps(seq, steps) -> float:
    """[m] The largest distance from the truth of a fit of the default tracker that saw every
    frame of this swing, frame 12 left out (fitted ~2 cm off with or without a gap); itself held
    under 1 cm, so a worse tracker cannot raise its own bar without failing.

    The bound for a frame fitted after a gap (by the default tracker, or in the defer test by one
    whose extra hypotheses act only on failed frames). **A loosening** (2026-12-03): it was 5 mm,
    set on a Zen 4 CPU's rendering; on a Zen 3's (the CI's since) the no-gap fits of frames 0-23
    are 0.4-7.8 mm off (frame 12 23 mm), frame 11 is 3.7 mm off without a gap and 6.6 mm after
    ``skip(1)`` (4.8 mm fitted from the un-skipped prediction), so one frame's error varies by a
    few mm with the last bits of the frames and the fit, and 5 mm lay inside that spread. Here
    7.8 mm; the Zen 4 value was not measured. At a one-frame gap this cannot tell ``skip`` from
    no ``skip`` (nor could 5 mm); at 3 and 4 frames the fit without ``skip`` failed (measured,
    not asserted). ``docs/testing.md``, session 63.
    """
    _, st = steps
    err = [np.linalg.norm(s.measured_position - seq.position[s.frame]) for s in st if s.frame != 12]
    assert all(s.valid for s in st) and max(err) < 0.01, err
    return max(err)


def test_update_matches_track_box(seq, steps):
    _, st = steps
    tr = track_box(seq.frames, seq.intrinsics, EDGE, FPS)
    assert isinstance(st[0], TrackStep)
    np.testing.assert_array_equal([s.valid for s in st], tr.valid)
    np.testing.assert_array_equal([s.position for s in st], tr.causal_position)
    np.testing.assert_array_equal([s.velocity for s in st], tr.causal_velocity)
    np.testing.assert_array_equal([s.acceleration for s in st], tr.causal_acceleration)
    np.testing.assert_array_equal([s.measured_position for s in st], tr.measured_position)
    np.testing.assert_array_equal([s.edge_ids for s in st], tr.edge_ids)
    assert [s.frame for s in st] == list(range(len(seq.frames)))
    s = st[-1]
    assert s.initialised and s.pose_rotation.shape == (3, 3) and s.segments.shape[1:] == (2, 2)
    assert set(s.timing_ms) == {"detection_ms", "estimation_ms", "total_ms"}


def test_predict_extrapolates_the_filter(seq, steps):
    tracker, st = steps
    now = tracker.predict(0.0)
    np.testing.assert_allclose(now.position, st[-1].position)
    np.testing.assert_allclose(now.velocity, st[-1].velocity)
    dt = 0.4 / FPS
    later = tracker.predict(dt)
    p, v, a = st[-1].position, st[-1].velocity, st[-1].acceleration
    np.testing.assert_allclose(later.position, p + v * dt + 0.5 * a * dt**2)
    np.testing.assert_allclose(later.velocity, v + a * dt)
    assert np.all(np.linalg.eigvalsh(later.position_cov - now.position_cov) > 0)
    # mid-swing (the cube moves ~4 cm per frame), one frame ahead: the prediction is much
    # closer to the next frame's true centre than the last estimate (measured 6 mm vs 41 mm)
    mid = BoxTracker(seq.intrinsics, EDGE, FPS, background=background_model(seq.frames))
    last = [mid.update(f) for f in seq.frames[:12]][-1]
    ahead = mid.predict(1.0 / FPS)
    err_pred = np.linalg.norm(ahead.position - seq.position[12])
    err_last = np.linalg.norm(last.position - seq.position[12])
    assert err_last > 0.03 and err_pred < 0.25 * err_last, (err_pred, err_last)


def test_reset_and_no_background(seq):
    # no background given: whole-image search, then the median of the frames seen (from frame 12)
    tracker = BoxTracker(seq.intrinsics, EDGE, FPS)
    out = [tracker.update(f) for f in seq.frames][-6:]
    assert np.mean([s.valid for s in out]) >= 0.6
    err = [np.linalg.norm(s.measured_position - seq.position[s.frame]) for s in out if s.valid]
    assert np.median(err) < 0.02
    tracker.reset()
    assert tracker.frame == 0 and not tracker.predict(0.1).initialised
    assert tracker.update(np.zeros_like(seq.frames[0])).valid == False  # noqa: E712


def test_bad_input_raises(seq):
    tracker = BoxTracker(seq.intrinsics, EDGE, FPS, background=seq.frames[0])
    with pytest.raises(ValueError, match="uint8"):
        tracker.update(seq.frames[0].astype(np.float32))
    with pytest.raises(ValueError, match="shape"):
        tracker.update(seq.frames[0, ..., 0])
    with pytest.raises(ValueError, match="match"):
        tracker.update(np.zeros((64, 64, 3), np.uint8))
    with pytest.raises(ValueError):
        BoxTracker(seq.intrinsics, EDGE, FPS, background=np.zeros((4, 4, 4), np.uint8))
    with pytest.raises(ValueError):
        BoxTracker(seq.intrinsics, 0.0, FPS)


def test_warm_up_compiles_the_refinement_even_where_no_located_fit_passes(seq):
    """``BoxTracker.warm_up`` compiles every path of ``update`` before a real-time run. The
    tracker no longer refines a fit whose located fit failed (``_fit`` returns None), but in
    the warm-up it does, so the refinement is compiled on a frame where every located fit
    fails too (here: every one made to fail); after the warm-up the skip is back on."""
    tracker = BoxTracker(seq.intrinsics, EDGE, FPS, background=background_model(seq.frames))
    locate = tracker._locate
    failed = []

    def failing(*args):
        loc = locate(*args)
        failed.append(1)
        return loc._replace(valid=loc.valid & False)

    tracker._locate = failing
    tracker.warm_up(seq.frames[3])
    assert failed and tracker._finish._cache_size() >= 1
    assert not tracker._refine_failed
    # out of the warm-up, the same failed located fits are not refined
    tracker._finish = None  # any refinement would raise
    tracker.update(seq.frames[3])
    assert not tracker._refine_failed


def test_a_fit_in_another_labelling_of_the_cube_s_axes_changes_nothing(seq):
    # one frame's fit comes back in another of the cube's 24 labellings (as a search's may):
    # the same box, its axes named otherwise. The track keeps its own labelling, so every later
    # step is the one without the relabelling (before, the rotation jumped by 90 deg there and
    # the constant-angular-velocity prediction spun the next frames by as much each:
    # development seeds 28 and 155 of the randomized benchmark)
    turn = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # 90 deg about x
    runs = []
    for relabel, keep in ((False, True), (True, True), (True, False)):
        cfg = TrackConfig(keep_labelling=keep)
        tracker = BoxTracker(seq.intrinsics, EDGE, FPS, cfg, background_model(seq.frames))
        steps = [tracker.update(f) for f in seq.frames[:8]]
        fit = tracker._fit
        if relabel:
            tracker._fit = lambda *a, _fit=fit, **k: (
                lambda fin: (
                    None if fin is None else fin._replace(rotation=np.asarray(fin.rotation) @ turn)
                )
            )(_fit(*a, **k))
        steps.append(tracker.update(seq.frames[8]))
        tracker._fit = fit
        steps += [tracker.update(f) for f in seq.frames[9:16]]
        runs.append(steps)
    plain, relabelled, as_before = runs
    turned = as_before[8].pose_rotation @ plain[8].pose_rotation.T  # without keep_labelling
    angle = np.degrees(np.arccos(np.clip((np.trace(turned) - 1.0) / 2.0, -1.0, 1.0)))
    assert abs(angle - 90.0) < 1e-6
    assert all(s.valid for s in relabelled[1:])
    for a, b in zip(plain, relabelled, strict=True):
        np.testing.assert_allclose(b.pose_rotation, a.pose_rotation, atol=1e-9)
        np.testing.assert_allclose(b.angular_velocity, a.angular_velocity, atol=1e-7)
        np.testing.assert_allclose(b.measured_position, a.measured_position, atol=1e-9)


@pytest.mark.parametrize("gap", [1, 3, 4])
def test_skip_predicts_over_unseen_frames(seq, steps, gap):
    # frames 10 .. 9 + gap never seen (dropped by a busy eye): skip(gap) moves the filter and the
    # (frame 12 is left out as the frame after a gap: the tracker fits it 20 mm off in any case)
    # frame count over them, so the next frame is fitted at its own time
    bg = background_model(seq.frames)
    tracker = BoxTracker(seq.intrinsics, EDGE, FPS, background=bg)
    for f in seq.frames[:10]:
        tracker.update(f)
    ahead = tracker.predict((gap + 1) / FPS)
    tracker.skip(gap)
    assert tracker.frame == 10 + gap
    after = tracker.predict(1.0 / FPS)  # F(dt)^(gap+1) = F((gap+1) dt): float32 round-off
    np.testing.assert_allclose(after.position, ahead.position, atol=1e-6)
    np.testing.assert_allclose(after.velocity, ahead.velocity, atol=1e-5)
    st = tracker.update(seq.frames[10 + gap])
    assert st.valid and st.frame == 10 + gap
    error = np.linalg.norm(st.measured_position - seq.position[10 + gap])
    assert error <= _fit_error_without_gaps(seq, steps)
    # a long gap (a starved consumer): the rotation stays a rotation, the prediction finite
    tracker.skip(300)
    late = tracker.predict(0.0)
    np.testing.assert_allclose(late.pose_rotation @ late.pose_rotation.T, np.eye(3), atol=1e-9)
    assert np.all(np.isfinite(late.position)) and np.all(np.isfinite(late.position_cov))
    # the same frame taken as the one after the last seen (no skip): measured, the fit fails
    # (mid-swing the cube moves ~4 cm per frame); not asserted, it is the reason for skip


def test_skip_rejects_bad_counts(seq):
    tracker = BoxTracker(seq.intrinsics, EDGE, FPS, background=seq.frames[0])
    for bad in (-1, 1.5, True, None):
        with pytest.raises(ValueError, match="integer"):
            tracker.skip(bad)
    tracker.skip(0)  # nothing to account for: no change
    assert tracker.frame == 0 and not tracker.predict(0.0).initialised


def _offset_prediction(tracker, dx_m):
    """Move the tracker's prediction ``dx_m`` [m] along camera x (as after an unmodelled push)."""
    mean = np.array(tracker._predicted.mean)
    mean[0] += dx_m
    tracker._predicted = kf.FilterState(mean, tracker._predicted.cov)


@pytest.mark.slow  # the local search's recovery of a sudden turn stays in the default suite
def test_local_search_reacquires_without_a_search_from_scratch(seq):
    # the filter's prediction 6 cm off the cube (as after an unmodelled push): the tracked fit
    # fails; with local_starts the search around the prediction and the last fit finds the cube
    # again (measured 3.4 mm, ~10 ms), without it the search from scratch runs (~0.25 s)
    bg = background_model(seq.frames)
    for starts in (12, 1, 0):
        tracker = BoxTracker(
            seq.intrinsics, EDGE, FPS, TrackConfig(local_starts=starts), background=bg
        )
        for f in seq.frames[:9]:
            tracker.update(f)
        searched = []
        acquire = tracker._acquire
        tracker._acquire = lambda *a, _f=acquire, _s=searched: _s.append(1) or _f(*a)
        assert tracker.update(seq.frames[9]).fit_source == "tracked"
        _offset_prediction(tracker, 0.06)
        st = tracker.update(seq.frames[10])
        assert st.valid
        assert np.linalg.norm(st.measured_position - seq.position[10]) < 0.005
        assert searched == ([] if starts else [1]), starts
        assert st.fit_source == ("local" if starts else "search")


@pytest.mark.slow  # the turned starts' recovery itself is in the default suite (the next test)
def test_local_search_runs_its_turned_starts_only_when_the_predicted_rotation_fails(seq):
    # the local search's two stages: the predicted rotation at both centres, then its turns;
    # a passing first stage ends the search, a failing one (forced here) hands on to the turns
    # (``local_keep`` 3: the turned starts' fine gates for the 3 best of 2 x 5 only)
    bg = background_model(seq.frames)
    for force_first_to_fail, keep in ((False, 0), (True, 0), (True, 3)):
        cfg = TrackConfig(local_starts=6, local_keep=keep)
        tracker = BoxTracker(seq.intrinsics, EDGE, FPS, cfg, background=bg)
        for f in seq.frames[:10]:
            tracker.update(f)
        first, rest = tracker._local
        calls = []

        def first_stage(*a, _f=first, _c=calls, _fail=force_first_to_fail):
            _c.append("first")
            loc = _f(*a)
            return loc._replace(valid=loc.valid & (not _fail))

        def rest_stage(*a, _f=rest, _c=calls):
            _c.append("rest")
            return _f(*a)

        tracker._local = (first_stage, rest_stage)
        acquire = tracker._acquire
        tracker._acquire = lambda *a, _f=acquire, _c=calls: _c.append("scratch") or _f(*a)
        _offset_prediction(tracker, 0.06)
        st = tracker.update(seq.frames[10])
        assert calls == (["first", "rest"] if force_first_to_fail else ["first"])
        assert st.valid
        assert st.fit_source == ("local_turned" if force_first_to_fail else "local")
        assert np.linalg.norm(st.measured_position - seq.position[10]) < 0.005
    one = BoxTracker(seq.intrinsics, EDGE, FPS, TrackConfig(local_starts=1), background=bg)
    assert one._local[1] is None  # no turns: the first stage only


# slow, every setting (the CI's time: the real-time eye's (4, 0.1) alone took 71 s there, its
# warm_up compiling every form). The default suite keeps the turned starts' recovery with (4, 0.1)
# on the real-time eye's own frames: test_the_held_cube_s_turned_recoveries_with_fewer_turned_starts
@pytest.mark.parametrize(
    "keep, merge",
    [
        pytest.param(0, 0.0, marks=pytest.mark.slow),
        pytest.param(4, 0.0, marks=pytest.mark.slow),
        pytest.param(4, 0.1, marks=pytest.mark.slow),
        pytest.param(0, 10.0, marks=pytest.mark.slow),
    ],
)
def test_local_search_recovers_a_sudden_turn_from_its_turned_starts(seq, keep, merge):
    # the last rotations turned by 25 deg (as by an impact): the tracked fit fails and, with the
    # predicted rotation's stage made to fail (below), a turned start finds the cube; with
    # ``local_keep`` 4 only the 4 best turned starts after the coarse gates go through the fine
    # ones (a fraction of the time);
    # with ``local_merge`` the turns start at the predicted centre alone where the last fitted
    # one is that close (mid-swing the two are ~4 cm apart: 0.1 box sizes keeps both, 10
    # merges them). warm_up compiles every form: nothing compiles in update
    bg = background_model(seq.frames)
    cfg = TrackConfig(local_starts=12, local_keep=keep, local_merge=merge)
    tracker = BoxTracker(seq.intrinsics, EDGE, FPS, cfg, background=bg)
    tracker.warm_up(seq.frames[0])
    compiled = [f._cache_size() for f in tracker._local]
    for f in seq.frames[:14]:
        tracker.update(f)
    axis = np.random.default_rng(5).normal(size=(8, 3))[6]
    turn = rotation_from_axis_angle(axis / np.linalg.norm(axis), np.deg2rad(25.0))
    tracker._rot_prev, tracker._rot_prev2 = turn @ tracker._rot_prev, turn @ tracker._rot_prev2
    first, rest = tracker._local
    centres, first_ran = [], []

    def first_stage_failing(*a, _f=first):
        # Whether the predicted rotation's own stage fails 25 deg off depends on the CPU: it
        # did on Zen 4, and on Zen 3 it recovered the turn itself (docs/testing.md, session 66).
        # This test is about the turned starts, so that stage is run and then made to fail.
        first_ran.append(1)
        return _f(*a)._replace(valid=False)

    tracker._local = (
        first_stage_failing,
        lambda *a, _f=rest: centres.append(a[1].shape[0]) or _f(*a),
    )
    from hec_jax.report import CompileMeter

    meter = CompileMeter().install()  # JAX's own trace and compile events, any function
    try:
        st = tracker.update(seq.frames[14])
    finally:
        meter.uninstall()
    assert st.valid and st.fit_source == "local_turned"
    assert np.linalg.norm(st.measured_position - seq.position[14]) < 0.002
    assert first_ran == [1] and centres == [1 if merge > 1 else 2]
    assert [f._cache_size() for f in (first, rest)] == compiled
    assert meter.events == 0, f"traced or compiled in update: {meter.last_name}"


# the default suite keeps the real-time eye's setting (1); the others are slow
@pytest.mark.parametrize(
    "defer", [pytest.param(0, marks=pytest.mark.slow), 1, pytest.param(2, marks=pytest.mark.slow)]
)
def test_the_search_from_scratch_waits_for_defer_search_failed_frames(seq, steps, defer):
    # black frames while the filter runs (the cube hidden): with ``defer_search`` n the first n
    # failed frames in a row are left to the prediction (invalid, no search from scratch), the
    # next ones searched near it; once lost (``lost_after`` 3) every frame is searched. A frame
    # left to the prediction does not disturb the next one: the cube is tracked again there
    bg = background_model(seq.frames)
    cfg = TrackConfig(stop_hypothesis=True, local_starts=6, defer_search=defer)
    tracker = BoxTracker(seq.intrinsics, EDGE, FPS, cfg, background=bg)
    for f in seq.frames[:10]:
        assert tracker.update(f).valid
    searched = []
    acquire = tracker._acquire
    tracker._acquire = lambda *a, _f=acquire, _s=searched: _s.append(tracker.frame) or _f(*a)
    black = np.zeros_like(seq.frames[0])
    st = tracker.update(black)
    assert not st.valid and st.initialised and st.fit_source == ""
    assert st.search_deferred == (defer > 0)
    assert searched == ([] if defer else [10])
    st = tracker.update(seq.frames[11])  # the cube again, one frame after the last fit
    assert st.valid and st.fit_source == "tracked"
    error = np.linalg.norm(st.measured_position - seq.position[11])
    assert error <= _fit_error_without_gaps(seq, steps)
    searched.clear()
    lost = [tracker.update(black) for _ in range(5)]  # frames 12-16: lost after 3
    assert [s.search_deferred for s in lost] == [i < defer for i in range(5)]
    assert searched == [12 + i for i in range(5) if i >= defer]
    assert not any(s.valid for s in lost)


def test_defer_search_must_be_a_count(seq):
    for bad in (-1, 1.5, None):
        with pytest.raises(ValueError, match="defer_search must be an integer >= 0"):
            BoxTracker(seq.intrinsics, EDGE, FPS, TrackConfig(defer_search=bad))


# frame 9 has no blob to search (it breaks a run of failed searches when it is searched)
_LOST_SEARCHED = {
    1: list(range(18)),
    2: [0, 1, 2, 3, 5, 7, 9, 10, 11, 12, 13, 15, 17],
    3: [0, 1, 2, 3, 6, 9, 10, 11, 12, 13, 16],
}


@pytest.mark.parametrize("every", [1, 2, pytest.param(3, marks=pytest.mark.slow)])
def test_once_lost_a_failing_search_runs_on_every_lost_search_every_frames(seq, every):
    # the search from scratch stubbed to fail (a blob it cannot fit): the first
    # ``lost_search_after`` (4) frames are searched, then one in ``every``; a searched frame
    # without a blob starts the count again. With the real search back, the cube is found on
    # the next frame that is searched
    bg = background_model(seq.frames)
    cfg = TrackConfig(lost_search_every=every)
    tracker = BoxTracker(seq.intrinsics, EDGE, FPS, cfg, background=bg)
    searched = []
    acquire = tracker._acquire

    def failing(gray, gate):
        searched.append(tracker.frame)
        tracker._searched = tracker.frame != 9
        return None

    tracker._acquire = failing
    steps = [tracker.update(f) for f in seq.frames[:18]]
    assert searched == _LOST_SEARCHED[every]
    assert [s.search_skipped for s in steps] == [i not in searched for i in range(18)]
    assert not any(s.valid for s in steps)
    tracker._acquire = acquire
    later = [tracker.update(f) for f in seq.frames[18 : 18 + every]]
    first = next(i for i, s in enumerate(later) if not s.search_skipped)
    assert later[first].valid and later[first].fit_source == "search"
    assert not any(s.valid for s in later[:first])
    # the cube found (a first fit from scratch, no filter behind it: within 2 cm at 1.6 m)
    assert np.linalg.norm(later[first].measured_position - seq.position[18 + first]) < 0.02
    tracker.reset()  # a new track searches every frame again
    tracker._acquire = failing
    searched.clear()
    assert not any(tracker.update(f).search_skipped for f in seq.frames[:4])


def test_lost_search_every_must_be_a_count(seq):
    for name, bad in (
        ("lost_search_every", 0),
        ("lost_search_every", 1.5),
        ("lost_search_after", -1),
    ):
        with pytest.raises(ValueError, match=f"{name} must be an integer"):
            BoxTracker(seq.intrinsics, EDGE, FPS, TrackConfig(**{name: bad}))


def _difference_numpy(image, background, shadow_ratio=(0.25, 0.92), shadow_tol=0.08):
    """``detect.difference`` as first written, in NumPy (the reference for the OpenCV one)."""
    diff = np.abs(image.astype(np.int16) - background.astype(np.int16)).astype(np.uint8)
    if diff.ndim != 3:
        return diff
    out = diff.max(axis=-1)
    bg = background.astype(np.float32)
    ratio = image.astype(np.float32) / np.maximum(bg, 1.0)
    mean = ratio.mean(axis=-1)
    shadow = (
        (mean >= shadow_ratio[0])
        & (mean <= shadow_ratio[1])
        & (np.abs(ratio - mean[..., None]).max(axis=-1) <= shadow_tol)
        & (bg.min(axis=-1) >= 24)
    )
    out[shadow] = 0
    return out


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("block_px", [None, 1000])
def test_colour_difference_is_the_numpy_one_bit_for_bit(seed, block_px, monkeypatch):
    """The OpenCV colour difference with its shadow test equals the NumPy reference on a
    background with a darkened (shadow) patch, a differently coloured box, sensor noise, dark
    pixels, windows (non-contiguous views) and gray images, with the background as an array
    and as a ``detect.Background`` (its terms kept); shadows and the box are found. The same
    with the shadow test in blocks of 1000 pixels (here 6 rows each)."""
    from hec_jax.geometry import detect
    from hec_jax.geometry.detect import Background, difference

    if block_px is not None:
        monkeypatch.setattr(detect, "_SHADOW_BLOCK_PX", block_px)

    rng = np.random.default_rng(seed)
    h, w = 120, 160
    background = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    background[:10] = rng.integers(0, 30, (10, w, 3))  # dark rows: not tested for shadows
    background[30:60, 20:70] = rng.integers(60, 256, (30, 50, 3))  # lit: ratios well resolved
    image = background.copy()
    image[30:60, 20:70] = (background[30:60, 20:70] * rng.uniform(0.3, 0.9)).astype(np.uint8)
    image[70:100, 90:140] = rng.integers(0, 256, 3, dtype=np.uint8)  # the box
    noisy = np.clip(image + rng.normal(0, 2, image.shape), 0, 255).astype(np.uint8)
    kept = Background(background)  # its terms computed once, windows as views of them
    for img in (image, noisy):
        for window in (np.s_[:, :], np.s_[5:90, 13:151]):
            want = _difference_numpy(img[window], background[window])
            np.testing.assert_array_equal(difference(img[window], background[window]), want)
            np.testing.assert_array_equal(difference(img[window], kept[window]), want)
        gray_img, gray_bg = img[..., 1], background[..., 1]
        np.testing.assert_array_equal(
            difference(gray_img, gray_bg), _difference_numpy(gray_img, gray_bg)
        )
        np.testing.assert_array_equal(
            difference(gray_img, Background(gray_bg)), _difference_numpy(gray_img, gray_bg)
        )
    got = difference(image, background)
    assert np.all(got[30:60, 20:70] == 0)  # the shadow patch
    assert (got[70:100, 90:140] > 0).mean() > 0.9  # the box


def _shadowed_box_scene(seed: int, noise: float) -> tuple[np.ndarray, np.ndarray]:
    """(image, background), 120x160 RGB: a random background, a darkened (shadow) patch, a
    box of one colour and sensor noise of ``noise`` grey levels."""
    rng = np.random.default_rng(seed)
    h, w = 120, 160
    background = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    background[30:60, 20:70] = rng.integers(60, 256, (30, 50, 3))
    image = background.copy()
    image[30:60, 20:70] = (background[30:60, 20:70] * rng.uniform(0.3, 0.9)).astype(np.uint8)
    image[70:100, 90:140] = rng.integers(0, 256, 3, dtype=np.uint8)
    image = np.clip(image + rng.normal(0, noise, image.shape), 0, 255).astype(np.uint8)
    return image, background


@pytest.mark.parametrize("seed", [3, 4])
def test_frame_differences_are_each_window_s_difference_and_reuse_kept_windows(seed):
    """``detect.FrameDifferences``: every window asked for, with and without the shadow test,
    equals the NumPy reference of that window (windows inside a kept one, partly outside it,
    at the image's borders, RGB and gray); a window inside one computed before (same shadow
    test) computes nothing; a wrong frame at the public functions is a clear error."""
    from hec_jax.geometry import detect
    from hec_jax.geometry.detect import Background, FrameDifferences

    image, background = _shadowed_box_scene(seed, noise=2.0)
    h, w = image.shape[:2]

    def want(img, bg, box, ratio):
        x0, y0, x1, y1 = box
        if ratio is None:
            diff = np.abs(img[y0:y1, x0:x1].astype(int) - bg[y0:y1, x0:x1])
            return diff.max(-1) if img.ndim == 3 else diff
        return _difference_numpy(img[y0:y1, x0:x1], bg[y0:y1, x0:x1])

    boxes = [(10, 20, 150, 110), (30, 40, 90, 100), (100, 5, 160, 60), (0, 0, w, h), (5, 5, 9, 9)]
    computed = []
    real = detect.difference
    counting = lambda *a, **k: (computed.append(a[0].shape), real(*a, **k))[1]  # noqa: E731
    for img, bg in ((image, Background(background)), (image[..., 1], background[..., 1])):
        diffs = FrameDifferences(img, bg)
        for ratio in ((0.25, 0.92), None):
            for box in boxes:
                computed.clear()
                with pytest.MonkeyPatch.context() as mp:
                    mp.setattr(detect, "difference", counting)
                    got = diffs(box, ratio)
                bgi = bg.image if isinstance(bg, Background) else bg
                np.testing.assert_array_equal(
                    got, want(img, bgi, box, ratio if img.ndim == 3 else None)
                )
                inside_kept = box in [
                    (30, 40, 90, 100),
                    (5, 5, 9, 9),
                ]  # in (10, 20, 150, 110) / frame
                assert (not computed) == inside_kept, (box, computed)
    other = image.copy()
    diffs = FrameDifferences(image, background)
    for bad in ((-1, 0, 10, 10), (0, 0, w + 1, 10), (5, 5, 5, 9), (0, 9, 10, 3)):
        with pytest.raises(ValueError, match="inside the 160x120 image"):
            diffs(bad)
        with pytest.raises(ValueError, match="inside the 160x120 image"):
            diffs.faint(bad)
    with pytest.raises(ValueError, match="FrameDifferences"):
        detect.foreground_mask(other, background, (0, 0, 50, 50), differences=diffs)
    with pytest.raises(ValueError, match="FrameDifferences"):
        detect.faint_window(other, background, (0, 0, 50, 50), 5.0, differences=diffs)
    got = detect.foreground_mask(image, background, (0, 0, 50, 50), differences=diffs)
    np.testing.assert_array_equal(
        got[0], detect.foreground_mask(image, background, (0, 0, 50, 50))[0]
    )


@pytest.mark.parametrize("seed", [5, 6])
def test_frame_differences_faint_windows_are_each_window_s_own_blur_bit_for_bit(seed):
    """``FrameDifferences.faint``: each window's difference equals the NumPy reference of the
    window blurred on its own (``cv2.blur`` of a copy, its border reflected at the window's
    sides) against the whole background blurred, with and without the shadow test, RGB and
    gray, for windows at the image's borders, inside others and the whole frame; a window
    asked for again computes nothing and gives the same numbers."""
    import cv2

    from hec_jax.geometry.detect import Background, FrameDifferences

    image, background = _shadowed_box_scene(seed, noise=3.0)
    h, w = image.shape[:2]
    blur = 5

    def want(img, bg, box, ratio):
        x0, y0, x1, y1 = box
        window = cv2.blur(img[y0:y1, x0:x1].copy(), (blur, blur))
        bgw = cv2.blur(bg, (blur, blur))[y0:y1, x0:x1]
        if ratio is None or img.ndim == 2:
            diff = np.abs(window.astype(int) - bgw)
            return diff.max(-1) if img.ndim == 3 else diff
        return _difference_numpy(window, bgw)

    boxes = [(10, 20, 150, 110), (30, 40, 90, 100), (0, 22, 60, 80), (0, 0, w, h), (40, 50, 44, 90)]
    for img, bg in ((image, Background(background)), (image[..., 1], background[..., 1])):
        bgi = bg.image if isinstance(bg, Background) else bg
        for ratio in ((0.25, 0.92), None):
            diffs = FrameDifferences(img, bg)
            direct = diffs._faint_direct
            for box in boxes + boxes[::-1]:
                computed = []
                diffs._faint_direct = lambda b, *a, _d=direct, _c=computed: (
                    _c.append(b),
                    _d(b, *a),
                )[1]
                again = diffs._faint.get((box, blur, ratio)) is not None
                got = diffs.faint(box, blur, ratio)
                np.testing.assert_array_equal(got, want(img, bgi, box, ratio), str(box))
                assert computed == ([] if again else [box])
            assert len(diffs._faint) == len(boxes)


def test_faint_regions_and_their_median_as_numpy_computes_them():
    """The faint foreground's noise level (the median of a uint8 difference, from its histogram)
    is NumPy's median, odd and even sizes; the faint blobs are the same with the background
    as an array and as a ``detect.Background`` (its blurred copy kept)."""
    from hec_jax.geometry.detect import Background, _median_uint8, faint_foreground_regions

    rng = np.random.default_rng(3)
    for shape in ((7,), (8,), (31, 17), (480, 640)):
        for high in (2, 9, 256):
            x = rng.integers(0, high, shape, dtype=np.uint8)
            assert _median_uint8(x) == float(np.median(x))
    background = rng.integers(40, 200, (120, 160, 3), dtype=np.uint8)
    image = np.clip(background + rng.normal(0, 2, background.shape), 0, 255).astype(np.uint8)
    image[40:80, 50:100] = np.clip(background[40:80, 50:100] + 12, 0, 255)  # a faint box
    want = faint_foreground_regions(image, background)
    assert want and want[0][0] == pytest.approx((50, 40, 100, 80), abs=3)
    kept = Background(background)
    assert faint_foreground_regions(image, kept) == want
    assert faint_foreground_regions(image, kept) == want  # the kept blur, second use


def test_stretch_percentiles_as_numpy_computes_them():
    """The contrast stretch's 1st and 99th percentiles of a uint8 window (from its histogram)
    are NumPy's ``np.percentile(x, (1, 99))`` bit for bit: sizes from 1 to a frame, wide,
    narrow and constant grey ranges, and NumPy's interpolation on both sides of a half."""
    from hec_jax.geometry.detect import _percentile_uint8

    rng = np.random.default_rng(5)
    for size in (1, 2, 3, 51, 100, 101, 257, 1000, 4097, 307200):
        for low, high in ((0, 256), (100, 104), (37, 38)):
            x = rng.integers(low, high, size, dtype=np.uint8)
            want = np.percentile(x, (1, 99))
            assert [_percentile_uint8(x, q) for q in (0.01, 0.99)] == [float(w) for w in want]
    # the windows of a frame, as the tracker takes them
    frame = np.clip(rng.normal(120, 25, (480, 640)), 0, 255).astype(np.uint8)
    for _ in range(50):
        x0, y0 = rng.integers(0, 600), rng.integers(0, 440)
        w, h = rng.integers(1, 200, 2)
        window = frame[y0 : y0 + h, x0 : x0 + w]
        want = np.percentile(window, (1, 99))
        assert [_percentile_uint8(window, q) for q in (0.01, 0.99)] == [float(v) for v in want]


def test_snapshot_and_restore_replay_the_track_frame_for_frame(seq):
    # a snapshot taken mid-swing, restored into a new tracker, gives the same fits on the next
    # frames as the tracker it came from (how a failed frame of a real-time run is replayed)
    bg = background_model(seq.frames)
    cfg = TrackConfig(local_starts=12)
    tracker = BoxTracker(seq.intrinsics, EDGE, FPS, cfg, background=bg)
    for f in seq.frames[:10]:
        tracker.update(f)
    snap = tracker.snapshot()
    import pickle

    snap = pickle.loads(pickle.dumps(snap))  # crosses a process boundary
    ahead = [tracker.update(f) for f in seq.frames[10:14]]
    replay = BoxTracker(seq.intrinsics, EDGE, FPS, cfg, background=bg)
    replay.restore(snap)
    again = [replay.update(f) for f in seq.frames[10:14]]
    for a, b in zip(ahead, again, strict=True):
        assert a.frame == b.frame and a.valid == b.valid and a.fit_source == b.fit_source
        np.testing.assert_array_equal(a.position, b.position)
        np.testing.assert_array_equal(a.pose_rotation, b.pose_rotation)
    # the snapshot is a copy: the replay did not change it, and restoring it again works
    replay.restore(snap)
    np.testing.assert_array_equal(replay.update(seq.frames[10]).position, ahead[0].position)
    with pytest.raises(ValueError, match="not a BoxTracker snapshot"):
        replay.restore({"_state": snap["_state"]})


@pytest.mark.slow  # a diagnostic off by default (eye_save_failed = 0); the default suite's time
def test_a_failed_frame_saved_by_the_real_time_eye_replays_to_the_same_fit(seq):
    # the real-time eye's diagnostic (``RealtimeConfig.eye_save_failed``): a frame whose
    # tracked fit failed (forced: the prediction 6 cm off) is saved with the tracker's snapshot
    # before it; the file, through pickle, replays to the same step on a new tracker
    import pickle

    from hec_jax.realtime.workers import (
        failed_frame_record,
        failed_frames_file,
        replay_failed_frames,
    )

    bg = np.stack([background_model(seq.frames)] * 3, axis=-1)  # given in colour, as the eye's
    tracker = BoxTracker(seq.intrinsics, EDGE, FPS, TrackConfig(local_starts=12), background=bg)
    for f in seq.frames[:10]:
        tracker.update(f)
    _offset_prediction(tracker, 0.06)
    occluded = np.zeros(seq.frames[10].shape[:2], bool)
    occluded[:40] = True  # pixels away from the cube (as the arm's mask)
    before = tracker.snapshot()
    st = tracker.update(seq.frames[10], occluded)
    assert st.valid and st.fit_source == "local"
    record = failed_frame_record({"number": 10}, seq.frames[10], occluded, before, st)
    saved = pickle.loads(pickle.dumps(failed_frames_file(tracker, [record])))
    assert saved["tracker"]["background"].shape == bg.shape
    (again,) = replay_failed_frames(saved)
    assert again.fit_source == record["fit_source"] == "local" and again.valid
    np.testing.assert_array_equal(again.measured_position, record["measured_position"])
    np.testing.assert_array_equal(again.position, st.position)


def _held_cube_frames(name="held_cube_failed_frames.npz", **changes):
    """The real-time eye's invalid frames (``tests/data/make_held_cube_frames.py``) replayed:
    per frame (tracker restored to its snapshot before the frame, image, occluded pixels, the
    simulator's cube centre (world x, z) [m], a function from the camera frame to world x, z),
    the tracker's recorded config with ``changes``. The default: those no hypothesis recovered
    before ``min_segments_hidden`` (the held cube face-on, the hand's masked disc over one of
    its edges, 3 segments left)."""
    import dataclasses
    import pickle
    from pathlib import Path

    d = np.load(Path(__file__).parent / "data" / name)
    ends = np.cumsum(d["snapshot_lengths"])
    snaps = [
        pickle.loads(d["snapshots"][e - n : e].tobytes())
        for e, n in zip(ends, d["snapshot_lengths"], strict=True)
    ]
    config = dataclasses.replace(pickle.loads(d["config"].tobytes()), **changes)
    tracker = BoxTracker(
        d["intrinsics"], float(d["size"]), float(d["fps"]), config, d["background"]
    )
    r_wc, t_wc = d["world_from_camera_r"], d["world_from_camera_t"]

    def world(p):
        return (r_wc @ p + t_wc)[[0, 2]]

    for image, occluded, snap, truth in zip(
        d["images"], d["occluded"], snaps, d["truth_world_xz"], strict=True
    ):
        tracker.restore(snap)
        yield tracker, image, occluded, truth, world


# slow: 4, the negative control (every hypothesis fails these frames without the change)
@pytest.mark.parametrize("floor", [pytest.param(4, marks=pytest.mark.slow), 3])
def test_a_fit_with_fewer_segments_where_the_mask_hides_an_edge(floor):
    # independent truth: the simulator's cube centre at each frame's exposure. With 4 segments
    # required (as before) every hypothesis fails these frames; with an edge hidden by the mask,
    # 3 segments suffice and the fit lands within 1 cm of the truth (measured 6.4 and 8.9 mm).
    # Not told the mask, nothing changes (the count stays 4)
    for tracker, image, occluded, truth, world in _held_cube_frames(min_segments_hidden=floor):
        before = tracker.snapshot()
        st = tracker.update(image, occluded)
        if floor == 4:
            assert not st.valid and st.fit_source == ""
        else:
            assert st.valid and st.fit_source == "three_segments"
            got = world(st.measured_position)
            assert np.linalg.norm(got - truth) < 0.01, (got, truth)
        tracker.restore(before)
        assert tracker.update(image).fit_source != "three_segments"


def test_gate_split_along_the_line_of_sight():
    # analytic cases: a centre 1.6 m deep, radius 7.5 cm, depth allowance 10% (16 cm)
    from hec_jax.geometry.track import Gate

    centre = np.array([-0.25, -0.03, 1.6])
    gate = Gate(centre, 0.075, 0.1)
    deeper = centre * (1.68 / 1.6)  # the same image point 8 cm deeper
    assert not gate.admits(deeper)  # the sphere rejects it
    assert gate.admits_along_sight(deeper)
    assert gate.admits_along_sight(centre * (1.6 + 0.075 + 0.159) / 1.6)
    assert not gate.admits_along_sight(centre * (1.6 + 0.075 + 0.161) / 1.6)  # too deep
    sideways = centre + np.array([0.076, 0.0, 0.0])
    assert not gate.admits(sideways) and not gate.admits_along_sight(sideways)
    # a lateral offset is measured at the gate's depth: 7 cm at 1.68 m is 6.67 cm at 1.6 m
    assert gate.admits_along_sight(deeper + np.array([0.07, 0.0, 0.0]))
    for bad in ([np.nan, 0.0, 1.6], [0.0, 0.0, -1.6], [0.0, 0.0, 0.0]):
        assert not gate.admits_along_sight(np.array(bad))
    assert not gate.admits(np.array([np.nan, 0.0, 1.6]))
    assert not Gate(centre, 0.075).admits_along_sight(deeper)  # no depth_gate: off


def test_gate_jump_bound():
    # analytic cases: the innovation sphere 30 cm wide around the prediction, the last valid fit
    # 2 cm from it, the jump bound 12 cm around that fit
    from hec_jax.geometry.track import Gate

    predicted = np.array([0.1, -0.2, 2.0])
    last_fit = predicted + np.array([0.0, 0.0, 0.02])
    gate = Gate(predicted, 0.3, 0.1, last_fit, 0.12)
    deeper = last_fit * (2.02 + 0.119) / 2.02  # along its line of sight, inside the bound
    too_deep = last_fit * (2.02 + 0.121) / 2.02
    assert gate.admits(deeper) and not gate.admits(too_deep)
    assert Gate(predicted, 0.3).admits(too_deep)  # the sphere alone admits it
    assert gate.admits_along_sight(deeper) and not gate.admits_along_sight(too_deep)
    assert Gate(predicted, 0.3, 0.1).admits_along_sight(too_deep)
    far = predicted + np.array([0.31, 0.0, 0.0])  # outside the sphere, inside no bound
    assert not Gate(predicted, 0.3, None, far, 1.0).admits(far)
    assert not gate.admits(np.array([np.nan, 0.0, 2.0]))


@pytest.mark.parametrize("depth_gate", [None, 0.1])
def test_a_filter_run_away_in_depth_gets_the_frame_s_own_fit(depth_gate):
    # independent truth: the simulator's cube centre at each frame's exposure. In these
    # real-time frames the filter had run 8 cm deep on the held cube's drifting fits, and its
    # gate rejected the tracked and stopped fits, which were accurate. Without depth_gate every
    # hypothesis failed (the logged outcome); with it the frame's own fit is taken along its
    # line of sight within 2 cm of the truth in the task plane (measured 0.5-13.8 mm; the
    # depth, which that plane sees at 0.15 of its error, is the weak direction), and the filter
    # restarts from it
    frames = _held_cube_frames("held_cube_runaway_frames.npz", depth_gate=depth_gate)
    for tracker, image, occluded, truth, world in frames:
        st = tracker.update(image, occluded)
        if depth_gate is None:
            assert not st.valid and st.fit_source == ""
            continue
        assert st.valid and st.fit_source == "along_sight"
        got = world(st.measured_position)
        assert np.linalg.norm(got - truth) < 0.02, (got, truth)
        np.testing.assert_allclose(st.position, st.measured_position)  # restarted there
        np.testing.assert_array_equal(st.velocity, np.zeros(3))
        np.testing.assert_array_equal(st.acceleration, np.zeros(3))


# slow: (0, 0.0), every turned start at both centres, as the frames were run
@pytest.mark.parametrize("keep, merge", [pytest.param(0, 0.0, marks=pytest.mark.slow), (4, 0.1)])
def test_the_held_cube_s_turned_recoveries_with_fewer_turned_starts(keep, merge):
    # real-time frames (sessions 24-25, 3 runs) where the tracked fit, the stop hypothesis and the
    # local search's predicted rotation failed and its turned starts recovered the held cube,
    # each 29-34 ms of eye on the quiet CPU. As run (every turned start at both centres
    # through every gate) and as the real-time eye runs since (4 kept after the coarse gates,
    # the turns at the predicted centre alone where the last fit is within 1 cm: 17-23 ms):
    # the logged fit again (measured within 0.2 mm), and the simulator's cube within 2 cm in
    # the task plane (the depth is the weak direction, seen there at ~0.15 of its error)
    frames = _held_cube_frames("held_cube_turned_frames.npz", local_keep=keep, local_merge=merge)
    logged = np.load(Path(__file__).parent / "data" / "held_cube_turned_frames.npz")
    centres = []
    for k, (tracker, image, occluded, truth, world) in enumerate(frames):
        first, rest = tracker._local
        tracker._local = (first, lambda *a, _f=rest: centres.append(a[1].shape[0]) or _f(*a))
        st = tracker.update(image, occluded)
        tracker._local = (first, rest)
        assert st.valid and st.fit_source == "local_turned"
        assert np.linalg.norm(st.measured_position - logged["logged_camera"][k]) < 1e-3
        assert np.linalg.norm(world(st.measured_position) - truth) < 0.02
    assert len(centres) == len(logged["images"])
    assert (min(centres) == 1) == (merge > 0) and max(centres) <= 2


def test_filter_init_on_the_host_equals_init():
    # the along-sight restart's NumPy init (no compilation on first use) against the JAX one
    import jax.numpy as jnp

    cfg = kf.FilterConfig(dt=1.0 / 30.0)
    p = np.array([-0.25, -0.03, 1.6])
    want = kf.init(cfg, jnp.asarray(p))  # float64 (conftest)
    got = kf.init_np(cfg, p)
    assert isinstance(got.mean, np.ndarray) and isinstance(got.cov, np.ndarray)
    np.testing.assert_array_equal(got.mean, np.asarray(want.mean))
    np.testing.assert_array_equal(got.cov, np.asarray(want.cov))


def test_edge_points_sample_only_near_the_image():
    # a horizontal intensity step (rows < 60: 50, rows >= 60: 200) and model edges along it:
    # one across the image, one a wrong fit's edge 6e5 px long (it overflowed OpenCV's remap,
    # sampling 3e5 points). The long edge gives the same points where both
    # sample, and none farther than the search outside the image
    from hec_jax.geometry.detect import edge_points

    gray = np.full((120, 160), 50, np.uint8)
    gray[60:] = 200
    short = np.array([[[0.0, 60.0], [160.0, 60.0]]])
    long = np.array([[[-3e5, 60.0], [3e5, 60.0]]])
    usable = np.array([True])
    p_short, _ = edge_points(gray, short, usable)
    p_long, _ = edge_points(gray, long, usable)
    assert len(p_short) > 50 and 0 < len(p_long) < 200
    assert np.all(np.abs(p_short[:, 1] - 60.0) < 0.6)  # on the step
    assert np.all((p_long[:, 0] > -5) & (p_long[:, 0] < 165))
    common = np.isin(p_long[:, 0], p_short[:, 0])
    assert common.sum() >= len(p_short) - 1
    by_x = dict(zip(p_short[:, 0], p_short[:, 1], strict=True))
    np.testing.assert_allclose(p_long[common, 1], [by_x[x] for x in p_long[common, 0]])


@pytest.mark.parametrize("shape", [(480, 640), (123, 157)])
def test_edge_points_smooth_only_their_window_with_the_whole_image_s_values(shape):
    """``edge_points`` without ``blurred`` smooths only the window its samples read
    (``detect.sample_window``): the same points, bit for bit, as with the whole image's
    ``edge_blur``, for edges inside, across the border and outside the image, linear and cubic
    interpolation, two blurs, and an image width that is not a multiple of the window's
    alignment.
    """
    import cv2

    from hec_jax.geometry.detect import edge_blur, edge_points

    rng = np.random.default_rng(7)
    h, w = shape
    gray = cv2.GaussianBlur(rng.integers(0, 256, shape, dtype=np.uint8), (0, 0), 2.0)
    cv2.rectangle(gray, (w // 5, h // 4), (3 * w // 5, 3 * h // 4), 230, -1)  # strong steps
    checked = 0
    for _ in range(40):
        centre = rng.uniform([-0.2 * w, -0.2 * h], [1.2 * w, 1.2 * h])
        ends = centre + rng.uniform(-0.6, 0.6, (12, 2, 2)) * [w, h]
        usable = rng.random(12) < 0.8
        for blur in (0.8, 1.3):
            for interp in (cv2.INTER_LINEAR, cv2.INTER_CUBIC):
                kw = dict(spacing=1.0, search=1.5, blur=blur, interpolation=interp)
                got = edge_points(gray, ends, usable, **kw)
                want = edge_points(gray, ends, usable, blurred=edge_blur(gray, blur), **kw)
                np.testing.assert_array_equal(got[0], want[0])
                np.testing.assert_array_equal(got[1], want[1])
                checked += len(got[0])
    assert checked > 1000  # the trials found edge points, inside the image and at its borders


@pytest.mark.parametrize("x64", [False, True])
def test_one_transfer_fetches_what_device_get_does(x64):
    """``track._OneTransfer``: one packed array unpacked on the host gives ``jax.device_get``'s
    leaves bit for bit (float32 and float64, with bool and int leaves, 0-d and 3-d), of the same
    dtypes, shapes and tree: a finish's :class:`Finished` and a search's nested ``Located``
    (pose, association); ``_cache_size`` counts its compiled signatures.
    """
    import jax
    import jax.numpy as jnp

    from hec_jax.geometry.box_model import Pose
    from hec_jax.geometry.track import (
        Association,
        Finished,
        Located,
        TrackConfig,
        _jit,
        _OneTransfer,
    )

    def located(x, n):  # the search's result: nested tuples, int32 ids (-1 unassigned), bools
        association = Association(
            x[: 2 * n * 2].reshape(n, 2, 2),
            jnp.arange(n, dtype=jnp.int32) - 1,
            jnp.abs(x[:n]),
            jnp.tanh(x[0]),
            jnp.sum(x[:3] > 0).astype(jnp.int32),
            jnp.int32(0),
        )
        pose = Pose(x[:9].reshape(3, 3), x[9:12] + 1.0)
        return Located(pose, association, jnp.sum(x**2), x[0] > x[1], jnp.outer(x[:3], x[:3]), True)

    def fn(x, n):
        return Finished(
            x[:9].reshape(3, 3) * 1.5,
            jnp.sin(x[:3]),
            jnp.sum(x),
            jnp.sum(x) > 0,
            jnp.outer(x[:6], x[:6]),
            kf.FilterState(x[:9] / 3.0, jnp.outer(x[:9], x[:9])),
            kf.FilterState(x[:9] ** 2, jnp.eye(9) * x[0]),
            x[: 2 * n * 2].reshape(n, 2, 2),
            jnp.arange(n, dtype=jnp.int32) - 1,
            jnp.cos(x[:n]),
            jnp.float32(0.25) * x[1],
        )

    with jax.enable_x64(x64):
        dtype = np.float64 if x64 else np.float32
        x = np.random.default_rng(3).normal(size=40).astype(dtype)
        cfg = TrackConfig()
        for make in (fn, located):
            one = _OneTransfer(lambda x, make=make: make(x, len(x) // 5), cfg)
            jitted = _jit(lambda x, make=make: make(x, len(x) // 5), cfg)
            # the layout recorded while tracing the first call is reused after; another
            # signature (x[:-1]: 7 segments instead of 8) is traced again and unpacked by its own
            # layout
            for arg, signatures in ((x, 1), (x, 1), (x[:-1], 2), (x, 2)):
                got, want = one(arg), jax.device_get(jitted(arg))
                assert jax.tree.structure(got) == jax.tree.structure(want)
                for g, v in zip(jax.tree.leaves(got), jax.tree.leaves(want), strict=True):
                    assert isinstance(g, np.ndarray) and g.dtype == v.dtype and g.shape == v.shape
                    np.testing.assert_array_equal(g, v)
                assert one._cache_size() == signatures


def test_configs_differing_only_on_the_host_share_their_compiled_functions():
    """Every TrackConfig field read inside the jitted functions (or by the functions they call in
    ``track.py``) is in ``_TRACED``, so normalising the others cannot change a compiled program;
    configs that differ only in host-read fields get the same compiled functions."""
    import ast
    import inspect

    from hec_jax.geometry import track

    tree = ast.parse(inspect.getsource(track))  # the reachable set: module-level functions
    functions = {n.name: n for n in tree.body if isinstance(n, ast.FunctionDef)}
    roots = ["_make_locate", "_make_finish", "_make_search", "_make_local_search"]
    reached, stack = set(), list(roots)
    while stack:
        name = stack.pop()
        if name in reached:
            continue
        reached.add(name)
        for node in ast.walk(functions[name]):
            if isinstance(node, ast.Name) and node.id in functions:
                stack.append(node.id)
    read = {
        node.attr
        for name in reached
        for node in ast.walk(functions[name])
        if isinstance(node, ast.Attribute)
        and isinstance(node.value, ast.Name)
        and node.value.id in ("cfg", "config")
    }
    assert {"locate", "associate", "refine_points"} <= reached
    assert read and read <= track._TRACED, sorted(read - track._TRACED)
    assert set(track._TRACED) <= {f.name for f in dataclasses.fields(TrackConfig)}
    base = TrackConfig()
    host = dataclasses.replace(base, defer_search=3, max_segments=17, min_iou_acquire=0.5)
    traced = dataclasses.replace(base, huber_px=base.huber_px + 1.0)
    assert track._compiled(host, FPS) is track._compiled(base, FPS)
    assert track._compiled(traced, FPS) is not track._compiled(base, FPS)
    # the filter's noise is read through its config, so it stays in the key
    jerk = dataclasses.replace(base, jerk_psd=2.0 * base.jerk_psd)
    assert track._compiled(jerk, FPS)[3] != track._compiled(base, FPS)[3]


@pytest.mark.slow  # an ablation's compiler options (off by default); the default suite's time
def test_cpu_small_kernels_reach_the_compiler_and_change_only_round_off(seq):
    """``cpu_small_kernels`` compiles the fit without YNNPACK fusions (XLA's default fit has
    them) and changes only round-off: from a prior 3 mm and 2 deg off the true pose of a rendered
    frame, the fit is the same pose to 1e-9 either way, and within 2 mm of the truth."""
    import jax

    from hec_jax.geometry import detect, track
    from hec_jax.geometry.box_model import Pose, project_corners_np

    if jax.default_backend() != "cpu":
        pytest.skip("CPU compiler options")
    i = 5
    turn = rotation_from_axis_angle(np.array([0.3, -1.0, 0.5]), np.deg2rad(2.0))
    prior = (turn @ seq.rotation[i], seq.position[i] + np.array([0.003, 0.0, 0.0]))
    gray = detect.to_gray(seq.frames[i])
    corners = project_corners_np(*prior, EDGE, seq.intrinsics)
    segments, mask = detect.pad_segments(
        detect.detect_segments(gray, track._window(corners, 0.6)), 48
    )
    args = (Pose(*prior), segments, mask, np.float64(EDGE), seq.intrinsics, None, None)
    fits, has_ynn = {}, {}
    for small in (False, True):
        compiled = track._compiled(TrackConfig(cpu_small_kernels=small), FPS)[0]
        compiled = compiled.lower(*args).compile()
        has_ynn[small] = "ynn" in compiled.as_text()
        fits[small] = jax.device_get(compiled(*args))
    assert has_ynn == {False: True, True: False}
    a, b = fits[False], fits[True]
    assert bool(a.valid) and bool(b.valid)
    assert np.linalg.norm(a.pose.translation - seq.position[i]) < 2e-3
    np.testing.assert_allclose(b.pose.translation, a.pose.translation, rtol=0, atol=1e-9)
    np.testing.assert_allclose(b.pose.rotation, a.pose.rotation, rtol=0, atol=1e-9)


def test_a_fit_is_never_a_measurement_that_leaves_the_filter_non_finite():
    """``finish`` (the jitted fit and filter update) flags a fit invalid where the filter update
    would not be finite, and keeps the prediction: a filter already run away (an infinite
    position variance, as the infinite covariance of a fit whose centre float32 left unobserved
    gave on a rendered sequence) takes no measurement, but a first fit restarts it. The same fit
    into a finite filter is valid, within 1 mm of the truth."""
    from hec_jax.geometry import track
    from hec_jax.geometry.box_model import EDGES, Pose, project_corners_np

    k = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
    rot, t, size = np.eye(3), np.array([0.02, -0.01, 1.5]), np.float64(EDGE)
    cfg = TrackConfig()
    locate, finish, _, fcfg, _ = track._compiled(cfg, FPS)
    edges = project_corners_np(rot, t, size, k)[EDGES]
    segments = np.zeros((cfg.max_segments, 2, 2))
    mask = np.zeros(cfg.max_segments, bool)
    segments[:12], mask[:12] = edges, True
    visible = np.flatnonzero(np.linalg.norm(edges[:, 1] - edges[:, 0], axis=-1) > 20)
    along = np.linspace(0.1, 0.9, 30)[:, None]
    points = np.zeros((cfg.max_points, 2))
    ids = np.zeros(cfg.max_points, np.int32)
    weights = np.zeros(cfg.max_points)
    for j, e in enumerate(visible):
        rows = slice(30 * j, 30 * (j + 1))
        points[rows] = edges[e, 0] + along * (edges[e, 1] - edges[e, 0])
        ids[rows], weights[rows] = e, 1.0
    loc = locate(Pose(rot, t + np.array([0.002, 0.0, 0.0])), segments, mask, size, k, None, None)
    state = kf.init_np(fcfg, t)
    run_away = kf.FilterState(state.mean, np.where(np.eye(9, dtype=bool), np.inf, state.cov))
    for filt, first, want in (
        (state, False, True),
        (run_away, False, False),
        (run_away, True, True),
    ):
        out = finish(filt, loc, points, ids, weights, size, k, first, rot, 0.0, False)
        assert bool(out.valid) is want
        finite = np.all(np.isfinite(out.filter_state.mean)) & np.all(
            np.isfinite(out.filter_state.cov)
        )
        assert finite or not want
    assert np.linalg.norm(np.asarray(out.translation) - t) < 1e-3
