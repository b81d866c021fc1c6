"""The guarded backward extension (:mod:`hec_jax.geometry.backward`): on synthetic pendulum fits
with a stand-in tracker (which frames it fills, what the guard drops), and through ``track_box``
on rendered frames with a black-out, against the rendered truth."""

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

from hec_jax.geometry.backward import BackwardFit, Fits, guarded_backward_fill
from hec_jax.geometry.refine import so3_exp
from hec_jax.geometry.smooth import NO_EXTRAPOLATION, SmootherConfig, smooth_track
from hec_jax.geometry.track import BoxTracker, TrackConfig, track_box
from hec_jax.mjx_scene.render import render_swing

DT = 1 / 30
T_N = 90
# unscaled information: chi2(6) costs, 95% at 12.6 (tests/test_eye_smooth.py's settings)
CFG = SmootherConfig(
    info_scale=1.0,
    hinge_max_cost=12.6,
    max_gap_s=0.2,
    hinge_robust_scale=6.0,
    hinge_whole_track=True,
)


def _pendulum(seed):
    """A pendulum about a tilted axis: truth (rotation, centre) and a sampler of noisy fits with
    their information (a nearly frontal face: depth and in-plane rotation well measured)."""
    t = np.arange(T_N) * DT
    axis = np.array([0.1, 0.05, 1.0]) / np.linalg.norm([0.1, 0.05, 1.0])
    theta = 0.6 * np.cos(3.5 * t)  # [rad]
    e = np.asarray(so3_exp(jnp.asarray(theta[:, None] * axis[None])))
    r0 = np.asarray(so3_exp(jnp.array([0.1, -0.2, 0.3])))
    pivot, arm = np.array([-0.1, -0.5, 2.0]), np.array([0.0, 0.55, 0.05])  # [m]
    rot, pos = e @ r0, pivot + e @ arm
    s_w = np.diag([0.03, 0.03, 0.003]) ** 2  # [rad^2]
    coupling = np.array([[0.0, 0.05, 0.0], [-0.05, 0.0, 0.0], [0.0, 0.0, 0.0]])  # [m/rad]
    cov = np.block([[s_w, s_w @ coupling.T], [coupling @ s_w, coupling @ s_w @ coupling.T]])
    cov[3:, 3:] += (3e-3) ** 2 * np.eye(3)
    err = np.random.default_rng(seed).multivariate_normal(np.zeros(6), cov, size=(2, T_N))
    # two independent draws: the forward tracker's fits and the backward tracker's
    meas_rot = np.asarray(so3_exp(jnp.asarray(err[..., :3]))) @ rot
    meas_pos = pos + err[..., 3:]
    info = np.tile(np.linalg.inv(cov), (T_N, 1, 1))
    return rot, pos, meas_rot, meas_pos, info


def _forward(seed, invalid, restarted=()):
    rot, pos, meas_rot, meas_pos, info = _pendulum(seed)
    valid = np.ones(T_N, bool)
    valid[list(invalid)] = False
    restarts = np.zeros(T_N, bool)
    restarts[list(restarted)] = True
    fits = Fits(valid, meas_rot[0], np.where(valid[:, None], meas_pos[0], np.nan), info, restarts)
    return fits, (rot, pos, meas_rot[1], meas_pos[1], info)


class StandIn:
    """A backward tracker on synthetic fits: the box is found at ``visible`` frames (the second
    noise draw, or a fit ``deeper_m`` deeper along the line of sight at ``wrong`` frames) and
    lost elsewhere; records the segments it was started on."""

    def __init__(self, backward, visible, wrong=(), deeper_m=0.15):
        self.rot, self.pos, self.info = backward[2], backward[3].copy(), backward[4]
        for t in wrong:
            self.pos[t] *= 1.0 + deeper_m / np.linalg.norm(self.pos[t])
        self.visible = set(visible)
        self.started = []

    def __call__(self, start, end, state):
        self.started.append(start)
        for t in range(start - 1, -1, -1):
            found = t in self.visible
            yield BackwardFit(found, self.rot[t], self.pos[t] if found else np.nan, self.info[t])


def test_fills_the_visible_frames_before_each_modelled_segment():
    """Acquired at frame 6, lost over 30-49, re-acquired at 50, the box visible again from
    frame 42: the pass fills 0-5 and 42-49, nothing in the black-out 30-41, keeps every forward
    fit bit for bit, moves the restart flags to each extension's first frame, and the filled
    frames' smoothed centres are the model's (within 1 cm of the truth, as the forward frames)."""
    fits, backward = _forward(11, [*range(6), *range(30, 50)], restarted=(6, 50))
    truth_pos = backward[1]
    stand_in = StandIn(backward, visible=[*range(6), *range(42, 50)])
    out = guarded_backward_fill(fits, DT, CFG, stand_in)
    assert stand_in.started == [6, 50]
    expected = np.zeros(T_N, bool)
    expected[[*range(6), *range(42, 50)]] = True
    np.testing.assert_array_equal(out.filled, expected)
    assert out.dropped == 0 and out.tried == 6 + 9  # 6 found before frame 6; 8 found, 1 lost
    np.testing.assert_array_equal(out.fits.valid, fits.valid | expected)
    v = fits.valid
    np.testing.assert_array_equal(out.fits.position[v], fits.position[v])
    np.testing.assert_array_equal(out.fits.pose_rotation[v], fits.pose_rotation[v])
    np.testing.assert_array_equal(np.flatnonzero(out.fits.restarted), [0, 42])
    assert out.first.hinge and out.smoothed.hinge
    err = np.linalg.norm(out.smoothed.position - truth_pos, axis=-1)
    assert np.max(err[out.fits.valid]) < 0.01, err


def test_the_guard_drops_filled_frames_the_model_rejects():
    """The backward tracker finds a twin 15 cm deep on frames 42-44 (a wrong lock at the edge
    of the black-out) and the box on 45-49: the second smoothing counts 42-44 as outliers, so
    they are dropped and the track smoothed once more with 45-49 alone."""
    fits, backward = _forward(12, range(30, 50), restarted=(50,))
    stand_in = StandIn(backward, visible=range(42, 50), wrong=range(42, 45))
    out = guarded_backward_fill(fits, DT, CFG, stand_in)
    expected = np.zeros(T_N, bool)
    expected[45:50] = True
    np.testing.assert_array_equal(out.filled, expected)
    assert out.dropped == 3
    np.testing.assert_array_equal(out.fits.valid, fits.valid | expected)
    np.testing.assert_array_equal(np.flatnonzero(out.fits.restarted), [45])
    err = np.linalg.norm(out.smoothed.position - backward[1], axis=-1)
    assert np.max(err[out.fits.valid]) < 0.01, err
    # the smoothing returned is that of the kept fits
    again = smooth_track(
        out.fits.pose_rotation,
        out.fits.position,
        out.fits.information,
        out.fits.valid,
        DT,
        CFG,
        out.fits.restarted,
    )
    np.testing.assert_array_equal(out.smoothed.position, again.position)


def test_the_guard_drops_filled_fits_the_jump_test_rejected():
    """With the jump test on (``max_speed_m_s``, as the benchmark's smoother), a wrong lock
    60 cm deep on the two frames before the box is found again (42-43) is cut off by jumps and
    left out of the smoothing: it counts as no inlier of the model, so it is dropped."""
    fits, backward = _forward(15, range(30, 50), restarted=(50,))
    stand_in = StandIn(backward, visible=range(42, 50), wrong=(42, 43), deeper_m=0.6)
    cfg = dataclasses.replace(CFG, max_speed_m_s=2.0)  # the swing's top speed is 1.2 m/s
    out = guarded_backward_fill(fits, DT, cfg, stand_in)
    np.testing.assert_array_equal(np.flatnonzero(out.filled), range(44, 50))
    assert out.dropped == 2


def test_reverse_time_runs_the_filter_backward():
    """After ``reverse_time`` the tracker's prediction one frame on is the state one frame
    earlier in forward time: centre p - v dt + a dt^2 / 2, velocity -(v - a dt), and the
    rotation turned back by the last frame's turn; its centre covariance is
    P_pp - dt (P_pv + P_vp) + dt^2 P_vv plus the filter's own noise (the cross-covariance's sign
    flipped with the velocity)."""
    seq = render_swing(0.3, 4, 1 / DT)
    tracker = BoxTracker(seq.intrinsics, 0.1, 1 / DT)
    z = np.zeros(3)
    with pytest.raises(ValueError, match="last processed frame was valid"):
        tracker.reverse_time(z, z, z, np.eye(9), np.eye(3))
    for frame in seq.frames:
        step = tracker.update(frame)
    assert step.valid
    snap = tracker.snapshot()
    p, v, acc = np.array([0.1, -0.2, 1.5]), np.array([0.4, 0.1, -0.3]), np.array([1.0, -2.0, 0.5])
    rot = np.asarray(so3_exp(jnp.array([0.2, 0.1, -0.3])))
    turn = np.asarray(so3_exp(jnp.array([0.0, 0.05, 0.02])))  # R(t+1) = turn R(t)
    cross = np.diag([2e-5, -1e-5, 3e-5])  # [m^2/s]
    cov = np.zeros((9, 9))
    cov[:3, :3], cov[3:6, 3:6] = 1e-4 * np.eye(3), 4e-4 * np.eye(3)
    cov[:3, 3:6], cov[3:6, :3] = cross, cross
    tracker.reverse_time(p, v, acc, np.zeros((9, 9)), rot, turn @ rot)
    noise = tracker.predict(DT).position_cov  # the filter's own, from a certain state
    tracker.restore(snap)
    tracker.reverse_time(p, v, acc, cov, rot, turn @ rot)
    now, back = tracker.predict(0.0), tracker.predict(DT)
    np.testing.assert_allclose(now.position, p)
    np.testing.assert_allclose(now.velocity, -v)
    np.testing.assert_allclose(back.position, p - v * DT + 0.5 * acc * DT**2, atol=1e-12)
    np.testing.assert_allclose(back.velocity, -(v - acc * DT), atol=1e-12)
    np.testing.assert_allclose(back.acceleration, acc)
    np.testing.assert_allclose(back.pose_rotation, turn.T @ rot, atol=1e-12)
    expected = 1e-4 * np.eye(3) - 2 * DT * cross + DT**2 * 4e-4 * np.eye(3) + noise
    np.testing.assert_allclose(back.position_cov, expected, rtol=1e-9, atol=1e-15)
    with pytest.raises(ValueError, match="finite"):
        tracker.reverse_time(p, v, acc, cov, rot, np.full((3, 3), np.nan))
    with pytest.raises(ValueError, match="covariance"):
        tracker.reverse_time(p, v, acc, np.eye(6), rot)


def test_a_segment_the_model_does_not_explain_is_not_extended():
    """A segment after a loss whose fits are all 15 cm deeper (a twin held, as in
    tests/test_eye_smooth.py): the accepted model leaves it its own state, so the pass does not
    start a tracker there; the segment it explains is extended."""
    fits, backward = _forward(8, [*range(4), *range(60, 70)])
    pos = fits.position.copy()
    pos[70:] *= 1.0 + 0.15 / np.linalg.norm(pos[70:], axis=-1, keepdims=True)
    fits = fits._replace(position=pos)
    stand_in = StandIn(backward, visible=range(T_N))
    out = guarded_backward_fill(fits, DT, CFG, stand_in)
    assert out.first.hinge and out.first.hinge_modelled[4] and not out.first.hinge_modelled[70]
    assert stand_in.started == [4]
    np.testing.assert_array_equal(np.flatnonzero(out.filled), range(4))


@pytest.mark.parametrize("cfg", [dataclasses.replace(CFG, hinge_whole_track=False), CFG])
def test_without_an_accepted_model_nothing_changes(cfg):
    """No whole-track model (off, or the fits a rotation about a moving axis it rejects): no
    tracker is started and the forward fits and their smoothing come back unchanged."""
    fits, backward = _forward(13, range(30, 50))
    if cfg.hinge_whole_track:  # an extra spin the fixed-axis model cannot explain
        spin = np.asarray(so3_exp(jnp.asarray(np.arange(T_N)[:, None] * [0.0, 0.0, 0.05])))
        fits = fits._replace(pose_rotation=spin @ fits.pose_rotation)
    stand_in = StandIn(backward, visible=range(T_N))
    out = guarded_backward_fill(fits, DT, cfg, stand_in)
    assert not out.first.hinge_modelled.any()
    assert stand_in.started == [] and not out.filled.any() and out.tried == 0
    assert out.fits is fits and out.smoothed is out.first


def test_mismatched_fits_raise():
    fits, backward = _forward(14, range(30, 40))
    with pytest.raises(ValueError, match="position"):
        guarded_backward_fill(
            fits._replace(position=fits.position[:-1]), DT, CFG, StandIn(backward, [])
        )


@pytest.fixture(scope="module")
def blacked_out():
    """A rendered swing (release 0.5 rad, 3 s) blacked out on frames 40-45, tracked with a search
    from scratch only every 8th frame once lost: the forward pass misses frames where the cube
    is plainly visible (before its first search lands, and after the black-out)."""
    seq = render_swing(0.5, T_N, 1 / DT)
    frames = seq.frames.copy()
    frames[40:46] = 0
    cfg = TrackConfig(lost_search_every=8, lost_search_after=0)
    runs = {
        eb: track_box(
            frames,
            seq.intrinsics,
            0.1,
            1 / DT,
            cfg,
            dataclasses.replace(NO_EXTRAPOLATION, extend_backward=eb),
        )
        for eb in (False, True)
    }
    return seq, runs


def test_track_box_fills_visible_frames_the_forward_pass_missed(blacked_out):
    seq, runs = blacked_out
    off, on = runs[False], runs[True]
    np.testing.assert_array_equal(off.offline_valid, off.valid)
    assert not off.backward_filled.any() and off.timing_ms["backward_ms"] == 0.0
    # the causal outputs are the forward tracker's either way
    np.testing.assert_array_equal(on.valid, off.valid)
    np.testing.assert_array_equal(on.causal_position, off.causal_position)
    missed = ~off.valid
    missed[40:46] = False  # the black-out: nothing to see
    assert missed.sum() >= 5, "the set-up should leave visible frames to the backward pass"
    assert not on.backward_filled[40:46].any()
    assert not (on.backward_filled & on.valid).any()
    np.testing.assert_array_equal(on.offline_valid, on.valid | on.backward_filled)
    assert on.backward_filled[missed].mean() >= 0.8
    err = np.linalg.norm(on.position - seq.position, axis=-1)
    assert np.max(err[on.offline_valid]) < 0.005, err  # 5 mm at 1 m: the 3 mm/m median
    assert on.timing_ms["backward_ms"] > 0.0


def test_backward_ms_counts_the_snapshots_the_pass_restores(blacked_out, monkeypatch):
    """The per-frame snapshots taken for the backward pass are its cost: in ``backward_ms`` and
    ``smoothing_ms`` (a snapshot made 2 ms slower shows there), none taken without the pass."""
    import time

    seq, _ = blacked_out
    real, taken = BoxTracker.snapshot, []

    def slow(self):
        time.sleep(0.002)
        taken.append(1)
        return real(self)

    monkeypatch.setattr(BoxTracker, "snapshot", slow)
    runs = {
        eb: track_box(
            seq.frames[:8],
            seq.intrinsics,
            0.1,
            1 / DT,
            TrackConfig(),
            dataclasses.replace(NO_EXTRAPOLATION, extend_backward=eb),
        )
        for eb in (False, True)
    }
    assert len(taken) == 8  # only with the pass, one a frame
    assert runs[False].timing_ms["backward_ms"] == 0.0
    on = runs[True].timing_ms
    assert on["backward_ms"] >= 2.0 and on["smoothing_ms"] >= on["backward_ms"]
