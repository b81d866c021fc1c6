"""Tracking on rendered frames of the swinging cube (rendered once per module, 24 frames), and
the defaults against the tracker recorded before issue 24's checks were merged."""

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from hec_jax.geometry import TrackConfig, rotation_error_deg
from hec_jax.geometry.smooth import SmootherConfig
from hec_jax.geometry.track import UNSEEN_SCENES, BoxTracker, track_box
from hec_jax.loop.config import LAB_CHECKS, CameraConfig, scene_tracker
from hec_jax.mjx_scene.render import render_swing

FPS = 30.0
EDGE = 0.1


@pytest.fixture(scope="module")
def seq():
    return render_swing(0.5, 24, FPS)


@pytest.fixture(scope="module")
def track(seq):
    return track_box(seq.frames, seq.intrinsics, EDGE, FPS)


@pytest.fixture(scope="module")
def swing_5s():
    """The issue's sequence length (5 s at 30 fps). The fixed-axis model's acceptance is decided
    by a median residual over the frames: on 24-48 frames of this swing it came out 0.39-0.61 on
    one machine (threshold 0.5), on 150 frames 0.26, so the targets are checked at full length."""
    seq = render_swing(0.5, 150, FPS)
    return seq, track_box(seq.frames, seq.intrinsics, EDGE, FPS)


def test_intrinsics_from_mjcf(seq):
    f = 240.0 / np.tan(np.deg2rad(45.0) / 2)
    np.testing.assert_allclose(seq.intrinsics, [[f, 0, 320], [0, f, 240], [0, 0, 1]])


def test_tracks_every_frame(seq, track):
    assert track.valid.mean() >= 0.9
    err = np.linalg.norm(track.measured_position - seq.position, axis=-1)[track.valid]
    assert np.median(err) < 0.02  # a coarse sanity bound (2 cm), not the issue's target


def _rms(a, b, valid):
    return np.sqrt(np.mean(np.sum((a - b) ** 2, -1)[valid]))


def test_issue_targets_position_velocity_acceleration(swing_5s):
    """Issue 5's rendered-sequence targets on a 5 s swing (release 0.5 rad)."""
    seq, track = swing_5s
    v = track.valid
    assert _rms(track.position, seq.position, v) <= 0.005
    assert _rms(track.velocity, seq.velocity, v) <= 0.05
    assert _rms(track.acceleration, seq.acceleration, v) <= 0.5


def test_issue_target_rotation(swing_5s):
    """Issue 5's rotation target on a 5 s swing: met through the fixed-axis model (the hinge)."""
    seq, track = swing_5s
    v = track.valid
    assert track.hinge
    phi = seq.rotation @ seq.rotation[0].T
    assert np.median(rotation_error_deg(track.rotation, phi)[v]) <= 1.0


@pytest.mark.parametrize(
    "frames, match",
    [
        (np.zeros((3, 48, 64, 3), np.float32), "uint8"),
        (np.zeros((3, 48, 64), np.uint8), "shape"),
        (np.zeros((0, 48, 64, 3), np.uint8), "at least one"),
    ],
)
def test_bad_frames_raise(frames, match):
    with pytest.raises(ValueError, match=match):
        track_box(frames, np.eye(3), EDGE, FPS)


def test_bad_arguments_raise(seq):
    with pytest.raises(ValueError):
        track_box(seq.frames[:2], np.eye(2), EDGE, FPS)
    with pytest.raises(ValueError):
        track_box(seq.frames[:2], seq.intrinsics, -1.0, FPS)
    with pytest.raises(ValueError):
        track_box(seq.frames[:2], seq.intrinsics, EDGE, 0.0)


def test_bad_gravity_raises_before_any_frame_is_tracked(seq, monkeypatch):
    """``track_box`` checks ``gravity_cam`` before tracking (a frame tracked would fail here)."""

    def tracked(*args, **kwargs):
        raise AssertionError("a frame was tracked")

    monkeypatch.setattr(BoxTracker, "update", tracked)
    for gravity in ([0.0, 1.0], [0.0, 0.0, 0.0], [np.inf, 1.0, 0.0]):
        with pytest.raises(ValueError, match="gravity_cam"):
            track_box(seq.frames[:2], seq.intrinsics, EDGE, FPS, gravity_cam=gravity)


@pytest.mark.parametrize("scales", [[3.0], (3.0, 0.0), (float("nan"),), ("3",)])
def test_bad_blob_scales_raise(scales):
    config = dataclasses.replace(TrackConfig(), blob_scales=scales)
    with pytest.raises(ValueError, match="blob_scales"):
        BoxTracker(np.diag([500.0, 500.0, 1.0]), EDGE, FPS, config)


@pytest.mark.parametrize("gates", [(), [1.5], (1.5, 0.0), (float("nan"),), (True,), ("1.5",)])
def test_bad_acquired_gates_px_raise(gates):
    config = dataclasses.replace(TrackConfig(), acquired_gates_px=gates)
    with pytest.raises(ValueError, match="acquired_gates_px"):
        BoxTracker(np.diag([500.0, 500.0, 1.0]), EDGE, FPS, config)


@pytest.mark.parametrize(
    "field, value",
    [
        ("jump_speed_m_s", 0.0),
        ("jump_speed_m_s", -1.0),
        ("jump_speed_m_s", float("nan")),
        ("jump_speed_m_s", True),
        ("jump_speed_m_s", "2"),
        ("jump_slack_m", -0.1),
        ("jump_slack_m", float("nan")),
        ("jump_slack_m", None),
        ("texture_families", 1),
        ("texture_families", 0),
        ("texture_families", 2.5),
        ("texture_families", True),
        ("texture_families", "3"),
    ],
)
def test_bad_jump_test_and_texture_family_settings_raise(field, value):
    config = dataclasses.replace(TrackConfig(), **{field: value})
    with pytest.raises(ValueError, match=field):
        BoxTracker(np.diag([500.0, 500.0, 1.0]), EDGE, FPS, config)


def test_a_jump_test_no_fit_violates_changes_nothing(seq):
    """A bound far above the rendered box's speed (100 m/s) changes no gate decision: the same
    track, bit for bit, as the default (off), through a loss (frames 8-11 blacked out: the bound
    grows with the frames missed) and the re-acquisition."""
    true_speed = np.linalg.norm(np.diff(seq.position, axis=0), axis=-1).max() * FPS
    assert true_speed < 10.0  # [m/s]
    frames = seq.frames.copy()
    frames[8:12] = 0
    base = track_box(frames, seq.intrinsics, EDGE, FPS)
    loose = dataclasses.replace(TrackConfig(), jump_speed_m_s=100.0)
    out = track_box(frames, seq.intrinsics, EDGE, FPS, loose)
    assert base.valid[:8].all() and base.valid[12:].any()  # acquired, lost, found again
    np.testing.assert_array_equal(out.valid, base.valid)
    np.testing.assert_array_equal(out.measured_position, base.measured_position)


def test_acquired_gates_equal_to_the_tracked_ones_change_nothing(seq):
    """``acquired_gates_px`` set to ``gates_px`` runs the search's fit through its own compiled
    re-location with the same gates: the same track, bit for bit, as the default (None), through
    a loss (frames 8-11 blacked out) and its re-acquisition by the search."""
    frames = seq.frames.copy()
    frames[8:12] = 0
    base = track_box(frames, seq.intrinsics, EDGE, FPS)
    same = dataclasses.replace(TrackConfig(), acquired_gates_px=TrackConfig().gates_px)
    out = track_box(frames, seq.intrinsics, EDGE, FPS, same)
    assert base.valid[:8].all() and base.valid[12:].any()  # acquired, lost, found again
    np.testing.assert_array_equal(out.valid, base.valid)
    np.testing.assert_array_equal(out.measured_position, base.measured_position)
    np.testing.assert_array_equal(out.causal_pose_rotation, base.causal_pose_rotation)


def test_no_box_visible_gives_invalid(seq):
    frames = np.zeros((6, 480, 640, 3), np.uint8)
    out = track_box(frames, seq.intrinsics, EDGE, FPS)
    assert not out.valid.any()
    assert np.all(np.isfinite(out.position))


def test_loss_of_track_is_detected_and_recovered(seq):
    frames = seq.frames.copy()
    frames[8:12] = 0  # camera blacked out for 4 frames
    out = track_box(frames, seq.intrinsics, EDGE, FPS)
    assert not out.valid[8:12].any()
    assert out.valid[14:].mean() >= 0.8
    err = np.linalg.norm(out.measured_position - seq.position, axis=-1)[14:][out.valid[14:]]
    assert np.median(err) < 0.02


def test_partial_occlusion_degrades_gracefully(seq):
    frames = seq.frames.copy()
    k = seq.intrinsics
    for i in range(6, 12):  # grey bar over the left half of the cube (a hand in front)
        u, v = (k[:2, :2] @ (seq.position[i, :2] / seq.position[i, 2]) + k[:2, 2]).astype(int)
        frames[i, v - 30 : v + 30, u - 30 : u] = 90
    out = track_box(frames, seq.intrinsics, EDGE, FPS)
    assert out.valid[14:].mean() >= 0.8
    good = out.valid
    err = np.linalg.norm(out.position - seq.position, axis=-1)[good]
    assert np.all(np.isfinite(out.position)) and np.median(err) < 0.02


def test_causal_outputs_and_timing(seq, track):
    """The causal path (per-frame fit + forward filter) is reported beside the smoothed track."""
    v = track.valid
    err = np.linalg.norm(track.causal_position - seq.position, axis=-1)[v]
    assert np.median(err) < 0.02
    assert track.information.shape == (len(v), 6, 6)
    assert np.all(np.isfinite(track.rotation)) and np.all(np.isfinite(track.causal_rotation))
    assert {"detection_ms", "estimation_ms", "smoothing_ms", "total_ms"} <= set(track.timing_ms)


# ---------------------------------------------------------------------------------------------
# The defaults are the tracker from before issue 24's checks: the outputs of ``track_box`` on
# stored frames of the project's scene, recorded from that code (main at 4416d0b,
# ``tests/data/make_tracker_reference.py`` -> ``tests/data/tracker_reference.npz``), reproduced.
# The checks are opt-in (``track.UNSEEN_SCENES``, ``SmootherConfig.max_gap_s``).

REFERENCE = Path(__file__).parent / "data" / "tracker_reference.npz"
# The outputs that recorded code gives on those frames on a CPU without AVX-512 (an AMD Zen 3,
# 2026-12-03, session 63; made with tests/data/tracker_reference_opencv5.patch applied to it).
# In the loop and plain cases the search from scratch picks another of its starts at frame 0
# there than on the AVX-512 CPUs the first reference was recorded on (Zen 4, Zen 5): other edge
# labels at frames 0-9, 18-21, 25 and 28, fits up to 7 mm apart, the smoothed box up to 6 mm.
# The stored segments are the same; the choice is an argmax over starts whose scores come out of
# XLA's arithmetic. That this follows the SIMD width is a hypothesis from the CPUs seen (Zen 3
# against Zen 4 and 5; no Intel AVX-512 machine was tried); the test picks by ``avx512f``. The
# ghost case's decisions are the same on both.
REFERENCE_AVX2 = Path(__file__).parent / "data" / "tracker_reference_avx2.npz"


def _has_avx512() -> bool:
    """Whether this (Linux x86) CPU has AVX-512 (``avx512f`` in ``/proc/cpuinfo``'s flags).
    Elsewhere (no such file, or no ``flags`` lines, as on ARM) neither recording was checked."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return True  # not Linux: the first reference, as before
    return any("avx512f" in line.split() for line in text.splitlines() if line.startswith("flags"))


# The same numbers up to the last bits of the float32 image stage (OpenCV's blur and segments),
# which differ between SIMD instruction sets: on an AMD Zen 5 CPU (AVX-512) the plain case's
# segments moved by 2e-7 px and its outputs by up to 2.7e-9 of their scale (causal rotation and
# acceleration; 2026-12-02, session 51), over the 1e-9 this was set to on the CPUs before. 1e-7
# (float32's resolution) leaves that a margin; a changed decision moves outputs by 1e-3 or more,
# and the decisions themselves (EXACT) must match exactly.
RTOL = 1e-7
EXACT = ("valid", "edge_ids", "hinge")
OFF = {  # the issue-24 settings and their off values
    "colour_background": False,
    "foreground_edges": False,
    "min_foreground": 0.0,
    "min_iou_acquire": 0.0,
    "min_inner_support": 0.0,
    "min_region_fraction": 0.0,
    "search_keep": 0,
    "blob_required": False,
    "low_contrast": False,
    "blob_core": 0.0,
    "faint_candidates": False,
    "batched_search": False,
    "stretch_points": False,
    "max_outside_foreground": None,
    "faint_masks": False,
    "lost_search_every": 1,
    "prior_segments": False,
    "min_foreground_tracked": None,
    "shadow_candidates": False,
    "faint_min_threshold": 6.0,
    "faint_segment_min_threshold": None,
    "shadow_faces": None,
    "blob_scales": (),
    "min_face_foreground": None,
    "min_face_foreground_tracked": None,
    "max_deep_shadow": None,
}


# The recorded tracker's smoother: plain Gauss-Newton steps, 10 of them, in the fixed-axis fit
# (the default since 2026-12-03 checks each step and runs to convergence, which moves the ghost
# case's smoothed outputs by up to 4e-7 of their scale and its axis by 1.3e-6: over RTOL)
RECORDED_SMOOTHER = SmootherConfig(hinge_step_check=False, hinge_iters=10)


@pytest.fixture(scope="module")
def ref():
    """The stored frames and the recorded code's outputs on them for this CPU's SIMD width."""
    with np.load(REFERENCE) as f:
        out = dict(f)
    if not _has_avx512():
        with np.load(REFERENCE_AVX2) as f:
            assert set(f) == {k for k in out if k.split("_")[0] in ("loop", "plain", "ghost")}
            out |= dict(f)
    return out


def _case(ref, case: str):
    """(frames, background, track config) of a recorded case: the loop's settings and its RGB
    background; every default (median background); a background with the cube in it. Each
    without ``depth_gate`` (2026-11-27), which the recorded tracker did not have: on the plain
    case it changes frames 27-31 (``test_depth_gate_on_the_recorded_frames``)."""
    frames = ref["frames"]
    cfg = {
        "loop": (frames, ref["background"], scene_tracker("void")),
        "plain": (frames, None, TrackConfig()),
        "ghost": (frames[:12], frames[3], TrackConfig()),
    }[case]
    return (*cfg[:2], dataclasses.replace(cfg[2], depth_gate=None))


def _differences(tr, ref, case: str) -> list[str]:
    """The fields of ``tr`` that differ from the recorded ones (all 18 but the timing)."""
    names = [k.removeprefix(f"{case}_") for k in ref if k.startswith(f"{case}_")]
    assert len(names) == 18, names
    out = []
    for name in names:
        got, want = np.asarray(getattr(tr, name)), ref[f"{case}_{name}"]
        if got.shape != want.shape:
            out.append(name)
        elif name in EXACT:
            out += [] if np.array_equal(got, want) else [name]
        else:
            scale = np.nanmax(np.abs(want)) if np.isfinite(want).any() else 1.0
            ok = np.allclose(got, want, rtol=RTOL, atol=RTOL * scale, equal_nan=True)
            out += [] if ok else [name]
    return out


def test_the_new_checks_are_off_by_default():
    for cfg in (TrackConfig(), scene_tracker("void"), CameraConfig.void_perfect().tracker):
        assert {name: getattr(cfg, name) for name in OFF} == OFF
    # the lab scene (the loop's default) turns on the checks of UNSEEN_SCENES but the region
    # fraction (in the loop the arm is the largest blob); the loop's impact settings stay
    lab = CameraConfig().tracker
    assert lab == dataclasses.replace(
        scene_tracker("void"), **{k: getattr(UNSEEN_SCENES, k) for k in LAB_CHECKS}
    )
    assert lab.min_region_fraction == 0 and lab.maneuver_nis == 16.3 and lab.stop_hypothesis
    assert CameraConfig(track=TrackConfig()).tracker == TrackConfig()  # a given tracker is kept
    assert SmootherConfig().max_gap_s is None and not SmootherConfig().split_at_restarts
    on = {name: getattr(UNSEEN_SCENES, name) for name in OFF}
    assert on == OFF | {
        "colour_background": True,
        "foreground_edges": True,
        "min_foreground": 0.5,
        "min_iou_acquire": 0.6,
        "min_inner_support": 0.05,
    }


@pytest.mark.parametrize(
    "case", [pytest.param("loop", marks=pytest.mark.slow), "plain", "ghost"]
)  # loop: its own compilation (~10 s on the 2 CI cores), with -m slow
def test_defaults_reproduce_the_recorded_tracker(ref, case):
    frames, background, cfg = _case(ref, case)
    tr = track_box(frames, ref["intrinsics"], EDGE, FPS, cfg, RECORDED_SMOOTHER, background)
    assert _differences(tr, ref, case) == []


def test_depth_gate_on_the_recorded_frames(ref):
    # independent truth: the rendered swing's cube centre. On the plain case (every default, a
    # median background) the search after the grey bar fits a wrong box 0.55 m off at frame 25
    # (with and without depth_gate: issue 24's business), and the filter starts from it. Without
    # depth_gate its gate then rejects the accurate fits of frames 29-31, and the filtered
    # position drifts 0.2-0.7 m away. With it (the default) the fits of frames 27-31 are taken,
    # the filter restarting at frame 27: the fits 32 mm (27) and 1-6 mm (28-31) off, and so is
    # the filtered position. Frames 0-26 are the same either way.
    truth = render_swing(0.5, 32, FPS).position
    frames, background, off = _case(ref, "plain")
    on = dataclasses.replace(off, depth_gate=TrackConfig().depth_gate)
    assert on.depth_gate == 0.1
    tr_off = track_box(frames, ref["intrinsics"], EDGE, FPS, off, background=background)
    tr_on = track_box(frames, ref["intrinsics"], EDGE, FPS, on, background=background)
    np.testing.assert_array_equal(tr_on.valid[:27], tr_off.valid[:27])
    np.testing.assert_array_equal(tr_on.causal_position[:27], tr_off.causal_position[:27])
    assert not tr_off.valid[29:].any() and tr_on.valid[27:].all()
    err_on = np.linalg.norm(tr_on.causal_position - truth, axis=1)
    err_off = np.linalg.norm(tr_off.causal_position - truth, axis=1)
    assert err_on[27] < 0.05 and np.all(err_on[28:] < 0.01), err_on[27:]
    assert np.all(err_off[29:] > 0.2), err_off[29:]


@pytest.mark.slow
@pytest.mark.parametrize(
    "case, track, smoother",
    [
        ("plain", {}, dataclasses.replace(RECORDED_SMOOTHER, max_gap_s=0.2)),
        ("ghost", {"foreground_edges": True}, RECORDED_SMOOTHER),
        ("ghost", {"min_iou_acquire": 0.6}, RECORDED_SMOOTHER),
        ("ghost", dataclasses.asdict(UNSEEN_SCENES), RECORDED_SMOOTHER),
    ],
    ids=["max_gap_s", "foreground_edges", "min_iou_acquire", "unseen_scenes"],
)
def test_the_reference_sees_the_new_checks(ref, case, track, smoother):
    """Not vacuous: with a check on, the same frames give other outputs. (On these frames the
    other checks alone change nothing: the cube is plain, lit and seen against black;
    ``test_the_new_checks_are_off_by_default`` pins them.)"""
    frames, background, cfg = _case(ref, case)
    cfg = dataclasses.replace(cfg, **track)
    tr = track_box(frames, ref["intrinsics"], EDGE, FPS, cfg, smoother, background)
    assert "position" in _differences(tr, ref, case)
