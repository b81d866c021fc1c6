"""Offline smoothing of pose sequences (:mod:`hec_jax.geometry.smooth`) against synthetic truth."""

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hec_jax.geometry import filter as kf
from hec_jax.geometry import rotation_error_deg
from hec_jax.geometry import smooth as smooth_mod
from hec_jax.geometry.box_model import cube_symmetries, nearest_labellings, snap_to_symmetry
from hec_jax.geometry.refine import so3_exp
from hec_jax.geometry.smooth import (
    NO_EXTRAPOLATION,
    SmootherConfig,
    smooth_rotations,
    smooth_track,
)

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


def _pendulum(t_n=60, seed=4):
    """A pendulum about a tilted axis measured as a nearly frontal face gives (the information
    of :func:`test_fixed_axis_model_recovers_a_pendulum`); returns truth and measurements."""
    t = np.arange(t_n) * DT
    axis = np.array([0.1, 0.05, 1.0]) / np.linalg.norm([0.1, 0.05, 1.0])
    theta = 0.6 * np.cos(3.5 * t)  # [rad]
    theta_dot = -0.6 * 3.5 * np.sin(3.5 * t)  # [rad/s]
    e = np.asarray(so3_exp(jnp.asarray(theta[:, None] * axis[None])))
    r0 = np.asarray(so3_exp(jnp.array([0.1, -0.2, 0.3])))
    pivot, arm = np.array([-0.1, -0.5, 2.0]), np.array([0.0, 0.55, 0.05])  # [m]
    rot, pos = e @ r0, pivot + e @ arm
    vel = theta_dot[:, None] * np.cross(axis, pos - pivot)
    s_w = np.diag([0.03, 0.03, 0.003]) ** 2  # [rad^2]
    coupling = np.array([[0.0, 0.05, 0.0], [-0.05, 0.0, 0.0], [0.0, 0.0, 0.0]])  # [m/rad]
    cov = np.block([[s_w, s_w @ coupling.T], [coupling @ s_w, coupling @ s_w @ coupling.T]])
    cov[3:, 3:] += (3e-3) ** 2 * np.eye(3)
    err = np.random.default_rng(seed).multivariate_normal(np.zeros(6), cov, size=t_n)
    meas_rot = np.asarray(so3_exp(jnp.asarray(err[:, :3]))) @ rot
    meas_pos = pos + err[:, 3:]
    info = np.tile(np.linalg.inv(cov), (t_n, 1, 1))
    return (rot, pos, vel, axis), (meas_rot, meas_pos, info)


def test_whole_track_hinge_ignores_wrong_fits_and_bridges_a_long_gap():
    """Robust whole-track fixed-axis fit (module docstring, 4.): a pendulum tracked with a wrong
    lock (frames 0-3: the centre 1 m off, the box turned 90 deg), a loss of 12 frames (a gap over
    ``max_gap_s``, so two segments) and two Necker-like fits 15 cm deep. Exactly the wrong fits
    are flagged; the other frames are within 1 cm, their velocity RMS under 6 cm/s, the flagged
    ones (the model's state, extrapolated over the first 4 frames) within 6 cm. The per-segment
    smoother and an unweighted whole-track fit (rejected) are off by up to 1 m. (Bounds: seeds
    5-19 of the noise gave at most 6 mm, 3.9 cm/s and 5.2 cm; the per-segment velocity RMS
    1.3 m/s.)"""
    (rot, pos, vel, axis), (meas_rot, meas_pos, info) = _pendulum(seed=5)
    meas_pos, meas_rot = meas_pos.copy(), meas_rot.copy()
    valid = np.ones(len(pos), bool)
    valid[20:32] = False  # lost for 0.4 s
    wrong = np.zeros(len(pos), bool)
    wrong[:4] = True
    meas_pos[:4] += np.array([0.6, -0.5, 0.6])  # [m], a wrong lock before the first loss
    meas_rot[:4] = np.asarray(so3_exp(jnp.array([np.pi / 2, 0.0, 0.0]))) @ meas_rot[:4]
    for i in (40, 41):  # a twin along the line of sight
        wrong[i] = True
        meas_pos[i] *= 1.0 + 0.15 / np.linalg.norm(meas_pos[i])
    args = (meas_rot, meas_pos, info, valid, DT)
    # unscaled information: chi2(6) costs, 95% at 12.6; c0 its mean (an inlier has c < 54)
    base = SmootherConfig(
        info_scale=1.0, hinge_max_cost=12.6, max_gap_s=0.2, hinge_robust_scale=6.0
    )
    robust = smooth_track(*args, dataclasses.replace(base, hinge_whole_track=True))
    per_segment = smooth_track(*args, base)
    unweighted = smooth_track(
        *args, dataclasses.replace(base, hinge_whole_track=True, hinge_robust_scale=1e12)
    )
    assert robust.hinge and not unweighted.hinge
    np.testing.assert_array_equal(robust.hinge_outlier, wrong)
    assert np.degrees(np.arccos(abs(robust.hinge_axis @ axis))) < 1.0
    pos_err = np.linalg.norm(robust.position - pos, axis=-1)
    vel_err = np.linalg.norm(robust.velocity - vel, axis=-1)
    assert np.max(pos_err[valid & ~wrong]) < 0.01, pos_err
    assert np.sqrt(np.mean(vel_err[valid & ~wrong] ** 2)) < 0.06, vel_err  # |v| up to 1.2 m/s
    assert np.max(pos_err[wrong]) < 0.06, pos_err
    for other in (per_segment, unweighted):
        assert np.max(np.linalg.norm(other.position - pos, axis=-1)[valid]) > 0.5
        other_vel = np.linalg.norm(other.velocity - vel, axis=-1)[valid & ~wrong]
        assert np.sqrt(np.mean(other_vel**2)) > 0.3
    # frames in the long gap hold the nearest segment end: nothing extrapolated across it
    np.testing.assert_array_equal(robust.position[20:26], np.tile(robust.position[19], (6, 1)))
    np.testing.assert_array_equal(robust.velocity[20:32], 0.0)


def test_whole_track_hinge_leaves_a_segment_it_disagrees_with():
    """A segment after a long gap whose fits are all 15 cm deeper (a twin held for 10 frames):
    the whole-track model is accepted on the rest, but that segment keeps the per-segment
    smoother's state bit for bit (the model's would be carried across the gap), unflagged."""
    (_, pos, _, _), (meas_rot, meas_pos, info) = _pendulum(seed=8)
    meas_pos = meas_pos.copy()
    valid = np.ones(len(pos), bool)
    valid[40:50] = False
    meas_pos[50:] *= 1.0 + 0.15 / np.linalg.norm(meas_pos[50:], axis=-1, keepdims=True)
    base = SmootherConfig(
        info_scale=1.0, hinge_max_cost=12.6, max_gap_s=0.2, hinge_robust_scale=6.0
    )
    args = (meas_rot, meas_pos, info, valid, DT)
    robust = smooth_track(*args, dataclasses.replace(base, hinge_whole_track=True))
    per_segment = smooth_track(*args, base)
    assert robust.hinge and not robust.hinge_outlier.any()
    for name in ("rotation", "position", "velocity", "acceleration"):
        np.testing.assert_array_equal(getattr(robust, name)[50:], getattr(per_segment, name)[50:])
    assert np.max(np.linalg.norm(robust.position[:40] - pos[:40], axis=-1)) < 0.01


def test_whole_track_hinge_rejects_motion_about_a_moving_axis():
    """On a rotation about a moving axis the whole-track model is rejected and the result is
    the per-segment smoother's, bit for bit."""
    pos, _, rot = _truth(64)
    rng = np.random.default_rng(6)
    meas_rot = np.asarray(so3_exp(jnp.asarray(rng.normal(size=(64, 3)) * 0.01))) @ rot
    meas_pos = pos + rng.normal(scale=2e-3, size=(64, 3))
    info = np.tile(np.diag([1e4, 1e4, 1e4, 2.5e5, 2.5e5, 2.5e5]), (64, 1, 1))
    valid = np.ones(64, bool)
    valid[30:40] = False
    cfg = SmootherConfig(info_scale=1.0, hinge_max_cost=12.6, max_gap_s=0.2)
    args = (meas_rot, meas_pos, info, valid, DT)
    whole = smooth_track(*args, dataclasses.replace(cfg, hinge_whole_track=True))
    plain = smooth_track(*args, cfg)
    assert not whole.hinge and not whole.hinge_outlier.any()
    for name in ("rotation", "position", "velocity", "acceleration"):
        np.testing.assert_array_equal(getattr(whole, name), getattr(plain, name))


def test_whole_track_hinge_velocity_is_the_model_s():
    """Noise-free pendulum: the model's velocity and acceleration are the analytic ones (to the
    central differences' error), and the fit is jittable and vmappable over sequences."""
    (rot, pos, vel, axis), (_, _, info) = _pendulum(t_n=64)
    valid = np.ones(64, bool)
    cfg = SmootherConfig(info_scale=1.0, hinge_max_cost=12.6, hinge_whole_track=True)
    fit = jax.jit(
        jax.vmap(
            lambda r, p, i, v: smooth_mod.fit_hinge_robust(r, p, i, v, r, p, DT, cfg),
        )
    )(*(np.stack([x, x]) for x in (rot, pos, info, valid)))
    assert np.all(np.asarray(fit.accepted))
    v_err = np.max(np.linalg.norm(np.asarray(fit.velocity[0]) - vel, axis=-1)[1:-1])
    assert v_err < 0.01, v_err  # |v| up to 1.2 m/s; central differences at 30 fps
    t = np.arange(64) * DT
    theta_ddot = -0.6 * 3.5**2 * np.cos(3.5 * t)
    theta_dot = -0.6 * 3.5 * np.sin(3.5 * t)
    arm = pos - np.asarray(fit.fit.pivot[0])
    acc = theta_ddot[:, None] * np.cross(axis, arm) + theta_dot[:, None] ** 2 * np.cross(
        axis, np.cross(axis, arm)
    )
    a_err = np.max(np.linalg.norm(np.asarray(fit.acceleration[0]) - acc, axis=-1)[2:-2])
    assert a_err < 0.1, a_err  # |a| up to 4.5 m/s^2


def _hinge_objective(fit, cfg) -> float:
    """:func:`smooth_mod.fit_hinge`'s objective, recomputed from its outputs: the frames'
    normalised squared residuals plus the angle's second differences over their prior sigma."""
    sigma = np.sqrt(2.0 / 3.0 * cfg.angular_accel_psd * DT**3)
    second = np.diff(np.asarray(fit.angle), 2) / sigma
    return float(np.nansum(np.asarray(fit.frame_cost)) + np.sum(second**2))


def test_hinge_step_check_never_raises_the_objective_where_plain_steps_do():
    """A fixed-axis fit started on a wrong lock (frames 0-3 1 m off and turned 90 deg, the
    information unweighted, as the robust fit's first pass sees it), 10 iterations each. Plain
    Gauss-Newton steps raise the objective (on this seed by 27% at iteration 4, to 6.3 times its
    lowest by iteration 7, ending at 0.94e6), so where they end depends on the iteration count;
    with ``hinge_step_check`` it never rises, not even in the last bit (ending at 0.33e6). The
    reported objective trace ends at the objective recomputed from the fit's outputs. From a good start both take the
    same steps to the same fit."""
    (rot, pos, _, _), (meas_rot, meas_pos, info) = _pendulum(seed=8)
    meas_pos, meas_rot = meas_pos.copy(), meas_rot.copy()
    meas_pos[:4] += np.array([0.6, -0.5, 0.6])  # [m]
    meas_rot[:4] = np.asarray(so3_exp(jnp.array([np.pi / 2, 0.0, 0.0]))) @ meas_rot[:4]
    valid = np.ones(len(pos), bool)

    configs = {
        c: SmootherConfig(info_scale=1.0, hinge_step_check=c, hinge_iters=10) for c in (0, 1)
    }
    fits = {  # one compilation per rule
        c: jax.jit(
            lambda r, p, i, v, r0, p0, cfg=cfg: smooth_mod.fit_hinge(r, p, i, v, r0, p0, DT, cfg)
        )
        for c, cfg in configs.items()
    }

    def fit(meas_rot, meas_pos, start_rot, start_pos, check):
        out = fits[int(check)](meas_rot, meas_pos, info, valid, start_rot, start_pos)
        return out, configs[int(check)]

    traces = {}
    for check in (False, True):
        out, cfg = fit(meas_rot, meas_pos, meas_rot, meas_pos, check)
        traces[check] = np.asarray(out.objective)
        assert traces[check].shape == (cfg.hinge_iters + 1,)
        np.testing.assert_allclose(traces[check][-1], _hinge_objective(out, cfg), rtol=1e-12)
    plain, checked = traces[False], traces[True]
    # the checked fit carries the accepted trial's objective: its trace never rises, not by a bit
    assert np.all(np.diff(checked) <= 0.0), checked
    assert np.any(np.diff(plain) > 0.05 * plain[:-1]), plain  # the failure the check removes
    assert checked[-1] < plain[-1], (checked, plain)
    # no wrong lock, started at the truth: each step lowers the objective (to round-off once
    # converged), and the two fits agree
    (_, _, _, _), (clean_rot, clean_pos, _) = _pendulum(seed=8)
    good = [fit(clean_rot, clean_pos, rot, pos, check)[0] for check in (False, True)]
    assert np.all(np.diff(good[0].objective) <= 1e-12 * good[0].objective[:-1])  # round-off
    np.testing.assert_allclose(good[1].objective, good[0].objective, rtol=1e-9)
    np.testing.assert_allclose(good[1].position, good[0].position, rtol=0, atol=1e-9)
    np.testing.assert_allclose(good[1].rotation, good[0].rotation, rtol=0, atol=1e-9)


def test_smooth_track_is_float64_without_x64():
    """With ``jax_enable_x64`` off the smoother still computes in float64: the same outputs, and
    the fixed-axis model is not lost (in float32 its fit can return NaN)."""
    (_, _, _, _), (meas_rot, meas_pos, info) = _pendulum(t_n=50, seed=7)
    valid = np.ones(50, bool)
    valid[25:35] = False
    cfg = SmootherConfig(
        info_scale=1.0,
        hinge_max_cost=12.6,
        max_gap_s=0.2,
        hinge_whole_track=True,
        hinge_robust_scale=6.0,
    )
    args = (meas_rot, meas_pos, info, valid, DT, cfg)
    ref = smooth_track(*args)
    with jax.enable_x64(False):
        out = smooth_track(*args)
        assert not jax.config.jax_enable_x64  # the caller's setting is left as it was
    assert ref.hinge and out.hinge
    for name in ("rotation", "position", "velocity", "acceleration"):
        np.testing.assert_allclose(getattr(out, name), getattr(ref, name), rtol=0, atol=1e-12)


def test_fits_with_an_unmeasured_depth_leave_the_smoothed_track_finite():
    """Recorded per-frame fits of a faint cube (development seed 355, the tracker with
    ``lsd_contrast`` 40, ``tests/data/smoother_singular_depth.npz``): frames 9, 11 and 21 are
    valid with a singular centre information along the line of sight (their points on too few
    edges). Their plain inverses overflowed and the rotation pass, one fit over every frame,
    turned the whole sequence to NaN while it stayed valid. Their depth is now unknown to the
    smoother, which takes it from the neighbours."""
    d = np.load(Path(__file__).parent / "data" / "smoother_singular_depth.npz")
    info = d["information"]
    ltt = info[:, 3:, 3:]
    evals = np.linalg.eigvalsh(0.5 * (ltt + np.swapaxes(ltt, -1, -2)))
    singular = evals[:, 0] < smooth_mod.SINGULAR_TT * evals[:, -1]
    np.testing.assert_array_equal(np.flatnonzero(singular), [9, 11, 21])
    out = smooth_track(
        d["rotation"], d["position"], info, d["valid"], DT, NO_EXTRAPOLATION, d["restarts"]
    )
    assert np.all(np.isfinite(out.position)) and np.all(np.isfinite(out.rotation))
    err = np.linalg.norm(out.position - d["truth_position"], axis=-1)
    measured = np.linalg.norm(d["position"] - d["truth_position"], axis=-1)
    assert np.median(err) <= np.median(measured), (np.median(err), np.median(measured))
    assert np.max(err) < 0.05  # no frame taken more than 5 cm off (the fits: up to 17 cm)
    # the well-conditioned frames keep the plain inverse, as before the floor
    scaled = jnp.asarray(NO_EXTRAPOLATION.info_scale * info[~singular])
    _, ltt_inv, _ = jax.vmap(smooth_mod._split)(scaled)
    np.testing.assert_array_equal(
        np.asarray(ltt_inv),
        np.asarray(jax.vmap(_plain_inverse)(scaled)),
    )


def _plain_inverse(info):
    """Lambda_tt^-1 as ``smooth._split`` computed it for every frame before the floor."""
    a = jnp.linalg.inv(info[3:, 3:] + 1e-12 * jnp.eye(3))
    return 0.5 * (a + a.T)


# the jump test (SmootherConfig.max_speed_m_s): _pendulum's centre moves at most 0.6 rad x 3.5
# rad/s x 0.552 m = 1.16 m/s
PENDULUM_SPEED_BOUND = 1.2  # [m/s]
JUMP_BASE = SmootherConfig(info_scale=1.0, hinge_max_cost=12.6, max_gap_s=0.2)


def _jump_cfg(cfg=JUMP_BASE):
    return dataclasses.replace(cfg, max_speed_m_s=PENDULUM_SPEED_BOUND)


def test_jump_split_keeps_a_wrong_lock_from_bending_the_good_fits():
    """A wrong lock 1 m off for 4 frames, lost for 5 frames (under ``max_gap_s``: one segment
    without the jump test), then the pendulum tracked. With the jump test the good fits are
    smoothed on their own: within 1 cm and 6 cm/s RMS, with the whole-track model on or off;
    without it the free smoother bends them (over 5 cm, over 0.3 m/s RMS; seeds 11-15, 21, 22
    gave 9.8-10.1 cm and 0.45-0.46 m/s against 1.6-4.7 mm and 1.2-3.4 cm/s with it). The wrong
    lock's own piece (4 frames) is not rejected."""
    for seed in (11, 12, 13):
        (_, pos, vel, _), (meas_rot, meas_pos, info) = _pendulum(seed=seed)
        meas_pos = meas_pos.copy()
        meas_pos[:4] += np.array([0.6, -0.5, 0.6])  # [m]
        valid = np.ones(len(pos), bool)
        valid[4:9] = False
        args = (meas_rot, meas_pos, info, valid, DT)
        good = np.arange(len(pos)) >= 9

        def errors(out, good=good, pos=pos, vel=vel):
            err = np.linalg.norm(out.position - pos, axis=-1)[good]
            v_err = np.linalg.norm(out.velocity - vel, axis=-1)[good]
            return err.max(), np.sqrt(np.mean(v_err**2))

        max_err, v_rms = errors(smooth_track(*args, JUMP_BASE))
        assert max_err > 0.05 and v_rms > 0.3, (seed, max_err, v_rms)
        for cfg in (JUMP_BASE, dataclasses.replace(JUMP_BASE, hinge_whole_track=True)):
            split = smooth_track(*args, _jump_cfg(cfg))
            max_err, v_rms = errors(split)
            assert max_err < 0.01 and v_rms < 0.06, (seed, max_err, v_rms)
            assert not split.jump_rejected.any()
            # frames between the pieces hold the nearest piece's end: nothing carried across
            if not cfg.hinge_whole_track:
                np.testing.assert_array_equal(split.velocity[4:9], 0.0)


def test_jump_split_bridges_a_short_wrong_piece():
    """One fit 0.4 m off mid-track, two 0.3 m deep at the end: cut off by jumps from the long
    track, they are flagged (``jump_rejected``) and bridged: the mid-track frame within 1 cm,
    the last two holding the track's end (the motion of at most 2 frames, under 8 cm); every
    other frame within 1 cm. Without the test the free smoother is pulled over 5 cm off (seeds
    11-15, 21, 22: 19-20 cm at the next-to-last frame). With the whole-track model on, the
    flagged fits are left out of it and it is accepted."""
    for seed in (21, 22):
        (_, pos, _, _), (meas_rot, meas_pos, info) = _pendulum(seed=seed)
        meas_pos = meas_pos.copy()
        t_n = len(pos)
        wrong = np.zeros(t_n, bool)
        wrong[[30, t_n - 2, t_n - 1]] = True
        meas_pos[30] += np.array([0.0, 0.4, 0.0])  # [m]
        meas_pos[-2:] *= 1.0 + 0.3 / np.linalg.norm(meas_pos[-2:], axis=-1, keepdims=True)
        args = (meas_rot, meas_pos, info, np.ones(t_n, bool), DT)
        for cfg in (JUMP_BASE, dataclasses.replace(JUMP_BASE, hinge_whole_track=True)):
            split, plain = smooth_track(*args, _jump_cfg(cfg)), smooth_track(*args, cfg)
            np.testing.assert_array_equal(split.jump_rejected, wrong)
            err = np.linalg.norm(split.position - pos, axis=-1)
            assert err[~wrong].max() < 0.01 and err[30] < 0.01, (seed, err)
            assert err[-2:].max() < 0.08, err[-2:]
            if cfg.hinge_whole_track:
                assert split.hinge and not (split.hinge_outlier & split.jump_rejected).any()
            else:
                assert np.linalg.norm(plain.position - pos, axis=-1).max() > 0.05


def test_jump_split_changes_nothing_without_a_jump():
    """A track whose fits never jump: the same numbers, bit for bit, with the jump test on, with
    and without a long gap and the whole-track model; nothing flagged."""
    (_, _, _, _), (meas_rot, meas_pos, info) = _pendulum(seed=31)
    valid = np.ones(len(meas_pos), bool)
    for gap in (False, True):
        valid[20:32] = not gap
        for cfg in (JUMP_BASE, NO_EXTRAPOLATION):
            args = (meas_rot, meas_pos, info, valid, DT)
            on, off = smooth_track(*args, _jump_cfg(cfg)), smooth_track(*args, cfg)
            assert not on.jump_rejected.any()
            for name in ("rotation", "position", "velocity", "acceleration", "position_cov"):
                np.testing.assert_array_equal(getattr(on, name), getattr(off, name))


def test_the_speed_bound_caps_the_smoothed_velocity():
    """Fits that rush 0.3 m along a line over frames 20-24 and back (a wrong drift), with the
    jump test unable to fire (slack 100 m): the smoothed velocity there exceeds the pendulum's
    bound, and with the bound set it is scaled down to it, direction kept; every frame under the
    bound is the same bit for bit, and no frame's velocity is farther from the truth (the true
    speed, at most 1.16 m/s, is within the bound). ``bound_speed`` alone: a hand-made case."""
    from hec_jax.geometry.smooth import bound_speed

    (_, _, vel, _), (meas_rot, meas_pos, info) = _pendulum(seed=41)
    meas_pos = meas_pos.copy()
    meas_pos[20:30] += np.outer([0, 0.1, 0.2, 0.3, 0.3, 0.3, 0.3, 0.2, 0.1, 0], [0.6, 0, 0.8])
    args = (meas_rot, meas_pos, info, np.ones(len(meas_pos), bool), DT)
    loose = dataclasses.replace(JUMP_BASE, jump_slack_m=100.0)
    off, on = smooth_track(*args, loose), smooth_track(*args, _jump_cfg(loose))
    speed_off = np.linalg.norm(off.velocity, axis=-1)
    speed_on = np.linalg.norm(on.velocity, axis=-1)
    over = speed_off > PENDULUM_SPEED_BOUND
    assert 2 <= over.sum() < len(over) // 2, speed_off.max()
    np.testing.assert_array_equal(on.velocity[~over], off.velocity[~over])
    np.testing.assert_allclose(speed_on[over], PENDULUM_SPEED_BOUND, rtol=1e-12)
    cos = np.sum(on.velocity[over] * off.velocity[over], -1) / (speed_on * speed_off)[over]
    np.testing.assert_allclose(cos, 1.0, rtol=1e-12)
    err_on = np.linalg.norm(on.velocity - vel, axis=-1)
    err_off = np.linalg.norm(off.velocity - vel, axis=-1)
    assert np.all(err_on <= err_off + 1e-12) and np.all(err_on[over] < err_off[over])
    for name in ("rotation", "position", "acceleration", "position_cov"):
        np.testing.assert_array_equal(getattr(on, name), getattr(off, name))
    capped = bound_speed(np.array([[3.0, 4.0, 0.0], [0.3, 0.4, 0.0], [0.0, 0.0, 0.0]]), 1.0)
    np.testing.assert_allclose(capped, [[0.6, 0.8, 0.0], [0.3, 0.4, 0.0], [0.0, 0.0, 0.0]])


def test_jump_test_rejects_bad_settings():
    args = (*_pendulum()[1], np.ones(60, bool), DT)
    for bad in ({"max_speed_m_s": 0.0}, {"max_speed_m_s": -1.0}, {"jump_slack_m": -0.1}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            smooth_track(*args, dataclasses.replace(JUMP_BASE, **bad))


def test_settings_differing_in_numbers_share_one_compilation_and_each_number_acts():
    """The real-valued settings enter the jitted fits as arguments: settings that differ only in
    them reuse one compiled program (a sweep over them compiles once per length), every one of
    them changes the result, and the per-segment result is the one with the numbers compiled in
    as constants (the smoother before), to round-off."""
    (_, _, _, _), (meas_rot, meas_pos, info) = _pendulum(t_n=50, seed=11)
    meas_pos = meas_pos.copy()
    for i in (40, 41):  # two wrong fits, 15 cm along the line of sight: outliers of the model
        meas_pos[i] *= 1.0 + 0.15 / np.linalg.norm(meas_pos[i])
    valid = np.ones(50, bool)
    base = SmootherConfig(
        info_scale=1.0, hinge_max_cost=12.6, hinge_whole_track=True, hinge_robust_scale=6.0
    )
    args = (meas_rot, meas_pos, info, valid, DT)
    ref = smooth_track(*args, base)
    assert ref.hinge
    static, _ = smooth_mod._compiled_form(base)
    segment_fit = smooth_mod._JIT[(static, float(DT), False)]  # (False: no gravity)
    whole_fit = smooth_mod._JIT[("whole", static, float(DT), False)]
    # programs of this length now compiled (other tests may have compiled other lengths)
    compiled = (segment_fit._cache_size(), whole_fit._cache_size())
    jitted = len(smooth_mod._JIT)
    changes = {
        "angular_accel_psd": 200.0,
        "jerk_psd": 100.0,
        "info_scale": 0.3,
        "hinge_max_cost": 1e-6,  # below every fit's cost: the model is refused
        "hinge_robust_scale": 1e-3,
        "hinge_min_inliers": 1.0,  # every valid frame an inlier, not the two wrong fits: refused
    }
    # the whole-track program on its own, from the measurements (every number but jerk_psd acts)
    padded = smooth_mod._pad_inputs(meas_rot, meas_pos, info, valid)
    with jax.enable_x64(True):
        whole = lambda c: whole_fit(*padded, *padded[:2], smooth_mod._compiled_form(c)[1])  # noqa: E731
        whole_ref = whole(base)
    for name, value in changes.items():
        cfg = dataclasses.replace(base, **{name: value})
        out = smooth_track(*args, cfg)
        fields = ("rotation", "position", "velocity", "acceleration")
        moved = max(np.max(np.abs(getattr(out, f) - getattr(ref, f))) for f in fields)
        assert moved > 1e-6 or bool(out.hinge) != bool(ref.hinge), name
        if name != "jerk_psd":
            with jax.enable_x64(True):
                got = whole(cfg)
            fit_moved = max(
                float(np.max(np.abs(np.asarray(a) - np.asarray(b))))
                for a, b in (
                    (got.fit.rotation, whole_ref.fit.rotation),
                    (got.velocity, whole_ref.velocity),
                )
            )
            assert fit_moved > 1e-6 or bool(got.accepted) != bool(whole_ref.accepted), name
    assert len(smooth_mod._JIT) == jitted  # no new jitted function
    assert (segment_fit._cache_size(), whole_fit._cache_size()) == compiled  # none compiled
    # the numbers as constants of the program (as compiled before): the same per-segment result
    cfg = dataclasses.replace(base, angular_accel_psd=7.0, jerk_psd=33.0, info_scale=0.7)
    with jax.enable_x64(True):
        baked = jax.jit(lambda r, p, i, v: smooth_mod._smooth(r, p, i, v, DT, cfg))(*padded)
        traced = smooth_mod._smooth_segment(meas_rot, meas_pos, info, valid, DT, cfg)
    assert segment_fit._cache_size() == compiled[0]
    for f in ("rotation", "position", "velocity"):
        np.testing.assert_allclose(
            getattr(traced, f), np.asarray(getattr(baked, f))[:50], atol=1e-9
        )


# slow: 40-60 s of compiles on the 2-core CI machine (five smoother programs at two frame
# intervals no other test uses) for a contract on compile counts, not on numbers; the
# smoother's warm-up serves benchmarks/eye_randomized.py's timing alone (session 79)
@pytest.mark.slow
def test_warm_up_compiles_every_fit_a_track_of_its_length_can_call():
    """After ``warm_up(t_n, dt, cfg)``, smoothing tracks of t_n frames with gaps anywhere (so
    segments of every length) compiles nothing; without it, the same tracks compile (the meter
    hears JAX's compilations, so the check can fail). A frame interval no other test uses keeps
    the compiled programs of other tests out of it."""
    from hec_jax.report import CompileMeter

    (_, _, _, _), (meas_rot, meas_pos, info) = _pendulum(t_n=45, seed=3)
    rng = np.random.default_rng(0)
    tracks = []
    for _ in range(6):  # valid runs of random lengths between gaps longer than max_gap_s
        valid = np.zeros(45, bool)
        a = int(rng.integers(0, 10))
        while a < 45:
            b = min(45, a + int(rng.integers(4, 40)))
            valid[a:b] = True
            a = b + int(rng.integers(8, 15))
        tracks.append(valid)
    assert {int(np.diff(np.flatnonzero(np.diff(np.r_[0, v, 0]))).max()) > 32 for v in tracks} == {
        True,
        False,
    }  # segments padded to 32 frames and to 64

    def compilations(dt):
        meter = CompileMeter().install()
        try:
            for valid in tracks:
                smooth_track(meas_rot, meas_pos, info, valid, dt, NO_EXTRAPOLATION)
        finally:
            meter.uninstall()
        return meter.compilations

    # cold: the segment fits padded to 32 and to 64 frames and the whole-track fit
    assert compilations(1 / 29.37) == 3
    dt = 1 / 31.13
    assert smooth_mod.warm_up(45, dt, NO_EXTRAPOLATION) == 2  # padded lengths 32 and 64
    assert compilations(dt) == 0
    with pytest.raises(ValueError, match="t_n"):
        smooth_mod.warm_up(0, dt)
    with pytest.raises(ValueError, match="dt"):
        smooth_mod.warm_up(45, 0.0)


# a quarter turn about the box's own x axis: a cube symmetry (another labelling of the same box)
QUARTER_TURN_X = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


def _random_labellings(t_n, seed):
    """(t_n, 3, 3) cube symmetries drawn uniformly (seeded)."""
    return cube_symmetries()[np.random.default_rng(seed).integers(0, 24, t_n)]


def test_nearest_labellings_is_the_least_angle_labelling():
    """:func:`box_model.nearest_labellings` (JAX, batched) against a brute force over the 24
    labellings: the same box (R S, S a symmetry) at the least angle from the reference, and the
    same matrices as the NumPy :func:`box_model.snap_to_symmetry`."""
    rng = np.random.default_rng(0)
    rotations = np.asarray(so3_exp(jnp.asarray(rng.normal(0.0, 1.5, (50, 3)))))
    references = np.asarray(so3_exp(jnp.asarray(rng.normal(0.0, 1.5, (50, 3)))))
    out = np.asarray(nearest_labellings(jnp.asarray(rotations), jnp.asarray(references)))
    sym = cube_symmetries()
    for r, ref, got in zip(rotations, references, out, strict=True):
        angles = rotation_error_deg(r[None] @ sym, np.tile(ref, (24, 1, 1)))
        best = sym[np.argmin(angles)]
        np.testing.assert_allclose(got, r @ best, atol=1e-12)
        np.testing.assert_allclose(got, snap_to_symmetry(r, ref), atol=1e-12)
        assert rotation_error_deg(got[None], ref[None])[0] <= angles.min() + 1e-9


def test_unwrap_labellings_gives_one_labelling_over_a_turning_cube():
    """Fits of a pendulum's box (up to 4 deg a frame) each under a random labelling: the chain
    over ``idx`` gives back the first frame's labelling at every frame of ``idx`` (the truth
    rotations, to round-off); frames outside ``idx`` are returned as given."""
    (rot, _, _, _), _ = _pendulum(seed=3)
    labels = _random_labellings(len(rot), seed=1)
    labels[0] = np.eye(3)
    measured = rot @ labels
    idx = np.flatnonzero(np.arange(len(rot)) % 7 != 3)  # a few frames left out
    out = smooth_mod.unwrap_labellings(measured, idx)
    np.testing.assert_allclose(out[idx], rot[idx], atol=1e-12)
    left_out = np.setdiff1d(np.arange(len(rot)), idx)
    np.testing.assert_array_equal(out[left_out], measured[left_out])


def test_whole_track_fit_relabels_each_frame_to_its_model():
    """The robust whole-track fixed-axis fit on a pendulum whose every fit comes under a random
    labelling, started from the truth: with ``unwrap_labelling`` each pass relabels the fits to
    the model's rotations: accepted, axis within 1 deg, centres within 1 cm, no outlier (started
    from the truth, so this checks the relabelled passes, not their start). Without
    it the labellings are read as motion: rejected (most frames outliers)."""
    (rot, pos, _, axis), (meas_rot, meas_pos, info) = _pendulum(seed=6)
    meas_rot = meas_rot @ _random_labellings(len(rot), seed=2)
    valid = np.ones(len(rot), bool)
    cfg = SmootherConfig(info_scale=1.0, hinge_max_cost=12.6, hinge_robust_scale=6.0)
    with jax.enable_x64(True):
        args = (jnp.asarray(meas_rot), jnp.asarray(meas_pos), jnp.asarray(info))
        start = (jnp.asarray(rot), jnp.asarray(pos))

        def fit(unwrap):
            c = dataclasses.replace(cfg, unwrap_labelling=unwrap)
            return smooth_mod.fit_hinge_robust(*args, jnp.asarray(valid), *start, DT, c)

        unwrapped, plain = fit(True), fit(False)
    assert bool(unwrapped.accepted) and bool(np.all(unwrapped.inlier))
    assert np.degrees(np.arccos(abs(float(unwrapped.fit.axis @ axis)))) < 1.0
    assert np.max(np.linalg.norm(np.asarray(unwrapped.fit.position) - pos, axis=-1)) < 0.01
    assert not bool(plain.accepted) and np.mean(np.asarray(plain.inlier)) < 0.5


def test_unwrap_labelling_keeps_a_run_of_turning_wrong_fits_from_relabelling_the_track():
    """The labelling pattern of development seed 2034 (session 89), drawn synthetic: three wrong
    fits (30 cm off, the box turned by 30, 60 and 80 deg) then the good fits under another
    labelling (a quarter turn, as the tracker's labelling chain carried the wrong fits' turn
    on). With ``unwrap_labelling`` (the jump test rejects the three, the chain skips them) the
    whole-track model is accepted over every frame with no outlier, and every other frame is
    within 1 cm and 2 deg of the truth (seeds 5 and 9-14 gave at most 5.3 mm and 0.8 deg).
    Without it the quarter turn is read as motion: the rotation after it is over 45 deg off,
    and (a failure of another kind than 2034's, where the model was rejected) a whole-track
    model is accepted that flags the 22 good fits before the wrong run as outliers and bends
    the centres over 5 cm (15.9-16.7 cm on seeds 9-12 and 14; on seeds 5 and 13 the model was
    rejected instead, the centres then within 4 mm)."""
    for seed in (9, 10, 11):
        (rot, pos, _, _), (meas_rot, meas_pos, info) = _pendulum(seed=seed)
        meas_rot, meas_pos = meas_rot.copy(), meas_pos.copy()
        for i, deg in zip((22, 23, 24), (30.0, 60.0, 80.0), strict=True):
            meas_rot[i] = meas_rot[i] @ np.asarray(so3_exp(jnp.array([np.radians(deg), 0, 0])))
            meas_pos[i] = meas_pos[i] + np.array([0.0, 0.3, 0.0])  # [m]
        meas_rot[25:] = meas_rot[25:] @ QUARTER_TURN_X
        valid = np.ones(len(pos), bool)
        good = np.ones(len(pos), bool)
        good[22:25] = False
        cfg = dataclasses.replace(_jump_cfg(), hinge_whole_track=True, hinge_robust_scale=6.0)
        args = (meas_rot, meas_pos, info, valid, DT)
        unwrapped = smooth_track(*args, dataclasses.replace(cfg, unwrap_labelling=True))
        plain = smooth_track(*args, cfg)
        np.testing.assert_array_equal(unwrapped.jump_rejected, ~good)
        assert unwrapped.hinge_modelled.all() and not unwrapped.hinge_outlier.any()
        err = np.linalg.norm(unwrapped.position - pos, axis=-1)[good]
        rot_err = rotation_error_deg(unwrapped.rotation[good], rot[good])
        assert err.max() < 0.01 and rot_err.max() < 2.0, (seed, err.max(), rot_err.max())
        assert rotation_error_deg(plain.rotation[25:], rot[25:]).min() > 45.0
        assert plain.hinge_modelled.any() and plain.hinge_outlier[:22].all()
        plain_err = np.linalg.norm(plain.position - pos, axis=-1)[good]
        assert plain_err.max() > 0.05, (seed, plain_err.max())


def test_unwrap_labelling_on_one_segment_without_the_jump_test():
    """The smoother's path without gaps or the jump test (one segment, a fixed-axis fit per
    segment): a pendulum whose every fit comes under a random labelling. With the option the
    chain gives every frame the first one's labelling: the fixed-axis model is used, rotations
    within 2 deg, centres within 1 cm, velocity RMS under 5 cm/s (seeds 3-6 gave at most 0.6
    deg, 3.0 mm and 1.2 cm/s). Without it the model is rejected, the rotations are up to 176-180
    deg off and the velocity RMS over 0.2 m/s (0.24-0.37)."""
    for seed in (3, 4, 5):
        (rot, pos, vel, _), (meas_rot, meas_pos, info) = _pendulum(seed=seed)
        labels = _random_labellings(len(rot), seed=seed)
        labels[0] = np.eye(3)
        args = (meas_rot @ labels, meas_pos, info, np.ones(len(rot), bool), DT)
        cfg = SmootherConfig(info_scale=1.0, hinge_max_cost=12.6)
        unwrapped = smooth_track(*args, dataclasses.replace(cfg, unwrap_labelling=True))
        plain = smooth_track(*args, cfg)
        assert unwrapped.hinge and not plain.hinge
        assert rotation_error_deg(unwrapped.rotation, rot).max() < 2.0
        assert np.linalg.norm(unwrapped.position - pos, axis=-1).max() < 0.01
        vel_rms = [
            np.sqrt(np.mean(np.linalg.norm(out.velocity - vel, axis=-1) ** 2))
            for out in (unwrapped, plain)
        ]
        assert vel_rms[0] < 0.05 and vel_rms[1] > 0.2, vel_rms
        assert rotation_error_deg(plain.rotation, rot).max() > 90.0


def test_unwrap_labelling_changes_little_where_the_fits_keep_one_labelling():
    """With one labelling throughout (a pendulum, two fits 15 cm deep, a 12-frame loss), the
    option has nothing to unwrap: the whole-track model is accepted with the same frames flagged
    (the two deep fits), its centres and rotations those without it to round-off (its
    relabelled passes refit the same frames to the same minimum; seeds 5-8 of the noise gave at
    most 2e-12 m and 8e-10 deg)."""
    for seed in (5, 6, 7):
        (_, pos, _, _), (meas_rot, meas_pos, info) = _pendulum(seed=seed)
        meas_pos = meas_pos.copy()
        valid = np.ones(len(pos), bool)
        valid[20:32] = False
        for i in (40, 41):
            meas_pos[i] *= 1.0 + 0.15 / np.linalg.norm(meas_pos[i])
        cfg = dataclasses.replace(JUMP_BASE, hinge_robust_scale=6.0, hinge_whole_track=True)
        args = (meas_rot, meas_pos, info, valid, DT)
        plain = smooth_track(*args, cfg)
        unwrapped = smooth_track(*args, dataclasses.replace(cfg, unwrap_labelling=True))
        assert plain.hinge_modelled.any() and unwrapped.hinge_modelled.any()
        np.testing.assert_array_equal(np.flatnonzero(unwrapped.hinge_outlier), [40, 41])
        np.testing.assert_array_equal(unwrapped.hinge_outlier, plain.hinge_outlier)
        assert np.max(np.linalg.norm(unwrapped.position - plain.position, axis=-1)) < 1e-9
        assert rotation_error_deg(unwrapped.rotation, plain.rotation).max() < 1e-6


def _horizontal_pendulum(gravity, t_n=60, seed=0, depth_sd=0.03):
    """A pendulum whose hinge is horizontal (perpendicular to ``gravity``, camera frame), its
    centre hanging below the pivot, measured with a centre noise of ``depth_sd`` [m] along the
    line of sight (z) and 3 mm across, and 1 deg in rotation: (truth axis, rot, pos), (meas_rot,
    meas_pos, info)."""
    g = np.asarray(gravity, float) / np.linalg.norm(gravity)
    axis = np.cross(g, [0.3, -0.2, 1.0])  # horizontal: perpendicular to gravity
    axis /= np.linalg.norm(axis)
    t = np.arange(t_n) * DT
    theta = 0.5 * np.cos(3.0 * t)  # [rad]
    e = np.asarray(so3_exp(jnp.asarray(theta[:, None] * axis[None])))
    r0 = np.asarray(so3_exp(jnp.array([0.3, -0.1, 0.2])))
    pivot = np.array([0.05, -0.2, 1.8])  # [m]
    rot, pos = e @ r0, pivot + e @ (0.6 * g)  # the arm hangs along gravity at theta = 0
    rng = np.random.default_rng(seed)
    s_w, s_p = np.deg2rad(1.0), np.array([3e-3, 3e-3, depth_sd])
    meas_rot = np.asarray(so3_exp(jnp.asarray(rng.normal(0.0, s_w, (t_n, 3))))) @ rot
    meas_pos = pos + rng.normal(0.0, 1.0, (t_n, 3)) * s_p
    info = np.tile(np.diag(np.r_[np.full(3, s_w**-2), s_p**-2]), (t_n, 1, 1))
    return (axis, rot, pos), (meas_rot, meas_pos, info)


# a camera looking down 35 deg and rolled 10 deg: gravity in its frame (y down in the image)
GRAVITY_CAM = np.asarray(so3_exp(jnp.array([np.deg2rad(-35.0), 0.0, np.deg2rad(10.0)])))[:, 1]
GRAVITY_CFG = dataclasses.replace(
    NO_EXTRAPOLATION, info_scale=1.0, hinge_max_cost=12.6, hinge_robust_scale=6.0
)


def test_gravity_holds_the_fixed_axis_horizontal_and_nearer_the_truth():
    """With ``gravity_cam`` the accepted whole-track model keeps its axis perpendicular to gravity
    (to round-off; the per-segment fit's axis: the next test) and, on depth-noisy fits of a pendulum whose hinge is horizontal, the axis and the
    centres come nearer the truth than without it, on the mean over 6 noise seeds (the free
    axis tilts with the depth noise; the constrained one cannot). Both models are accepted.
    (Measured: mean axis errors 0.21 against 0.41 deg.)"""
    axis_err, pos_err = {True: [], False: []}, {True: [], False: []}
    for seed in range(6):
        (axis, _, pos), (meas_rot, meas_pos, info) = _horizontal_pendulum(GRAVITY_CAM, seed=seed)
        valid = np.ones(len(pos), bool)
        for constrained in (True, False):
            g = GRAVITY_CAM if constrained else None
            out = smooth_track(meas_rot, meas_pos, info, valid, DT, GRAVITY_CFG, gravity_cam=g)
            assert out.hinge and out.hinge_modelled.all()
            if constrained:
                assert abs(out.hinge_axis @ GRAVITY_CAM) < 1e-9
            axis_err[constrained].append(np.degrees(np.arccos(abs(out.hinge_axis @ axis))))
            pos_err[constrained].append(np.sqrt(np.mean(np.sum((out.position - pos) ** 2, -1))))
    assert np.mean(axis_err[True]) < np.mean(axis_err[False]), axis_err
    assert np.mean(pos_err[True]) < np.mean(pos_err[False]), pos_err


def test_gravity_of_noise_free_fits_gives_the_truth_and_refuses_a_tilted_hinge():
    """Noise-free fits of a horizontal hinge: the constrained fit recovers the axis and centres
    (the constraint biases nothing that is true). Told a gravity 30 deg off (the hinge then not
    horizontal), the whole-track model no longer explains the fits: rejected, not bent."""
    (axis, rot, pos), _ = _horizontal_pendulum(GRAVITY_CAM, seed=0)
    meas_rot, meas_pos = rot, pos  # noise free
    info = np.tile(np.diag([1e4] * 3 + [1e6] * 3), (len(pos), 1, 1))
    valid = np.ones(len(pos), bool)
    out = smooth_track(meas_rot, meas_pos, info, valid, DT, GRAVITY_CFG, gravity_cam=GRAVITY_CAM)
    assert out.hinge_modelled.all()
    assert np.degrees(np.arccos(abs(out.hinge_axis @ axis))) < 0.01
    assert np.max(np.linalg.norm(out.position - pos, axis=-1)) < 1e-4
    g = GRAVITY_CAM / np.linalg.norm(GRAVITY_CAM)
    tilt = np.cos(np.deg2rad(30.0)) * g + np.sin(np.deg2rad(30.0)) * axis  # a gravity 30 deg off
    wrong = smooth_track(meas_rot, meas_pos, info, valid, DT, GRAVITY_CFG, gravity_cam=tilt)
    assert abs(np.degrees(np.arcsin(abs(tilt @ axis))) - 30.0) < 1e-6  # the hinge 30 deg off
    assert not wrong.hinge_modelled.any() and not wrong.hinge  # both fits refused
    assert abs(wrong.hinge_axis @ tilt) < 1e-9  # the per-segment fit was held horizontal
    # not bent: the per-segment smoother's own result on the (exact) fits, near the truth
    assert np.max(np.linalg.norm(wrong.position - pos, axis=-1)) < 0.01


def test_gravity_cam_bad_values_raise():
    (_, _, pos), (meas_rot, meas_pos, info) = _horizontal_pendulum(GRAVITY_CAM, t_n=12)
    valid = np.ones(len(pos), bool)
    for bad in ([0.0, 1.0], [0.0, 0.0, 0.0], [np.nan, 1.0, 0.0]):
        with pytest.raises(ValueError, match="gravity_cam"):
            smooth_track(meas_rot, meas_pos, info, valid, DT, gravity_cam=bad)


@pytest.mark.slow  # compiles, for a contract on compile counts (as the warm-up test above)
def test_warm_up_with_gravity_compiles_the_constrained_fits():
    """``warm_up(..., gravity=True)`` compiles the fits ``gravity_cam`` calls: after it, tracks
    smoothed with a gravity compile nothing (the meter hears JAX's compilations); a frame
    interval no other test uses."""
    from hec_jax.report import CompileMeter

    (_, _, pos), (meas_rot, meas_pos, info) = _horizontal_pendulum(GRAVITY_CAM, t_n=45)
    dt = 1 / 28.71
    assert smooth_mod.warm_up(45, dt, NO_EXTRAPOLATION, gravity=True) == 2
    meter = CompileMeter().install()
    try:
        valid = np.ones(45, bool)
        valid[20:30] = False  # two segments, padded to 32 frames, and the whole-track fit
        smooth_track(meas_rot, meas_pos, info, valid, dt, NO_EXTRAPOLATION, gravity_cam=[0, 1, 0])
    finally:
        meter.uninstall()
    assert meter.compilations == 0
