"""Tracking on rendered frames of the swinging cube (rendered once per module, 24 frames)."""

import numpy as np
import pytest

from hec_jax.geometry import rotation_error_deg
from hec_jax.geometry.track import track_box
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
