"""The eye on randomized rendered scenes (issue 24): scene drawing, a short rendered sequence, the
smoother's segments (no extrapolation), the cube-symmetric rotation error and the OpenCV
baseline. The full benchmark is ``benchmarks/eye_randomized.py``. The tracker's issue-24 checks
and the smoother's ``max_gap_s`` are off by default (the hand-eye loop's tracker): these tests
turn them on, as the benchmark does."""

import dataclasses
import functools
import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest

from hec_jax.geometry import accuracy
from hec_jax.geometry.baselines import match_quad, paper_two_frame_track, pnp_face_track
from hec_jax.geometry.smooth import NO_EXTRAPOLATION, SmootherConfig, smooth_track
from hec_jax.geometry.synthetic import random_rotation, rotation_from_axis_angle
from hec_jax.geometry.track import (
    RANDOMIZED_BENCHMARK,
    RANDOMIZED_PHOTOMETRIC,
    UNSEEN_SCENES,
    _iou,
    cube_symmetries,
    track_box,
)
from hec_jax.mjx_scene.randomized import RandomSceneRanges, draw_scene, render_random_sequence

FPS = 30.0
DEV_SEED = 0  # a development seed (the held-out range starts at 1_000_000)
NO_GAPS = 0.2  # SmootherConfig.max_gap_s of the benchmark [s]


def test_draw_scene_is_seeded_and_in_range():
    r = RandomSceneRanges()
    # the ranges (issue 24, point 1), not the class's own values only
    assert r.elevation_deg == (-10.0, 60.0) and r.azimuth_deg == 70.0
    assert r.distance_m == (0.6, 2.5) and r.edge_m == (0.05, 0.15)
    scenes = [draw_scene(s) for s in range(400)]
    # and the draws cover them: each range's outer tenths are reached on both sides
    for field, (lo, hi) in (
        ("elevation_deg", r.elevation_deg),
        ("azimuth_deg", (-r.azimuth_deg, r.azimuth_deg)),
        ("distance_m", r.distance_m),
        ("edge_m", r.edge_m),
    ):
        x = np.array([getattr(sc, field) for sc in scenes])
        assert x.min() < lo + 0.1 * (hi - lo) and x.max() > hi - 0.1 * (hi - lo), field
    scenes = scenes[:40]
    assert draw_scene(7) == draw_scene(7) and draw_scene(7) != draw_scene(8)
    for sc in scenes:
        assert r.elevation_deg[0] <= sc.elevation_deg <= r.elevation_deg[1]
        assert abs(sc.azimuth_deg) <= r.azimuth_deg
        assert r.distance_m[0] <= sc.distance_m <= r.distance_m[1]
        assert r.edge_m[0] <= sc.edge_m <= r.edge_m[1]
    assert {sc.look for sc in scenes} == {"plain", "wood", "low_contrast"}
    assert any(sc.shadows for sc in scenes) and any(sc.exposure_s > 0 for sc in scenes)


def test_max_swing_speed_bounds_the_simulated_cube():
    """``max_swing_speed_m_s`` against MuJoCo C: the scene at the ranges' longest rod, largest
    cube and largest release (release forced past draw_scene's in-view cap), 2 s at the scene's
    own 1 ms step, its cube centre's fastest speed (finite differences) is under the bound and
    within 2% of it (the bound's grid maximum is at that corner); the point-mass bound
    sqrt(2 g L (1 - cos theta)) is not one (the rod's mass nearer the hinge speeds the cube)."""
    import mujoco

    from hec_jax.mjx_scene.randomized import max_swing_speed_m_s, scene_mjcf

    r = RandomSceneRanges()
    widest = RandomSceneRanges(edge_m=(r.edge_m[1],) * 2, rod_m=(r.rod_m[1],) * 2)
    scene = draw_scene(3, widest)
    m = mujoco.MjModel.from_xml_string(*scene_mjcf(scene, 64, 48))
    d = mujoco.MjData(m)
    d.qpos[0] = r.release_rad[1]
    cube = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "cube")
    mujoco.mj_forward(m, d)
    centres = [d.xpos[cube].copy()]
    for _ in range(int(2.0 / m.opt.timestep)):
        mujoco.mj_step(m, d)
        mujoco.mj_forward(m, d)
        centres.append(d.xpos[cube].copy())
    speed = np.linalg.norm(np.diff(centres, axis=0), axis=-1).max() / m.opt.timestep
    bound = max_swing_speed_m_s(r)
    assert 0.98 * bound < speed <= bound, (speed, bound)
    arm = r.rod_m[1] + r.edge_m[1] / 2
    assert speed > np.sqrt(2 * 9.81 * arm * (1 - np.cos(r.release_rad[1])))
    assert max_swing_speed_m_s(RandomSceneRanges(release_rad=(0.1, 0.3))) < bound


def test_world_from_camera_is_the_rendering_camera_s_pose():
    """``world_from_camera`` (the scenes' calibrated extrinsics) against MuJoCo's own camera after
    ``mj_forward``: the cube at rest (``swing_bottom``, world) has the camera coordinates that
    ``body_in_camera`` gives, it is ``distance_m`` from the camera (the orbit) and projects into
    the image, and the camera has no roll (gravity has no image-x component). Before session 90
    it returned a zero pose (``mj_kinematics`` does not place cameras)."""
    import mujoco

    from hec_jax.mjx_scene.camera import camera_intrinsics
    from hec_jax.mjx_scene.randomized import scene_mjcf, swing_bottom, world_from_camera
    from hec_jax.mjx_scene.render import body_in_camera

    for seed in (DEV_SEED, 3, 11):
        scene = draw_scene(seed)
        r_wc, p_wc = world_from_camera(scene)
        np.testing.assert_allclose(r_wc.T @ r_wc, np.eye(3), atol=1e-9)
        m = mujoco.MjModel.from_xml_string(*scene_mjcf(scene, 640, 480))
        d = mujoco.MjData(m)  # qpos 0: the pendulum hangs at rest
        mujoco.mj_forward(m, d)
        at_rest, _ = body_in_camera(m, d, "cube", "eye")
        mine = r_wc.T @ (swing_bottom(scene) - p_wc)
        np.testing.assert_allclose(mine, at_rest, atol=1e-6)
        # the MJCF holds the camera's position to 6 significant digits (scene_mjcf): ~1e-5 m
        assert abs(np.linalg.norm(mine) - scene.distance_m) < 1e-5
        uvw = camera_intrinsics(m, "eye", 640, 480) @ mine
        assert 0 < uvw[0] / uvw[2] < 640 and 0 < uvw[1] / uvw[2] < 480
        gravity_cam = r_wc.T @ np.array([0.0, 0.0, -1.0])
        assert abs(gravity_cam[0]) < 1e-9 and gravity_cam[1] > 0  # no roll; down is image +y


@pytest.fixture(scope="module")
def rendered():
    scene = draw_scene(DEV_SEED)
    seq, background = render_random_sequence(scene, 12, FPS, 640, 480)
    return scene, seq, background


def test_rendered_truth_and_visibility(rendered):
    scene, seq, background = rendered
    assert seq.frames.shape == (12, 480, 640, 3) and background.shape == (480, 640, 3)
    vis = accuracy.fully_visible(seq.position, seq.rotation, scene.edge_m, seq.intrinsics, 640, 480)
    assert vis.all()
    # the box differs from the empty scene where it is projected
    centre = seq.intrinsics @ (seq.position[0] / seq.position[0, 2])
    u, v = int(centre[0]), int(centre[1])
    diff = np.abs(seq.frames[0, v, u].astype(int) - background[v, u].astype(int)).max()
    assert diff > 10


def test_a_motion_blurred_frame_s_truth_is_its_mid_exposure_state():
    """A blurred scene (seed 4: 6.2 ms exposures, three renders each): each frame's true state is
    the pendulum's at the middle render, stepped here independently with MuJoCo; the state at
    the exposure's end is millimetres away once the cube moves."""
    import mujoco

    from hec_jax.mjx_scene.randomized import scene_mjcf
    from hec_jax.mjx_scene.render import body_in_camera

    scene = draw_scene(4)
    assert scene.exposure_s > 0.006
    n = 8
    seq, _ = render_random_sequence(scene, n, FPS, 320, 240)
    m = mujoco.MjModel.from_xml_string(*scene_mjcf(scene, 320, 240))
    steps = int(round(1.0 / (FPS * m.opt.timestep)))
    m.opt.timestep = 1.0 / (FPS * steps)
    blur = int(round(scene.exposure_s / m.opt.timestep))
    d = mujoco.MjData(m)
    d.qpos[0] = scene.release_rad
    mujoco.mj_forward(m, d)
    states = [body_in_camera(m, d, "cube", "eye")]
    for _ in range(n * steps + 1):
        mujoco.mj_step(m, d)
        mujoco.mj_forward(m, d)
        states.append(body_in_camera(m, d, "cube", "eye"))
    end_offsets = []
    for i in range(n):
        end = 1 + i * steps  # the frame's time, its exposure's end
        mid = end - (int(round(blur / 2)) if i > 0 else 0)  # frame 0 is one render
        np.testing.assert_allclose(seq.position[i], states[mid][0], atol=1e-12)
        np.testing.assert_allclose(seq.rotation[i], states[mid][1], atol=1e-12)
        assert seq.times[i] == pytest.approx(mid * m.opt.timestep)
        end_offsets.append(np.linalg.norm(states[end][0] - states[mid][0]))
    assert max(end_offsets) > 1e-3, end_offsets  # [m]


# slow (68 s of the CI's time, nearly all of it compiling; 2.5 s warm): UNSEEN_SCENES (its own
# search, unbatched) and the benchmark's preset end to end; their checks run in the default suite
# in the hand-eye loop's lab tracker (tests/test_hand_eye.py's camera loop), and the preset's
# search, threads and options on this scene in the tests below
@pytest.mark.slow
@pytest.mark.parametrize("tracker", ["unseen_scenes", "randomized_benchmark"])
def test_tracker_acquires_and_tracks_a_new_scene(rendered, tracker):
    """Acquired on the first frame from an oblique view (three faces visible), within the
    issue's accuracy, no valid frame more than 5 cm off: the issue-24 checks, and with them the
    benchmark's search options."""
    scene, seq, background = rendered
    smoother = NO_EXTRAPOLATION  # the benchmark's: max_gap_s 0.2
    cfg = {"unseen_scenes": UNSEEN_SCENES, "randomized_benchmark": RANDOMIZED_BENCHMARK}[tracker]
    photometric = RANDOMIZED_PHOTOMETRIC if tracker == "randomized_benchmark" else None
    tr = track_box(
        seq.frames,
        seq.intrinsics,
        scene.edge_m,
        FPS,
        cfg,
        smoother,
        background,
        photometric=photometric,
    )
    assert tr.valid[0] and tr.valid.mean() >= 0.9
    assert tr.restarted[0] and not (tr.restarted & ~tr.valid).any()  # a restart is a valid fit
    assert not (tr.search_skipped & tr.valid).any()  # a skipped search gives no fit
    err = np.linalg.norm(tr.position - seq.position, axis=-1)[tr.valid]
    assert err.max() < accuracy.GROSS_M
    dist = np.linalg.norm(seq.position, axis=-1)[tr.valid]
    assert np.median(err / dist) < 3e-3
    rot = accuracy.symmetric_rotation_error_deg(tr.pose_rotation, seq.rotation)[tr.valid]
    assert np.median(rot) < 1.0
    # the per-frame record: frame 0 found by the search, the tracked fits after it, and the
    # frame times whose mean is the reported time
    assert tr.fit_source[0] == "search" and np.all((tr.fit_source != "") == tr.valid)
    np.testing.assert_allclose(tr.frame_ms.mean(), tr.timing_ms["total_ms"], rtol=1e-9)
    kinds = accuracy.frame_kinds(tr.valid, tr.fit_source, tr.initialised, tr.search_skipped)
    assert kinds[0] == "found by search"
    assert np.all(kinds[tr.fit_source == "tracked"] == "tracked")
    by_kind = accuracy.time_by_kind(kinds, tr.frame_ms)
    assert sum(m["frames"] for m in by_kind.values()) == len(seq.frames)
    assert np.isclose(sum(m["share"] for m in by_kind.values()), 1.0)


def test_frame_kinds_and_time_by_kind():
    """Each frame's kind from the tracker's flags (valid, fit source, filter running, search
    skipped), and the time per kind, against hand-made frames."""
    valid = np.array([0, 0, 1, 1, 0, 0, 0, 1, 0], bool)
    source = np.array(["", "", "search", "tracked", "", "", "", "local", ""])
    initialised = np.array([0, 0, 1, 1, 1, 0, 0, 1, 1], bool)
    skipped = np.array([0, 0, 0, 0, 0, 0, 1, 0, 0], bool)
    kinds = accuracy.frame_kinds(valid, source, initialised, skipped)
    want = ["failed with no track"] * 2 + ["found by search", "tracked", "failed while tracking"]
    want += ["failed with no track", "search skipped", "tracked", "failed while tracking"]
    assert kinds.tolist() == want
    ms = np.array([1.0, 3.0, 60.0, 10.0, 80.0, 2.0, 0.5, 12.0, 40.0])
    by_kind = accuracy.time_by_kind(kinds, ms)
    assert list(by_kind) == list(accuracy.FRAME_KINDS)  # every kind, in table order
    assert by_kind["tracked"] == {"frames": 2, "mean_ms": 11.0, "share": 22.0 / 208.5}
    assert by_kind["failed while tracking"]["mean_ms"] == 60.0
    assert by_kind["failed with no track"]["frames"] == 3
    assert by_kind["search skipped"]["share"] == 0.5 / 208.5
    with pytest.raises(ValueError, match="no fit_source"):
        accuracy.frame_kinds(valid, np.where(valid, "", source), initialised, skipped)
    with pytest.raises(ValueError, match="one length"):
        accuracy.frame_kinds(valid[:-1], source, initialised, skipped)
    with pytest.raises(ValueError, match="unknown frame kinds"):
        accuracy.time_by_kind(np.array(["tracked", "lost"]), np.ones(2))
    with pytest.raises(ValueError, match="finite"):
        accuracy.time_by_kind(kinds, np.where(valid, np.nan, ms))
    with pytest.raises(ValueError, match="alike"):
        accuracy.time_by_kind(kinds, ms[:-1])


def test_wilson_interval_against_hand_worked_values():
    """The 95% Wilson score interval against values worked by hand from its formula (Wilson
    1927; e.g. 0 of 10: (0, 0.2775), 5 of 10: (0.2366, 0.7634), 9 of 10: (0.5958, 0.9821)),
    and the degenerate and bad inputs."""
    want = {(0, 10): (0.0, 0.2775), (5, 10): (0.2366, 0.7634), (9, 10): (0.5958, 0.9821)}
    for (k, n), (lo, hi) in want.items():
        np.testing.assert_allclose(accuracy.wilson_interval(k, n), (lo, hi), atol=5e-5)
    assert accuracy.wilson_interval(0, 0) == (0.0, 1.0)
    lo, hi = accuracy.wilson_interval(183, 200)  # shrinks about sqrt(n)
    assert lo < 183 / 200 < hi and hi - lo < 0.09
    for bad in [(3, 2), (-1, 2)]:
        with pytest.raises(ValueError, match="successes"):
            accuracy.wilson_interval(*bad)


def test_bootstrap_intervals_against_known_cases():
    """:func:`accuracy.bootstrap_intervals` over sequences: identical sequences give a point
    interval at their pooled value; a binomial acquisition over 400 made-up sequences gives
    about the Wilson interval (both estimate the same 95% interval of a rate); pooled velocity
    RMS and gross counts bracket the full-set values; same seed, same intervals; bad input
    refused."""

    def seq(delay, valid=40, gross=0, sq=0.1, frames=40, visible=45):
        result = {
            "acquire_delay": delay,
            "valid_visible": valid,
            "gross": gross,
            "vel_sq_sum": sq,
            "vel_frames": frames,
        }
        return {"visible_frames": visible, "tracker": result}

    same = accuracy.bootstrap_intervals([seq(0, gross=2)] * 30, draws=200)
    assert same["acquired_within_3_rate"] == (1.0, 1.0)
    np.testing.assert_allclose(same["valid_rate"], (40 / 45, 40 / 45), rtol=1e-12)
    np.testing.assert_allclose(same["velocity_rms_m_s"], (0.05, 0.05), rtol=1e-12)
    assert same["gross_errors"] == (60.0, 60.0)

    rng = np.random.default_rng(7)
    hits = rng.random(400) < 0.9
    summaries = [
        seq(0 if h else 10**6, gross=int(rng.integers(0, 3)) * (i % 7 == 0), sq=float(rng.random()))
        for i, h in enumerate(hits)
    ]
    summaries.append(seq(None, valid=0, visible=0, frames=0, sq=0.0))  # never fully visible
    iv = accuracy.bootstrap_intervals(summaries, draws=4000, seed=3)
    wilson = accuracy.wilson_interval(int(hits.sum()), hits.size)
    np.testing.assert_allclose(iv["acquired_within_3_rate"], wilson, atol=0.01)
    rms = np.sqrt(sum(s["tracker"]["vel_sq_sum"] for s in summaries) / (40 * 400))
    gross = sum(s["tracker"]["gross"] for s in summaries)
    assert iv["velocity_rms_m_s"][0] < rms < iv["velocity_rms_m_s"][1]
    assert iv["gross_errors"][0] < gross < iv["gross_errors"][1]
    assert accuracy.bootstrap_intervals(summaries, draws=4000, seed=3) == iv
    assert accuracy.bootstrap_intervals(summaries, draws=4000, seed=4) != iv

    with pytest.raises(ValueError, match="no sequence"):
        accuracy.bootstrap_intervals([])
    with pytest.raises(ValueError, match="draws"):
        accuracy.bootstrap_intervals(summaries, draws=10)
    with pytest.raises(ValueError, match="lacks"):
        accuracy.bootstrap_intervals([{"visible_frames": 45, "tracker": {"gross": 0}}])


def test_strata_count_each_look_and_elevation_band():
    """:func:`accuracy.strata` against counts made by hand on made-up sequence summaries: a
    never-acquired sequence (a large delay) counts as not acquired, a never fully visible one
    (None) is left out of the acquisition's denominator but not of the frames."""

    def seq(look, elevation, delay, valid, gross=0, visible=45):
        result = {"acquire_delay": delay, "valid_visible": valid, "gross": gross}
        return {"look": look, "elevation_deg": elevation, "visible_frames": visible, "t": result}

    summaries = [
        seq("plain", 5.0, 0, 45),
        seq("plain", 40.0, 4, 30, gross=2),
        seq("wood", -3.0, 10**6, 0),
        seq("wood", 9.99, 1, 40),
        seq("wood", 10.0, None, 0, visible=0),
    ]
    rows = accuracy.strata(summaries, method="t", bands=(-90, 10, 90))
    got = [(r["look"], r["elevation_deg"], r["sequences"], r["acquired"]) for r in rows]
    assert got == [
        ("plain", (-90.0, 10.0), 1, 1),
        ("plain", (10.0, 90.0), 1, 0),
        ("wood", (-90.0, 10.0), 2, 1),
        ("wood", (10.0, 90.0), 1, 0),
        ("plain", (-90.0, 90.0), 2, 1),
        ("wood", (-90.0, 90.0), 3, 1),
        ("all", (-90.0, 90.0), 5, 2),
    ]
    wood_low, wood_high, everything = rows[2], rows[3], rows[-1]
    assert wood_low["acquired_rate"] == 0.5 and wood_low["valid_rate"] == 40 / 90
    assert np.isnan(wood_high["acquired_rate"]) and wood_high["acquired_interval"] == (0.0, 1.0)
    assert everything["acquired_rate"] == 2 / 4 and everything["gross_errors"] == 2
    assert everything["valid_rate"] == (45 + 30 + 40) / (4 * 45)
    assert everything["acquired_interval"] == accuracy.wilson_interval(2, 4)
    assert everything["velocity_rms_m_s"] is None and everything["velocity_sq_share"] is None
    with pytest.raises(ValueError, match="increasing"):
        accuracy.strata(summaries, method="t", bands=(10, -90))
    with pytest.raises(ValueError, match="lacks"):
        accuracy.strata(summaries, method="tracker")
    # with every summary's velocity sums: the strata's pooled RMS and share of the squares
    sums = [(0.5, 40), (2.0, 30), (0.0, 0), (1.5, 40), (0.0, 0)]
    for summary, (sq, frames) in zip(summaries, sums, strict=True):
        summary["t"] |= {"vel_sq_sum": sq, "vel_frames": frames}
    rows = accuracy.strata(summaries, method="t", bands=(-90, 10, 90))
    wood_low, wood_high, everything = rows[2], rows[3], rows[-1]
    assert wood_low["velocity_rms_m_s"] == pytest.approx(np.sqrt(1.5 / 40))
    assert wood_low["velocity_sq_share"] == pytest.approx(1.5 / 4.0)
    assert np.isnan(wood_high["velocity_rms_m_s"]) and wood_high["velocity_sq_share"] == 0
    assert everything["velocity_rms_m_s"] == pytest.approx(np.sqrt(4.0 / 110))
    assert everything["velocity_sq_share"] == 1.0


def test_velocity_sums_split_the_pooled_velocity_rms():
    """:func:`accuracy.velocity_sums` of each sequence adds up to :func:`accuracy.target_table`'s
    velocity RMS: valid frames only, frames without a velocity (NaN) left out."""
    rng = np.random.default_rng(7)
    per = []
    for n in (12, 30, 5):
        truth = SimpleNamespace(
            position=rng.normal(size=(n, 3)) + [0, 0, 2],
            rotation=np.broadcast_to(np.eye(3), (n, 3, 3)),
            velocity=rng.normal(size=(n, 3)),
        )
        velocity = truth.velocity + rng.normal(0, 0.1, (n, 3))
        velocity[1] = np.nan  # no velocity on one frame
        valid = rng.uniform(size=n) < 0.7
        per.append(
            accuracy.sequence_errors(
                truth.position, truth.rotation, velocity, valid, truth, np.ones(n, bool), 1.0
            )
        )
    sums = [accuracy.velocity_sums(e) for e in per]
    pooled = np.sqrt(sum(s for s, _ in sums) / sum(k for _, k in sums))
    assert pooled == pytest.approx(accuracy.target_table(per)["velocity_rms_m_s"], rel=1e-12)
    assert sum(k for _, k in sums) == sum(np.isfinite(e["velocity_err_m_s"]).sum() for e in per)


@functools.cache
def _rendered_six(seed: int):
    """(scene, 6 rendered frames, background) of a development seed (made once per module)."""
    scene = draw_scene(seed)
    return (scene, *render_random_sequence(scene, 6, FPS, 640, 480))


def test_host_threads_give_the_one_thread_outputs_bit_for_bit():
    """Development seed 130 (wood, shadows): frame 0's search from scratch tries three blobs,
    which ``threads=2`` (``RANDOMIZED_BENCHMARK``'s) searches side by side, as it finds the
    blob masks; frames 1-5 are tracked, the gray segments beside the foreground mask. Every
    output of every frame equals the one-thread tracker's exactly."""
    from hec_jax.geometry import BoxTracker

    scene, seq, background = _rendered_six(130)
    assert RANDOMIZED_BENCHMARK.threads == 2
    steps, mapped = {}, []
    for threads in (1, 2):
        cfg = dataclasses.replace(RANDOMIZED_BENCHMARK, threads=threads)
        tracker = BoxTracker(seq.intrinsics, scene.edge_m, FPS, cfg, background)
        spread = tracker._map

        def spy(fn, items, _f=spread, _threads=threads):
            mapped.append((_threads, len(items)))
            return _f(fn, items)

        tracker._map = spy
        steps[threads] = [tracker.update(f) for f in seq.frames]
        assert (tracker._pool is not None) == (threads == 2)
    assert (2, 3) in mapped  # three candidates on the threads
    assert [s.fit_source for s in steps[2]] == ["search"] + ["tracked"] * 5
    for one, two in zip(steps[1], steps[2], strict=True):
        for name in one._fields:
            if name != "timing_ms":  # NaN equal to NaN
                np.testing.assert_array_equal(getattr(one, name), getattr(two, name), name)
    # in the items' order, the first on the calling thread, whatever finishes first
    names = spread(
        lambda x: (time.sleep(0.02 * (3 - x)), threading.current_thread().name), [0, 1, 2]
    )
    assert [n[1] for n in names][0] == threading.current_thread().name
    assert all(n[1].startswith("box-tracker") for n in names[1:])
    assert spread(lambda x: (time.sleep(0.02 * (3 - x)), x)[1], [0, 1, 2]) == [0, 1, 2]
    with pytest.raises(ValueError, match="threads"):
        BoxTracker(seq.intrinsics, scene.edge_m, FPS, dataclasses.replace(cfg, threads=0))


def test_one_frame_s_windows_share_their_difference_and_change_nothing():
    """The tracker's detection window, checks and outline points of a frame take their colour
    difference from one ``detect.FrameDifferences`` (the checks' windows computed from none):
    on development seed 131 (search from scratch on frame 0, then tracked) every output equals
    a tracker's that computes each window anew, with the frames passed in one reused array (a
    frame's kept differences are not the next frame's)."""
    from hec_jax.geometry import BoxTracker, detect

    scene, seq, background = _rendered_six(131)
    steps, served = {}, []
    for reuse in (False, True):
        tracker = BoxTracker(seq.intrinsics, scene.edge_m, FPS, RANDOMIZED_BENCHMARK, background)
        kept = tracker._frame_differences

        def fresh(image, bg):  # a new FrameDifferences for every window: nothing reused
            return None if bg is None else detect.FrameDifferences(image, bg)

        def counted(image, bg, _kept=kept):
            got = _kept(image, bg)
            served.append(sum(len(b) for _, b in got._planes.values()))
            return got

        tracker._frame_differences = counted if reuse else fresh
        buffer = np.empty_like(seq.frames[0])
        steps[reuse] = []
        for frame in seq.frames:
            buffer[...] = frame
            steps[reuse].append(tracker.update(buffer))
    assert sum(s.valid for s in steps[True]) >= 5
    assert sum(n > 0 for n in served) > len(seq.frames)  # windows found kept
    for one, two in zip(steps[False], steps[True], strict=True):
        for name in one._fields:
            if name != "timing_ms":
                np.testing.assert_array_equal(getattr(one, name), getattr(two, name), name)


@pytest.mark.parametrize("seed", [130, 139])
def test_faint_candidates_find_a_box_the_usual_blobs_cut_into_faces(seed):
    """Development seeds 130 (wood, shadows) and 139 (low contrast): at frame 5 the usual blobs
    of the difference to the background are single faces of the cube, the faint foreground's
    blob the whole cube. A fresh tracker's search from scratch on that frame finds the cube
    (within 1 cm of the rendered truth) only when it also tries the faint blob
    (``faint_candidates``, on in ``RANDOMIZED_BENCHMARK``), or, without it, in the last round
    of ``faint_unshadowed`` (also on there: the faint blobs without the shadow test, tried when
    no other candidate passes). Without the grain families (``texture_families`` None: with
    them, session 87's preset, the last round no longer finds seed 130's cube on this frame)."""
    import dataclasses

    from hec_jax.geometry import BoxTracker, detect

    scene, seq, background = _rendered_six(seed)
    frame, truth = seq.frames[5], seq.position[5]
    usual = detect.foreground_regions(frame, background, core=RANDOMIZED_BENCHMARK.blob_core)
    faint = detect.faint_foreground_regions(frame, background, core=RANDOMIZED_BENCHMARK.blob_core)
    corners = seq.intrinsics @ (truth / truth[2])
    assert faint and usual
    # the faint blob contains the cube's centre and is larger than any usual blob
    (x0, y0, x1, y1), area = faint[0]
    assert x0 <= corners[0] <= x1 and y0 <= corners[1] <= y1
    assert area > max(a for _, a in usual)
    assert RANDOMIZED_BENCHMARK.faint_candidates
    assert RANDOMIZED_BENCHMARK.faint_unshadowed
    for faint_on, last_round in ((True, False), (False, False), (False, True)):
        cfg = dataclasses.replace(
            RANDOMIZED_BENCHMARK,
            faint_candidates=faint_on,
            faint_unshadowed=last_round,
            texture_families=None,
        )
        tracker = BoxTracker(seq.intrinsics, scene.edge_m, FPS, cfg, background)
        st = tracker.update(frame)
        found = bool(st.valid) and np.linalg.norm(st.measured_position - truth) < 0.01
        assert found == (faint_on or last_round)


@pytest.mark.parametrize("seed", [70, 111])
def test_stretch_points_give_edge_points_on_a_box_of_the_background_s_grey(seed):
    """Development seeds 70 (low contrast, 2.1 m) and 111 (plain): at frame 5 the search from
    scratch finds the cube, but its final refinement keeps few edge points at the usual step
    threshold (6 grey levels per px), too few on the inner edges for the inner-edge check
    (``min_inner_support`` 0.05), which rejects the fit. With the threshold over the box
    window's stretch gain (``stretch_points``, on in ``RANDOMIZED_BENCHMARK``) a fresh tracker
    with that check finds the cube within 2 cm of the rendered truth; without it, no valid fit.
    The benchmark's preset has the check off since session 50: there both fits are valid and
    within 2 cm (``stretch_points`` no longer decides these frames)."""
    scene = draw_scene(seed)
    seq, background = render_random_sequence(scene, 6, FPS, 640, 480)
    checked = dataclasses.replace(RANDOMIZED_BENCHMARK, min_inner_support=0.05)
    _found_at_frame_5_only_with("stretch_points", scene, seq, background, checked)
    from hec_jax.geometry import BoxTracker

    assert RANDOMIZED_BENCHMARK.min_inner_support == 0.0
    for on in (True, False):
        cfg = dataclasses.replace(RANDOMIZED_BENCHMARK, stretch_points=on)
        st = BoxTracker(seq.intrinsics, scene.edge_m, FPS, cfg, background).update(seq.frames[5])
        assert bool(st.valid)
        assert np.linalg.norm(st.measured_position - seq.position[5]) < 0.02


def _found_at_frame_5_only_with(option: str, scene, seq, background, base=RANDOMIZED_BENCHMARK):
    """A fresh tracker (``base``, where ``option`` is on) finds the cube at frame 5 within 2 cm
    of the rendered truth; with ``option`` off, no valid fit."""
    from hec_jax.geometry import BoxTracker

    assert getattr(base, option) is True
    for on in (True, False):
        cfg = dataclasses.replace(base, **{option: on})
        st = BoxTracker(seq.intrinsics, scene.edge_m, FPS, cfg, background).update(seq.frames[5])
        assert bool(st.valid) == on
        if on:
            assert np.linalg.norm(st.measured_position - seq.position[5]) < 0.02


def test_opencv_and_paper_baselines_run(rendered):
    scene, seq, background = rendered
    pnp = pnp_face_track(seq.frames, seq.intrinsics, scene.edge_m, FPS, background)
    paper = paper_two_frame_track(pnp.quads, seq.intrinsics, scene.edge_m, FPS)
    assert pnp.valid.any()
    assert pnp.position.shape == paper.position.shape == (12, 3)
    assert not paper.valid[0]  # needs a previous frame


def test_smoother_holds_instead_of_extrapolating():
    """Valid frames 20-39 of 60 moving at 1 m/s: outside them the output stays at the segment's
    ends with zero velocity (no motion model carried on over unmeasured frames)."""
    t_n, dt = 60, 1 / FPS
    valid = np.zeros(t_n, bool)
    valid[20:40] = True
    pos = np.zeros((t_n, 3))
    pos[:, 0] = np.arange(t_n) * dt  # 1 m/s
    pos[:, 2] = 1.0
    rot = np.tile(np.eye(3), (t_n, 1, 1))
    info = np.tile(np.eye(6) * 1e8, (t_n, 1, 1))
    out = smooth_track(
        rot, pos, info, valid, dt, SmootherConfig(info_scale=1.0, hinge=False, max_gap_s=NO_GAPS)
    )
    np.testing.assert_allclose(out.position[:20], np.repeat(out.position[20:21], 20, 0))
    np.testing.assert_allclose(out.position[40:], np.repeat(out.position[39:40], 20, 0))
    assert np.all(out.velocity[:20] == 0) and np.all(out.velocity[40:] == 0)
    np.testing.assert_allclose(out.position[20:40], pos[20:40], atol=1e-3)


def test_smoother_splits_at_long_gaps():
    t_n, dt = 50, 1 / FPS
    valid = np.ones(t_n, bool)
    valid[20:35] = False  # 0.5 s gap: two segments
    pos = np.tile([0.0, 0.0, 1.0], (t_n, 1))
    pos[35:, 0] = 0.5  # the box moved while unseen
    rot = np.tile(np.eye(3), (t_n, 1, 1))
    info = np.tile(np.eye(6) * 1e8, (t_n, 1, 1))
    out = smooth_track(
        rot, pos, info, valid, dt, SmootherConfig(info_scale=1.0, hinge=False, max_gap_s=NO_GAPS)
    )
    np.testing.assert_allclose(out.position[:20], pos[:20], atol=1e-6)
    np.testing.assert_allclose(out.position[35:], pos[35:], atol=1e-6)
    assert np.all(np.abs(out.position[20:35, 0] - 0.25) <= 0.25 + 1e-9)  # held, not overshot


def test_smoother_splits_at_the_tracker_s_restarts():
    """A wrong lock 1 m off (frames 0-4), lost for 3 frames (a gap under ``max_gap_s``), then
    the true track from frame 8 at 1 m/s, where the tracker restarted its filter. Split there,
    the true track's smoothed centres follow its measurements and the wrong lock keeps its own;
    as one segment (``split_at_restarts`` off, or no restarts given) the wrong lock pulls the
    true track's first frames."""
    t_n, dt = 40, 1 / FPS
    valid = np.ones(t_n, bool)
    valid[5:8] = False
    pos = np.zeros((t_n, 3))
    pos[:, 0] = np.arange(t_n) * dt  # 1 m/s
    pos[:, 2] = 1.0
    pos[:5, 2] = 2.0  # the wrong lock
    restarts = np.zeros(t_n, bool)
    restarts[[0, 8]] = True
    rot = np.tile(np.eye(3), (t_n, 1, 1))
    info = np.tile(np.eye(6) * 1e6, (t_n, 1, 1))
    split = SmootherConfig(info_scale=1.0, hinge=False, max_gap_s=NO_GAPS, split_at_restarts=True)
    out = smooth_track(rot, pos, info, valid, dt, split, restarts=restarts)
    np.testing.assert_allclose(out.position[8:], pos[8:], atol=2e-3)
    np.testing.assert_allclose(out.position[:5], pos[:5], atol=2e-3)
    np.testing.assert_array_equal(out.position[5:8], out.position[[4, 4, 8]])  # nearest end's
    for joined in (
        smooth_track(rot, pos, info, valid, dt, split),  # no restarts given
        smooth_track(
            rot,
            pos,
            info,
            valid,
            dt,
            dataclasses.replace(split, split_at_restarts=False),
            restarts=restarts,
        ),
    ):
        assert np.max(np.abs(joined.position[8:12, 2] - 1.0)) > 0.05
    # with no gap limit the restarts alone split
    only = SmootherConfig(info_scale=1.0, hinge=False, split_at_restarts=True)
    out = smooth_track(rot, pos, info, valid, dt, only, restarts=restarts)
    np.testing.assert_allclose(out.position[8:], pos[8:], atol=2e-3)
    with pytest.raises(ValueError, match="restarts"):
        smooth_track(rot, pos, info, valid, dt, split, restarts=restarts[:-1])


def test_pnp_baseline_is_exact_on_exact_corners(monkeypatch):
    """The OpenCV baseline on a face's exact corners (the intrinsics convention, as
    ``face_quad`` gives them): the box's centre to round-off. Corners shifted to OpenCV's pixel
    centres with K left as it is would put it about 1.2 mm/m off."""
    import cv2

    from hec_jax.geometry import baselines
    from hec_jax.geometry.camera import intrinsics_from_fovy

    k = intrinsics_from_fovy(45.0, 640, 480)
    edge = 0.1
    face_rot = [cv2.Rodrigues(np.array(r))[0] for r in ([0.3, -0.2, 0.1], [-0.1, 0.4, 0.05])]
    face_centre = [np.array([0.05, -0.03, 1.5]), np.array([-0.2, 0.1, 0.9])]
    obj = baselines._square_object_points(edge)
    quads = []
    for r, c in zip(face_rot, face_centre, strict=True):
        uvw = (obj @ r.T + c) @ k.T
        quads.append(uvw[:, :2] / uvw[:, 2:])
    monkeypatch.setattr(baselines, "face_quad", lambda frame, background: quads[int(frame)])
    track = baselines.pnp_face_track([0, 1], k, edge, FPS, None)
    assert track.valid.all()
    for i, (r, c) in enumerate(zip(face_rot, face_centre, strict=True)):
        n = r[:, 2] if r[:, 2] @ c > 0 else -r[:, 2]  # the box lies beyond its visible face
        np.testing.assert_allclose(track.position[i], c + 0.5 * edge * n, atol=1e-7)


def test_segments_in_mask_looks_up_the_pixel_that_holds_each_point():
    """Pixel (row j, column i) spans [i, i + 1) x [j, j + 1) in the intrinsics convention."""
    from hec_jax.geometry.detect import segments_in_mask

    seg = np.array([[[10.1, 10.2], [10.4, 10.3]]])  # inside pixel (10, 10)
    for where, kept in (((10, 10), 1), ((9, 9), 0)):
        mask = np.zeros((20, 20), bool)
        mask[where] = True
        assert len(segments_in_mask(seg, mask, (0, 0))) == kept, where
    # a window whose top-left pixel is (5, 8): the same pixel is (row 2, column 5) in it
    mask = np.zeros((6, 8), bool)
    mask[2, 5] = True
    assert len(segments_in_mask(seg, mask, (5, 8))) == 1


def test_track_errors_measure_rotation_from_the_first_valid_frame():
    """A perfect track acquired at frame 2 (its rotations relative to frame 2, as ``track_box``
    gives them) has no rotation error; one of frame 0's reference would show 2 frames' turn."""
    t_n = 10
    z = np.array([0.0, 0.0, 1.0])
    rot = np.stack([rotation_from_axis_angle(z, 0.05 * t) for t in range(t_n)])
    pos, zero = np.tile([0.0, 0.0, 1.0], (t_n, 1)), np.zeros((t_n, 3))
    truth = SimpleNamespace(position=pos, velocity=zero, acceleration=zero, rotation=rot)
    relative = rot @ rot[2].T
    track = SimpleNamespace(
        valid=np.arange(t_n) >= 2,
        position=pos,
        measured_position=pos,
        velocity=zero,
        acceleration=zero,
        rotation=relative,
        causal_position=pos,
        causal_velocity=zero,
        causal_acceleration=zero,
        causal_rotation=relative,
        timing_ms={},
    )
    errors = accuracy.track_errors(track, truth)
    assert errors["rotation_median_deg"] < 1e-5 and errors["causal_rotation_median_deg"] < 1e-5
    assert errors["position_rms_mm"] == 0.0 and errors["valid_rate"] == 0.8


def test_non_finite_outputs_on_valid_frames_count_against_the_method():
    """A valid frame with a NaN position is a gross error (not dropped), a NaN rotation 180 deg
    off; a NaN velocity is no velocity, counted by the table's velocity coverage."""
    t_n = 6
    truth = SimpleNamespace(
        position=np.tile([0.0, 0.0, 1.0], (t_n, 1)),
        velocity=np.zeros((t_n, 3)),
        rotation=np.tile(np.eye(3), (t_n, 1, 1)),
    )
    position, velocity = truth.position.copy(), np.zeros((t_n, 3))
    rotation = truth.rotation.copy()
    position[2] = np.nan
    rotation[3] = np.nan
    velocity[0] = np.nan
    errors = accuracy.sequence_errors(
        position, rotation, velocity, np.ones(t_n, bool), truth, np.ones(t_n, bool), 1.0
    )
    assert errors["gross_errors"] == 1 and errors["acquire_delay"] == 0
    assert errors["rotation_err_deg"][3] == 180.0 and np.sum(errors["rotation_err_deg"]) == 180.0
    table = accuracy.target_table([errors])
    assert table["gross_errors"] == 1 and not table["meets"]["gross_errors"]
    assert table["velocity_coverage"] == 5 / 6 and table["velocity_rms_m_s"] == 0.0


def test_symmetric_rotation_error():
    rng = np.random.default_rng(0)
    r = random_rotation(rng, (5,))
    sym = cube_symmetries()
    relabelled = r @ sym[rng.integers(0, 24, 5)]
    np.testing.assert_allclose(accuracy.symmetric_rotation_error_deg(relabelled, r), 0, atol=1e-5)
    assert len({tuple(np.round(s, 6).ravel()) for s in sym}) == 24


def test_match_quad_orders_corners():
    q = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]])
    moved = np.roll(q[::-1], 1, axis=0) + 0.5
    np.testing.assert_allclose(match_quad(q, moved), q + 0.5)


@pytest.mark.parametrize("seed", [20, 44])
def test_outside_foreground_rejects_a_box_fitted_inside_the_cube(seed):
    """Development seeds 20 and 44 (wood cubes, 45 and 60 px): the tracker took fits of a
    smaller box too far away, on the grain inside the cube, 0.1-0.9 m off
    (docs/eye_randomized.md, session 28). Such a box (the true rotation, 25% farther along the
    line of sight) passes the silhouette check (its pixels differ from the background), but
    the ring just outside it lies on the cube; the true pose's ring is background. On frames
    0, 10, 20 of each, against the threshold of ``RANDOMIZED_BENCHMARK``."""
    from hec_jax.geometry import detect
    from hec_jax.geometry.box_model import project_corners_np

    cfg = RANDOMIZED_BENCHMARK
    scene = draw_scene(seed)
    seq, background = render_random_sequence(scene, 21, FPS, 640, 480)
    thr = cfg.foreground_threshold
    for t in (0, 10, 20):
        frame, rot, pos = seq.frames[t], seq.rotation[t], seq.position[t]
        true = project_corners_np(rot, pos, scene.edge_m, seq.intrinsics)
        far = project_corners_np(rot, 1.25 * pos, scene.edge_m, seq.intrinsics)
        assert detect.foreground_fraction(frame, background, far, thr) >= cfg.min_foreground
        ring_far = detect.outside_foreground_fraction(frame, background, far, thr)
        ring_true = detect.outside_foreground_fraction(frame, background, true, thr)
        assert ring_true < cfg.max_outside_foreground < ring_far, (t, ring_true, ring_far)


def test_faint_masks_confirm_a_low_contrast_cube():
    """Development seed 11 (low contrast, a 28 px cube at 1.6 m), never acquired before the faint
    masks: the true pose's silhouette differs from the background in under half its pixels at
    the usual threshold (so even the true pose failed ``min_foreground``), and in over half
    with the faint foreground added (``faint_masks``, on in ``RANDOMIZED_BENCHMARK``), at
    frames 5, 20 and 35."""
    from hec_jax.geometry import detect
    from hec_jax.geometry.box_model import project_corners_np

    cfg = RANDOMIZED_BENCHMARK
    assert cfg.faint_masks
    scene = draw_scene(11)
    assert scene.look == "low_contrast"
    seq, background = render_random_sequence(scene, 36, FPS, 640, 480)
    thr, faint = cfg.foreground_threshold, detect.faint_threshold(seq.frames[0], background)
    for t in (5, 20, 35):
        frame = seq.frames[t]
        true = project_corners_np(seq.rotation[t], seq.position[t], scene.edge_m, seq.intrinsics)
        usual = detect.foreground_fraction(frame, background, true, thr)
        with_faint = detect.foreground_fraction(frame, background, true, thr, faint)
        assert usual < cfg.min_foreground < with_faint, (t, usual, with_faint)


def _fit_from_truth(tracker, seq, t: int, first: bool):
    """(the tracker's final fit of frame ``t`` from its rendered true pose as the prior, the
    frame in gray, the number of segments in the moving window), through the tracked fit's
    own steps (its segments, ``prior_segments``, the refinement; refined where the located fit
    failed too, which the tracker itself skips)."""
    from hec_jax.geometry import detect
    from hec_jax.geometry.box_model import project_corners_np
    from hec_jax.geometry.track import _window

    cfg, prior = tracker.config, (seq.rotation[t], seq.position[t])
    tracker._frame_rgb = seq.frames[t]
    gray = detect.to_gray(seq.frames[t])
    corners = project_corners_np(*prior, tracker.size, seq.intrinsics)
    seg = tracker._moving_segments(gray, _window(corners, cfg.roi_margin))
    segp, mask = detect.pad_segments(tracker._near_prior(seg, prior), cfg.max_segments)
    return tracker._fit(prior, segp, mask, gray, first, refine_failed=True), gray, len(seg)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_segments_near_edges_are_those_the_first_gate_can_assign(seed):
    """``segments_near_edges`` (NumPy, host) keeps exactly the segments that
    :func:`track.associate` (JAX) assigns to an edge at the first gate, for segments scattered
    around and along a random pose's projected edges."""
    import jax.numpy as jnp

    from hec_jax.geometry.box_model import EDGES, Pose, project_corners_np
    from hec_jax.geometry.track import TrackConfig, associate, segments_near_edges

    rng = np.random.default_rng(seed)
    cfg, size = TrackConfig(), 0.1
    k = np.array([[600.0, 0, 320], [0, 600.0, 240], [0, 0, 1]])
    rot, t = random_rotation(rng), np.array([0.05, -0.03, 0.8])
    edges = project_corners_np(rot, t, size, k)[EDGES]
    e = edges[rng.integers(0, 12, 200)]
    s = rng.uniform(-0.3, 1.3, (200, 2, 1))
    seg = e[:, :1] + s * (e[:, 1:] - e[:, :1])  # on the edges' lines, partly beyond them
    seg = seg + rng.normal(0, 1, (200, 1, 2)) * rng.choice([2.0, 12.0, 30.0], (200, 1, 1))
    seg[:20] = rng.uniform(0, 640, (20, 2, 2))  # anywhere
    kept = segments_near_edges(seg, rot, t, size, k, cfg)
    asc = associate(
        Pose(jnp.asarray(rot), jnp.asarray(t)),
        jnp.asarray(seg),
        jnp.ones(len(seg), bool),
        size,
        jnp.asarray(k),
        cfg.gates_px[0],
        np.cos(np.deg2rad(cfg.gate_deg)),
        cfg.min_edge_px,
    )
    assigned = np.asarray(asc.weights) > 0
    assert 20 < assigned.sum() < len(seg) - 20  # both kinds present
    np.testing.assert_array_equal(kept, seg[assigned])


def test_a_fit_whose_located_fit_failed_is_not_refined_and_nothing_else_changes():
    """``BoxTracker._fit`` makes no edge points and no refinement where the located fit failed
    its checks (a refined fit is valid only where the located one is). On development seed
    43's frames, from priors around and off the true pose (0-10 cm, 0-30 deg), with and
    without pixels occluded over half the box (which allow ``three``'s fits with hidden
    edges), the call returns None exactly where the fit refined all the same
    (``refine_failed``) is invalid, and otherwise the same fit, bit for bit; the ``three``
    fits are the same either way."""
    import cv2
    import jax

    from hec_jax.geometry import BoxTracker, detect
    from hec_jax.geometry.box_model import EDGE_FAMILY, project_corners_np
    from hec_jax.geometry.track import _window, usable_edges

    scene = draw_scene(43)
    seq, background = render_random_sequence(scene, 16, FPS, 640, 480)
    cfg = RANDOMIZED_BENCHMARK
    tracker = BoxTracker(seq.intrinsics, scene.edge_m, FPS, cfg, background)
    rng = np.random.default_rng(0)
    counts = {"skipped": 0, "refined": 0, "three": 0}

    def same(a, b) -> bool:
        leaves_a, leaves_b = jax.tree.leaves(a), jax.tree.leaves(b)
        return len(leaves_a) == len(leaves_b) and all(
            np.array_equal(np.asarray(x), np.asarray(y), equal_nan=True)
            for x, y in zip(leaves_a, leaves_b, strict=True)
        )

    for t in (5, 11, 15):
        box = project_corners_np(seq.rotation[t], seq.position[t], scene.edge_m, seq.intrinsics)
        (x0, y0), (x1, y1) = box.min(0).astype(int), box.max(0).astype(int)
        half = np.zeros(seq.frames[t].shape[:2], bool)
        half[y0:y1, x0 : (x0 + x1) // 2] = True
        for occluded in (None, half):
            # an occluder's pixels replaced by the background's, as the loop's robot mask does
            frame = seq.frames[t].copy()
            if occluded is not None:
                frame[occluded] = background[occluded]
            gray = detect.to_gray(frame)
            tracker._frame_rgb = frame
            tracker._occluded = tracker._occluded_pixels(occluded, gray.shape)
            for shift_m in (0.0, 0.01, 0.03, 0.1):
                for turn_deg in (0.0, 10.0, 30.0):
                    turn = rotation_from_axis_angle(rng.normal(size=3), np.deg2rad(turn_deg))
                    away = rng.normal(size=3)
                    prior = (
                        turn @ seq.rotation[t],
                        seq.position[t] + shift_m * away / np.linalg.norm(away),
                    )
                    corners = project_corners_np(*prior, scene.edge_m, seq.intrinsics)
                    seg = tracker._moving_segments(gray, _window(corners, cfg.roi_margin))
                    segp, mask = detect.pad_segments(
                        tracker._near_prior(seg, prior), cfg.max_segments
                    )
                    three, three_refined = [], []
                    fit = tracker._fit(prior, segp, mask, gray, True, three=three)
                    full = tracker._fit(
                        prior, segp, mask, gray, True, three=three_refined, refine_failed=True
                    )
                    assert len(three) == len(three_refined)
                    assert all(same(a, b) for a, b in zip(three, three_refined, strict=True))
                    counts["three"] += len(three)
                    if fit is None:
                        counts["skipped"] += 1
                        assert not bool(full.valid)
                    else:
                        counts["refined"] += 1
                        assert same(fit, full)
    # and a fit valid but for its segment count: three segments on edges of two families at the
    # true pose, every other edge of the box hidden by occluded pixels (``three`` gets its fit)
    for t in (5, 11, 15):
        gray = detect.to_gray(seq.frames[t])
        tracker._frame_rgb = seq.frames[t]
        truth = (seq.rotation[t], seq.position[t])
        edges_px, usable = usable_edges(*truth, scene.edge_m, seq.intrinsics, cfg)
        ids = np.flatnonzero(usable)
        family = EDGE_FAMILY[ids]
        chosen = np.concatenate([ids[family == family[0]][:2], ids[family != family[0]][:1]])
        corners = project_corners_np(*truth, scene.edge_m, seq.intrinsics)
        occluded = np.zeros(gray.shape, np.uint8)
        cv2.fillConvexPoly(occluded, cv2.convexHull(corners.astype(np.int32)), 1)
        occluded = cv2.dilate(occluded, np.ones((31, 31), np.uint8))
        for p0, p1 in edges_px[chosen].astype(int):
            cv2.line(occluded, (int(p0[0]), int(p0[1])), (int(p1[0]), int(p1[1])), 0, 13)
        tracker._occluded = tracker._occluded_pixels(occluded.astype(bool), gray.shape)
        mid = edges_px[chosen].mean(1, keepdims=True)
        segp, mask = detect.pad_segments(mid + 0.8 * (edges_px[chosen] - mid), cfg.max_segments)
        three, three_refined = [], []
        fit = tracker._fit(truth, segp, mask, gray, True, three=three)
        full = tracker._fit(truth, segp, mask, gray, True, three=three_refined, refine_failed=True)
        assert fit is None and not bool(full.valid)
        assert len(three) == len(three_refined) == 1 and same(three[0], three_refined[0])
        counts["three"] += 1
    assert counts["skipped"] > 0 and counts["refined"] > 0, counts


def test_prior_segments_keep_a_large_wood_box_s_fit_from_its_true_pose():
    """Development seed 43 (wood, 0.11 m at 0.7 m, about 150 px): the moving blob's window
    holds over 100 segments, most on the grain. From the true pose the final fit slides off
    (invalid, 7-16 cm) where the longest ``max_segments`` are kept, and stays within 2 cm where
    they are first cut to the prior's first gate (``prior_segments``). Without the grain
    families (``texture_families`` None, the preset of session 29; with them, session 87's,
    the grain is dropped before the cut)."""
    from hec_jax.geometry import BoxTracker

    scene = draw_scene(43)
    seq, background = render_random_sequence(scene, 16, FPS, 640, 480)
    for on in (True, False):
        cfg = dataclasses.replace(RANDOMIZED_BENCHMARK, prior_segments=on, texture_families=None)
        tracker = BoxTracker(seq.intrinsics, scene.edge_m, FPS, cfg, background)
        for t in (11, 15):
            fit, _, segments = _fit_from_truth(tracker, seq, t, first=True)
            assert segments > 2 * cfg.max_segments
            err = np.linalg.norm(np.asarray(fit.translation) - seq.position[t])
            if on:
                assert fit.valid and err < 0.02
            else:
                assert not fit.valid and err > 0.05


def test_a_low_contrast_box_s_true_fit_passes_the_tracked_silhouette_check():
    """Development seed 135 (low contrast): at frames 14 and 24 the fit from the true pose is
    within 5 mm, but with session 29's faint masks (the faint floor at 6 grey levels, no
    ``shadow_faces``) under half its silhouette differs from the background, so the full
    silhouette check (``min_foreground`` 0.5) rejects it; while the filter runs the benchmark
    asks a quarter (``min_foreground_tracked``). The same box moved off the cube, onto the
    static background beside it, fails both. With session 32's preset (floor 3,
    ``shadow_faces``) the true fits pass the full check too."""
    from hec_jax.geometry import BoxTracker
    from hec_jax.geometry.box_model import project_corners_np

    scene = draw_scene(135)
    seq, background = render_random_sequence(scene, 25, FPS, 640, 480)
    preset = RANDOMIZED_BENCHMARK
    # session 29's masks, and without session 81's face check while tracking (whose own faint
    # level refuses these faces at floor 6): the silhouette bars alone
    cfg = dataclasses.replace(
        preset, faint_min_threshold=6.0, shadow_faces=None, min_face_foreground_tracked=None
    )
    assert cfg.min_foreground == 0.5 and cfg.min_foreground_tracked == 0.25
    tracker = BoxTracker(seq.intrinsics, scene.edge_m, FPS, cfg, background)
    now = BoxTracker(seq.intrinsics, scene.edge_m, FPS, preset, background)
    for t in (14, 24):
        fit, gray, _ = _fit_from_truth(tracker, seq, t, first=False)
        fit_rot, fit_pos = np.asarray(fit.rotation), np.asarray(fit.translation)
        assert fit.valid and np.linalg.norm(fit_pos - seq.position[t]) < 0.005
        assert not tracker._confirmed(gray, fit_rot, fit_pos)
        assert tracker._confirmed(gray, fit_rot, fit_pos, tracked=True)
        now._frame_rgb = tracker._frame_rgb  # the frame _fit_from_truth gave the first tracker
        assert now._confirmed(gray, fit_rot, fit_pos)
        assert now._confirmed(gray, fit_rot, fit_pos, tracked=True)  # the face check's too
        beside = fit_pos + np.array([3 * scene.edge_m, 0.0, 0.0])
        moved = project_corners_np(fit_rot, beside, scene.edge_m, seq.intrinsics)
        assert np.all((moved > 0) & (moved < [640, 480]))  # in the image
        assert not tracker._confirmed(gray, fit_rot, beside, tracked=True)


def test_a_box_of_the_wall_s_hue_passes_the_shadow_test_and_its_blob_is_found_without_it():
    """Development seed 113 (plain, dark purple on a mauve wall: the cube's channels are the
    wall's times 0.43-0.51): the colour difference's shadow test zeroes most of the cube, and
    its blobs are the rod's alone; without the test (``shadows=False``) the largest blob is the
    cube. With ``shadow_candidates`` (on in ``RANDOMIZED_BENCHMARK``) a fresh tracker finds the
    cube at frame 5 within 2 cm; without it, no valid fit."""
    from hec_jax.geometry import detect
    from hec_jax.geometry.box_model import project_corners_np

    scene = draw_scene(113)
    seq, background = render_random_sequence(scene, 6, FPS, 640, 480)
    frame, truth = seq.frames[5], seq.position[5]
    corners = project_corners_np(seq.rotation[5], truth, scene.edge_m, seq.intrinsics)
    box = (*corners.min(0), *corners.max(0))
    core = RANDOMIZED_BENCHMARK.blob_core
    with_test = detect.foreground_regions(frame, background, core=core)
    without = detect.foreground_regions(frame, background, core=core, shadows=False)
    assert all(_iou(r[0], box) < 0.3 for r in with_test)
    assert _iou(without[0][0], box) > 0.8
    _found_at_frame_5_only_with("shadow_candidates", scene, seq, background)


def test_a_faint_cube_under_six_grey_levels_is_found_with_the_lower_floor():
    """Development seed 53 (low contrast; never acquired with the faint threshold's floor at 6
    grey levels; seed 48, not acquired in time there, behaves alike): the cube differs from the
    wall by 4-6 grey levels in the 5x5-blurred colour difference, the sensor noise there by
    1-2. At frame 5 no faint blob at
    the floor 6 matches the cube's true box (IoU under 0.5); at ``RANDOMIZED_BENCHMARK``'s floor
    (3) the largest does (over 0.7). A fresh tracker over frames 0-5 has a valid fit within 2 cm
    of the rendered truth on every frame with that floor, and none with the floor at 6."""
    from hec_jax.geometry import BoxTracker, detect
    from hec_jax.geometry.box_model import project_corners_np

    scene = draw_scene(53)
    seq, background = render_random_sequence(scene, 6, FPS, 640, 480)
    corners = project_corners_np(seq.rotation[5], seq.position[5], scene.edge_m, seq.intrinsics)
    box = (*corners.min(0), *corners.max(0))
    core = RANDOMIZED_BENCHMARK.blob_core
    floor = RANDOMIZED_BENCHMARK.faint_min_threshold
    assert floor == 3.0
    frame = seq.frames[5]
    at_six = detect.faint_foreground_regions(frame, background, min_threshold=6.0, core=core)
    lower = detect.faint_foreground_regions(frame, background, min_threshold=floor, core=core)
    assert all(_iou(r[0], box) < 0.5 for r in at_six)
    assert _iou(lower[0][0], box) > 0.7
    for value in (floor, 6.0):
        cfg = dataclasses.replace(RANDOMIZED_BENCHMARK, faint_min_threshold=value)
        tracker = BoxTracker(seq.intrinsics, scene.edge_m, FPS, cfg, background)
        steps = [tracker.update(f) for f in seq.frames]
        valid = np.array([bool(st.valid) for st in steps])
        if value == floor:
            measured = np.stack([st.measured_position for st in steps])
            assert valid.all()
            assert np.linalg.norm(measured - seq.position, axis=-1).max() < 0.02
        else:
            assert not valid.any()


def test_the_segments_mask_keeps_its_floor_on_a_far_faint_cube():
    """Development seed 157 (low contrast, an 8 cm cube at 2.2 m): with the faint floor of 3
    grey levels also in the mask that keeps the segments on the moving box, the tracked fits
    slide along the line of sight over the last third of the swing (more than 20 cm off by
    frame 44, still valid); ``RANDOMIZED_BENCHMARK`` keeps that mask's floor at 6
    (``faint_segment_min_threshold``), and its fits of frames 35-44 stay within 5 cm. Both
    without ``lsd_contrast`` and with the search's fits re-located at every gate
    (``acquired_gates_px`` None): session 32's preset. With ``lsd_contrast`` (session 37) the
    lower floor's fits of frames 35-44 stay within 5 cm, but an earlier fit is 24 cm off; with
    session 86's re-location at the search's last gate (the preset's now) they stay within
    4 cm, so this test keeps session 32's preset."""
    scene = draw_scene(157)
    seq, background = render_random_sequence(scene, 45, FPS, 640, 480)
    assert RANDOMIZED_BENCHMARK.faint_segment_min_threshold == 6.0
    late = slice(35, 45)
    for segment_floor in (6.0, None):
        cfg = dataclasses.replace(
            RANDOMIZED_BENCHMARK,
            faint_segment_min_threshold=segment_floor,
            lsd_contrast=None,
            acquired_gates_px=None,
        )
        tr = track_box(seq.frames, seq.intrinsics, scene.edge_m, FPS, cfg, background=background)
        err = np.linalg.norm(tr.measured_position - seq.position, axis=-1)[late][tr.valid[late]]
        assert tr.valid[late].sum() >= 5
        if segment_floor is None:
            assert err.max() > 0.2
        else:
            assert err.max() < 0.05


def _silhouette_frame(background, corners, colour_of):
    """``background`` with the convex hull of ``corners`` [px] painted pixel by pixel by
    ``colour_of(row, col, background_rgb)``; (frame, hull mask)."""
    import cv2

    hull = cv2.convexHull(np.round(corners - 0.5).astype(np.int32))
    mask = np.zeros(background.shape[:2], np.uint8)
    cv2.fillConvexPoly(mask, hull, 1)
    frame = background.copy()
    rows, cols = np.nonzero(mask)
    for r, c in zip(rows, cols, strict=True):
        frame[r, c] = colour_of(r, c, background[r, c].astype(float))
    return frame, mask.astype(bool)


def test_shadow_faces_count_a_dark_face_but_not_a_shadow():
    """Synthetic, the rule of ``TrackConfig.shadow_faces``: on a mauve wall, a box whose lower
    part is the wall darkened by 0.5 in every channel (what the shadow test calls a shadow: a
    cube of the wall's hue in shade) and whose top is lighter and redder passes the silhouette
    checks only with the option, and only where its lit part is at least the option's bar (a
    top third passes at the preset's 0.1 and at 0.25, a top fifth at 0.1 only); a box-shaped
    patch that is all shadow (the cube's own shadow) fails them at every bar."""
    from hec_jax.geometry import BoxTracker
    from hec_jax.geometry.box_model import project_corners_np

    assert RANDOMIZED_BENCHMARK.shadow_faces == 0.1
    k = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    rng = np.random.default_rng(3)
    wall = np.clip(np.array([150, 100, 130]) + rng.normal(0, 1.0, (480, 640, 3)), 0, 255)
    background = wall.round().astype(np.uint8)
    rotation = random_rotation(np.random.default_rng(11))
    translation = np.array([0.0, 0.0, 1.0])
    corners = project_corners_np(rotation, translation, 0.1, k)
    height = corners[:, 1].max() - corners[:, 1].min()
    frames = {}
    for name, part in (("third", 1 / 3), ("fifth", 1 / 5)):
        top = corners[:, 1].min() + height * part

        def face(r, c, bg, top=top):
            return np.array([200.0, 110, 120]) if r < top else 0.5 * bg

        frames[name], mask = _silhouette_frame(background, corners, face)
        lit = (np.nonzero(mask)[0] < top).mean()  # the lit part of the box
        assert 0.2 < lit < 0.5 if name == "third" else 0.1 < lit < 0.2, (name, lit)
    frames["shadow"], _ = _silhouette_frame(background, corners, lambda r, c, bg: 0.5 * bg)
    results = {}
    # the shadow rule alone: a box lit above a horizontal line and shaded below it has faces
    # whose halves differ, which ``max_face_split`` (a fit spanning two faces) refuses as well
    for option in (0.1, 0.25, None):
        cfg = dataclasses.replace(RANDOMIZED_BENCHMARK, shadow_faces=option, max_face_split=None)
        for name, frame in frames.items():
            tracker = BoxTracker(k, 0.1, FPS, cfg, background)
            tracker._frame_rgb = frame  # as update() sets it for the frame being checked
            gray = frame.mean(-1).astype(np.uint8)
            results[option, name] = tracker._confirmed(gray, rotation, translation, acquire=True)
    assert results == {
        (0.1, "third"): True,
        (0.1, "fifth"): True,
        (0.1, "shadow"): False,
        (0.25, "third"): True,
        (0.25, "fifth"): False,
        (0.25, "shadow"): False,
        (None, "third"): False,
        (None, "fifth"): False,
        (None, "shadow"): False,
    }


def _fresh_tracker_fits(scene, seq, background, cfg) -> tuple[np.ndarray, np.ndarray]:
    """A fresh ``BoxTracker`` (``cfg``) over the rendered frames: per frame, whether its fit is
    valid and the fit's distance from the rendered cube centre [m] (NaN where not valid)."""
    from hec_jax.geometry import BoxTracker

    tracker = BoxTracker(seq.intrinsics, scene.edge_m, FPS, cfg, background)
    steps = [tracker.update(f) for f in seq.frames]
    valid = np.array([bool(st.valid) for st in steps])
    fitted = np.stack([st.measured_position for st in steps])
    return valid, np.linalg.norm(fitted - seq.position, axis=-1)


def test_acquired_gates_keep_the_search_s_fit_of_a_wood_cube():
    """Development seed 6605 (a wood cube seen from 3 deg above; acquired at frame 11 before the
    option): on frames 1 and 3 the search from scratch returns a fit 1-3 cm from the truth that
    passes the acquisition checks, and the re-location from it at every tracked gate (16 px
    first) loses its coverage, so the frame is not valid. Re-located at the search's last gate
    only (``acquired_gates_px`` (1.5,), on in ``RANDOMIZED_BENCHMARK``), a fresh tracker has
    valid fits among frames 0-3, each within the benchmark's gross bar (5 cm) of the rendered
    truth; with every gate (None), no valid fit there. Under session 86's preset
    (``texture_families`` None): with the grain families dropped (session 87) both find it."""
    scene = draw_scene(6605)
    assert scene.look == "wood"
    seq, background = render_random_sequence(scene, 4, FPS, 640, 480)
    assert RANDOMIZED_BENCHMARK.acquired_gates_px == (1.5,)
    preset = dataclasses.replace(RANDOMIZED_BENCHMARK, texture_families=None, threads=1)
    for option in ((1.5,), None):
        cfg = dataclasses.replace(preset, acquired_gates_px=option)
        valid, err = _fresh_tracker_fits(scene, seq, background, cfg)
        if option is None:
            assert not valid.any()
        else:
            assert valid.any() and err[valid].max() < 0.05


def test_texture_families_keep_a_wood_cube_s_fits_off_its_grain():
    """Development seed 2074 (a wood cube 12 cm across, 2.1 m away, seen nearly face-on): ten
    or more grain lines run across its front face and its inner edges show no step. The fits
    walk off, from the true pose too: frame 1's tracked fit lies 29 cm off along the line of
    sight, and the track after it 19-47 cm off.
    Dropping the segments inside the box that form a family of three or more parallel lines
    (``texture_families`` 3), a fresh tracker's fits on frames 0-5 are all valid and within
    the benchmark's gross bar (5 cm) of the rendered truth; without, a valid fit lies more than
    20 cm off."""
    scene = draw_scene(2074)
    assert scene.look == "wood"
    seq, background = render_random_sequence(scene, 6, FPS, 640, 480)
    assert RANDOMIZED_BENCHMARK.texture_families == 3
    for option in (3, None):
        cfg = dataclasses.replace(RANDOMIZED_BENCHMARK, texture_families=option, threads=1)
        valid, err = _fresh_tracker_fits(scene, seq, background, cfg)
        if option is None:
            assert (valid & (err > 0.2)).any()
        else:
            assert valid.all() and err.max() < 0.05


def test_a_grain_family_keeps_its_strongest_line_the_box_s_edge():
    """Development seed 130 (wood, shadows; a large close box): its edge between the top and
    front faces lies among grain lines parallel to it. Dropping the whole family
    (``texture_family_keep_step`` False) drops that edge too, and a fresh tracker's fits on
    frames 0-2 lie 2-4 cm off; keeping each family's line of largest grey step (True, the
    preset), every fit on frames 0-5 is valid and within 3 mm of the rendered truth."""
    scene, seq, background = _rendered_six(130)
    assert RANDOMIZED_BENCHMARK.texture_family_keep_step
    for keep in (True, False):
        cfg = dataclasses.replace(RANDOMIZED_BENCHMARK, texture_family_keep_step=keep, threads=1)
        valid, err = _fresh_tracker_fits(scene, seq, background, cfg)
        if keep:
            assert valid.all() and err.max() < 0.003
        else:
            assert (valid[:3] & (err[:3] > 0.02)).all()


def test_shadow_faces_find_a_cube_of_the_wall_s_hue():
    """Development seed 21 (low contrast: a magenta cube on a magenta wall, never acquired
    before the option): the colour difference's shadow test takes the cube's darker faces
    for shadows, and even its true pose fails the silhouette checks (frame 5: 0.43 of its
    silhouette in the foreground, IoU 0.35). Counting the test's pixels there (``shadow_faces``,
    on in ``RANDOMIZED_BENCHMARK``), a fresh tracker has a valid fit within 2 cm of the
    rendered truth on each of frames 0-5; without, none within 5 cm."""
    scene = draw_scene(21)
    seq, background = render_random_sequence(scene, 6, FPS, 640, 480)
    assert RANDOMIZED_BENCHMARK.shadow_faces == 0.1
    for option in (0.1, None):
        cfg = dataclasses.replace(RANDOMIZED_BENCHMARK, shadow_faces=option)
        valid, err = _fresh_tracker_fits(scene, seq, background, cfg)
        if option is None:
            assert not (valid & (err < 0.05)).any()
        else:
            assert valid.all() and err.max() < 0.02


def test_blob_scales_find_a_low_view_box_the_blob_s_own_search_misses():
    """Development seed 507 (a low-contrast cube 5 cm across, the camera 9 deg above it, acquired
    only at frame 15 before the option): its first frames' blob lies on the cube, but the
    search from that blob's window finds too few of the cube's edges (9 segments, fits 0.2-1 m
    off). With a last round on the blob at 3x its size and window (``blob_scales`` (3,), the
    value chosen on the development seeds; off in the preset), a fresh tracker has a valid fit
    within 3 cm of the rendered truth on each of frames 1-3 (the benchmark's gross bar is
    5 cm); without it (the preset), no valid fit."""
    scene = draw_scene(507)
    seq, background = render_random_sequence(scene, 4, FPS, 640, 480)
    assert RANDOMIZED_BENCHMARK.blob_scales == ()
    for option in ((3.0,), ()):
        cfg = dataclasses.replace(RANDOMIZED_BENCHMARK, blob_scales=option)
        valid, err = _fresh_tracker_fits(scene, seq, background, cfg)
        if option:
            assert valid[1:].all() and err[1:].max() < 0.03
        else:
            assert not valid.any()


def test_difference_without_the_shadow_test_keeps_a_darkened_background():
    """A pixel at half the background in every channel is a shadow to the shadow test (0) and
    its plain difference without it (``shadow_ratio=None``); other pixels are the same."""
    from hec_jax.geometry import detect

    rng = np.random.default_rng(0)
    background = rng.integers(60, 200, (8, 8, 3)).astype(np.uint8)
    image = background.copy()
    image[2:5, 2:5] = background[2:5, 2:5] // 2  # the wall's hue, darker
    image[6, 6] = [0, 255, 0]
    with_test = detect.difference(image, background)
    without = detect.difference(image, background, None)
    plain = np.abs(image.astype(int) - background.astype(int)).max(-1)
    np.testing.assert_array_equal(without, plain)
    assert np.all(with_test[2:5, 2:5] == 0) and np.all(without[2:5, 2:5] >= 30)
    outside = np.ones((8, 8), bool)
    outside[2:5, 2:5] = False
    np.testing.assert_array_equal(with_test[outside], without[outside])
