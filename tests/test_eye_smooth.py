"""Offline smoothing of pose sequences (:mod:`hec_jax.geometry.smooth`) against synthetic truth."""

import jax
import jax.numpy as jnp
import numpy as np

from hec_jax.geometry import filter as kf
from hec_jax.geometry import rotation_error_deg
from hec_jax.geometry.refine import so3_exp
from hec_jax.geometry.smooth import SmootherConfig, smooth_rotations, smooth_track

DT = 1 / 30


def _truth(t_n=60):
    t = np.arange(t_n) * DT
    pos = np.stack([0.1 * np.sin(3 * t), 0.05 * np.cos(3 * t), 1.5 + 0.0 * t], -1)
    vel = np.stack([0.3 * np.cos(3 * t), -0.15 * np.sin(3 * t), 0.0 * t], -1)
    w = np.stack([0.2 * np.sin(2 * t), 0.1 * t, 0.5 * np.sin(3 * t)], -1)  # smooth rotation vector
    rot = np.asarray(so3_exp(jnp.asarray(w)))
    return pos, vel, rot


def test_rts_smoother_beats_filter_on_constant_acceleration():
    fc = kf.FilterConfig(dt=DT, jerk_psd=1.0)
    t = np.arange(90) * DT
    acc = np.array([1.0, -2.0, 0.5])
    pos = 0.5 * acc * t[:, None] ** 2
    z = pos + np.random.default_rng(0).normal(scale=2e-3, size=pos.shape)
    covs = np.tile(4e-6 * np.eye(3), (90, 1, 1))
    filt, pred = jax.jit(lambda a, b, c: kf.filter_sequence(fc, a, b, c))(
        z, covs, np.ones(90, bool)
    )
    sm = kf.rts_smooth(fc, filt, pred)
    vel_true = acc * t[:, None]
    err_f = np.sqrt(np.mean((np.asarray(filt.mean[30:, 3:6]) - vel_true[30:]) ** 2))
    err_s = np.sqrt(np.mean((np.asarray(sm.mean[30:, 3:6]) - vel_true[30:]) ** 2))
    assert err_s < 0.6 * err_f, (err_s, err_f)
    np.testing.assert_allclose(np.asarray(sm.mean[45, 6:]), acc, atol=0.3)


def test_rotation_smoother_exact_without_noise_and_better_with_noise():
    cfg = SmootherConfig(angular_accel_psd=5.0)
    info = np.tile(np.diag([1e2, 1e2, 1e4]), (60, 1, 1))  # weak tilt, strong in-plane
    # constant angular velocity: the prior's second difference vanishes, so no bias
    r0 = np.asarray(so3_exp(jnp.array([0.3, -0.2, 0.1])))
    steps = np.arange(60)[:, None] * np.array([0.02, -0.01, 0.05])
    rot_cv = np.asarray(so3_exp(jnp.asarray(steps))) @ r0
    out = np.asarray(jax.jit(lambda r, i: smooth_rotations(r, i, DT, cfg))(rot_cv, info))
    assert np.max(rotation_error_deg(out, rot_cv)) < 1e-6
    _, _, rot = _truth()
    rng = np.random.default_rng(1)
    noise = rng.normal(size=(len(rot), 3)) * np.array([0.1, 0.1, 0.01])  # [rad], matches info
    meas = np.asarray(so3_exp(jnp.asarray(noise))) @ rot
    out = np.asarray(jax.jit(lambda r, i: smooth_rotations(r, i, DT, cfg))(meas, info))
    before = np.median(rotation_error_deg(meas, rot))
    after = np.median(rotation_error_deg(out, rot))
    assert after < 0.5 * before, (after, before)


def test_smooth_track_conditions_centre_on_rotation_and_bridges_gaps():
    pos, vel, rot = _truth(64)
    valid = np.ones(64, bool)
    valid[20:26] = False  # a gap
    # a tilt error w moves the fitted centre by c w (the coupling the information encodes)
    coupling = np.array([[0.0, 0.05, 0.0], [-0.05, 0.0, 0.0], [0.0, 0.0, 0.0]])  # [m/rad]
    rng = np.random.default_rng(2)
    w_err = rng.normal(size=(64, 3)) * np.array([0.05, 0.05, 0.002])
    meas_rot = np.asarray(so3_exp(jnp.asarray(w_err))) @ rot
    meas_pos = pos + w_err @ coupling.T + rng.normal(scale=2e-4, size=(64, 3))
    # information of (w, t) for t = c w + e, w ~ N(0, S_w), e ~ N(0, S_e): joint covariance
    s_w, s_e = np.diag([0.05, 0.05, 0.002]) ** 2, (2e-4) ** 2 * np.eye(3)
    cov = np.block([[s_w, s_w @ coupling.T], [coupling @ s_w, coupling @ s_w @ coupling.T + s_e]])
    info = np.tile(np.linalg.inv(cov), (64, 1, 1))
    out = smooth_track(meas_rot, meas_pos, info, valid, DT, SmootherConfig(info_scale=1.0))
    raw = np.sqrt(np.mean(np.sum((meas_pos - pos) ** 2, -1)[valid]))
    sm = np.sqrt(np.mean(np.sum((out.position - pos) ** 2, -1)))
    assert sm < 0.5 * raw, (sm, raw)
    assert np.all(np.isfinite(out.velocity)) and out.position.shape == (64, 3)
    assert np.sqrt(np.mean(np.sum((out.velocity - vel) ** 2, -1))) < 0.05
    assert not out.hinge  # a rotation about a moving axis: the fixed-axis model is rejected


def test_fixed_axis_model_recovers_a_pendulum():
    """A pendulum about a tilted axis through a pivot off the box, measured with a weak (3 deg)
    tilt and a tilt-coupled centre, as a nearly frontal face gives: the fixed-axis model is
    accepted and recovers the relative rotation and the centre far better than the free one."""
    t_n = 96
    t = np.arange(t_n) * DT
    axis = np.array([0.05, -0.03, 1.0]) / np.linalg.norm([0.05, -0.03, 1.0])
    theta = 0.5 * np.cos(4.0 * t)  # [rad]
    e = np.asarray(so3_exp(jnp.asarray(theta[:, None] * axis[None])))
    r0 = np.asarray(so3_exp(jnp.array([0.02, -0.03, 0.3])))
    pivot, arm = np.array([0.05, -0.45, 1.6]), np.array([0.0, 0.5, 0.0])  # [m]
    rot, pos = e @ r0, pivot + e @ arm
    rng = np.random.default_rng(3)
    s_w = np.diag([0.05, 0.05, 0.002]) ** 2  # tilt 3 deg, in-plane 0.1 deg [rad^2]
    coupling = np.array([[0.0, 0.05, 0.0], [-0.05, 0.0, 0.0], [0.0, 0.0, 0.0]])  # [m/rad]
    s_e = (1e-3) ** 2 * np.eye(3)
    cov = np.block([[s_w, s_w @ coupling.T], [coupling @ s_w, coupling @ s_w @ coupling.T + s_e]])
    err = rng.multivariate_normal(np.zeros(6), cov, size=t_n)
    meas_rot = np.asarray(so3_exp(jnp.asarray(err[:, :3]))) @ rot
    meas_pos = pos + err[:, 3:]
    info = np.tile(np.linalg.inv(cov), (t_n, 1, 1))
    valid = np.ones(t_n, bool)
    args = (meas_rot, meas_pos, info, valid, DT)
    free = smooth_track(*args, SmootherConfig(info_scale=1.0, hinge=False))
    out = smooth_track(*args, SmootherConfig(info_scale=1.0, hinge_max_cost=12.6))  # chi2(6) 95%
    assert out.hinge and not free.hinge
    assert np.degrees(np.arccos(abs(out.hinge_axis @ axis))) < 1.0
    phi = rot @ rot[0].T

    def rel_err(r):
        return np.median(rotation_error_deg(r @ r[0].T, phi))

    assert rel_err(out.rotation) < 0.5 and rel_err(out.rotation) < 0.3 * rel_err(free.rotation)
    pos_err = np.sqrt(np.mean(np.sum((out.position - pos) ** 2, -1)))
    free_err = np.sqrt(np.mean(np.sum((free.position - pos) ** 2, -1)))
    assert pos_err < 0.7 * free_err, (pos_err, free_err)


def test_smooth_track_too_few_frames_is_identity():
    _, _, rot = _truth(8)
    valid = np.zeros(8, bool)
    valid[:2] = True
    pos = np.ones((8, 3))
    out = smooth_track(rot, pos, np.tile(np.eye(6), (8, 1, 1)), valid, DT)
    np.testing.assert_allclose(out.rotation, rot)
    assert np.all(out.velocity == 0)
