"""Offline smoothing of a tracked pose sequence (pure JAX; one ``jit`` per sequence length).

The per-frame fits of :mod:`track` are measurements (R_i, t_i) with an information matrix
Lambda_i (6, 6) over the pose increment (dw, dt) (left perturbation, ``refine.retract``). For a
nearly frontal cube the tilt is weakly observed in one frame (the side faces are a few px wide),
and a tilt error moves the fitted centre sideways; both are fixed by using the whole sequence:

1. rotations: Gauss-Newton on the marginal rotation information of every frame
   (Lambda_ww - Lambda_wt Lambda_tt^-1 Lambda_tw) plus a white-angular-acceleration prior, the
   second difference of the rotation, log(R_{i+2} R_{i+1}^T) - log(R_{i+1} R_i^T), with variance
   (2/3) q_w dt^3 per axis (q_w the spectral density, [rad^2/s^3]). Any motion, no model of the
   pendulum.
2. centres: each frame's centre conditioned on its smoothed rotation,
   t_i - Lambda_tt^-1 Lambda_tw log(R*_i R_i^T), covariance Lambda_tt^-1, then the
   constant-acceleration Kalman filter and the Rauch-Tung-Striebel smoother (:mod:`filter`).

3. fixed axis (``SmootherConfig.hinge``): the whole sequence is also fitted as one rigid rotation
   about a fixed line in space (a hinge: pendulum, door, lid), R_i = exp(theta_i [a]x) R_0,
   t_i = p + exp(theta_i [a]x) (t_0 - p), with the axis a, a point p on it, the reference pose
   (R_0, t_0) and one angle theta_i per frame (white angular acceleration prior as in 1.), by
   Gauss-Newton on the full (6, 6) information of every frame, started from 1. and 2. It is
   used when its residual is consistent with the measurements (median normalised squared
   residual over the measured frames at most ``hinge_max_cost``), else the free result of 1.
   and 2. is kept; when used, its centres are the measurements of the RTS smoother of 2. With a
   nearly frontal face the tilt of one frame is weakly observed (and biased over runs of
   frames), but a fixed axis ties every frame's tilt to the frames where it is well observed,
   and to the centre's circle about the axis (its plane fixes the axis' tilt).

4. one fixed axis over the whole track (``SmootherConfig.hinge_whole_track``): the fixed-axis
   model of 3. fitted once over every valid frame of the sequence, across the segments that the
   gaps split (a hinge's axis and pivot do not change while the eye loses the object), robustly:
   iteratively reweighted, each frame's information scaled by the Cauchy weight
   1 / (1 + c_i / c0) of its normalised squared residual c_i (``hinge_robust_scale`` c0), so a
   wrong fit of a few frames (a Necker-like twin, a fit 1 m off before a loss) does not pull the
   axis. Accepted when at least ``hinge_min_inliers`` of the valid frames (and
   ``hinge_min_frames``) are inliers (c_i < 9 c0, weight over 0.1) and their median c_i is at
   most ``hinge_max_cost``; then every frame inside a segment in which at least half the valid
   frames are inliers takes the model's pose (a segment the model disagrees with keeps its own
   result: the model's state there would be carried across a gap from the other segments), and
   its velocity from the model, v_i = dtheta_i/dt a x (t_i - p), the angle's derivative by
   central differences (one-sided at the ends). The acceleration stays the per-segment
   smoother's: the angle's second difference under the white-angular-acceleration prior is
   noisy (docs/eye_randomized.md, "One hinge over the whole track"). Frames outside every
   segment still hold the nearest segment end's state (nothing extrapolated across a long gap).

5. jumps (``SmootherConfig.max_speed_m_s``): consecutive fits farther apart than the object can
   move cannot both be right; a short piece of the track cut off by such a jump is dropped from
   the smoothing (``SmoothedTrack.jump_rejected``) and the track is split at the jumps left, so
   a wrong lock does not bend the good fits next to it. A smoothed velocity faster than that
   bound is scaled down to it: the nearest velocity the object can have, which (the true speed
   being within the bound, and the bound's ball convex) is never farther from the true one.

6. labellings (``SmootherConfig.unwrap_labelling``): a cube's measured rotation R_i is only
   known up to R_i S, S one of its 24 symmetries. Read as motion, a change of labelling between
   two fits is a 90 or 180 deg turn in one frame: the fixed-axis model is rejected, and the
   centres, conditioned on the smoothed rotation, bend. The kept fits are unwrapped first (each
   to the labelling nearest the previous kept fit, as a phase is unwrapped), and the whole-track
   fit may take each frame's residual against the labelling nearest its model rotation
   (relabelled before every robust pass, as correspondences are in ICP). Free labellings also
   let a wrong axis explain more frames, so those passes run from two starts (the smoothed
   poses, and the model of the passes without relabelling) and the run with the lower robust
   objective is kept.

Frames without a measurement get zero information (bridged by the priors).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from hec_jax.geometry import filter as kf
from hec_jax.geometry.box_model import nearest_labellings, snap_to_symmetry
from hec_jax.geometry.refine import so3_exp, so3_log


@dataclass(frozen=True)
class SmootherConfig:
    """Parameters of the smoother. The real-valued ones the jitted fits read
    (``angular_accel_psd``, ``jerk_psd``, ``info_scale``, ``hinge_max_cost``,
    ``hinge_robust_scale``, ``hinge_min_inliers``) enter them as arguments: settings that differ
    only in those share one compilation per padded sequence length.

    Attributes:
        angular_accel_psd: spectral density of the white angular acceleration [rad^2/s^3].
        jerk_psd: spectral density of the white jerk of the centre [m^2/s^5].
        info_scale: factor on the per-frame information [-]. The edge points of one edge share
            their error (blur, a bias along the whole edge), so J^T W J / s^2 over-counts them:
            on a held-out rendered swing (release 0.35 rad, not the benchmark's) the per-frame
            errors were 2-7x the predicted standard deviations (NEES median 670 against 6);
            0.03 was chosen there from {1, 0.3, 0.1, 0.03, 0.01}. Later (denser edge points) 0.01
            with ``jerk_psd`` 10 (was 50) on two held-out swings (release 0.35 and 0.58 rad):
            acceleration RMS 0.27, 0.40 -> 0.13, 0.23 m/s^2, from jerk_psd {5 .. 100} x
            info_scale {0.003 .. 0.1}; lower values smooth more and would blur faster motion.
        iters: Gauss-Newton iterations of the rotation pass.
        hinge: also fit the fixed-axis model (3. above) and use it where it fits.
        hinge_iters: its Gauss-Newton iterations: the most, refused steps included, with
            ``hinge_step_check`` (the fit stops once converged); all of them without.
        hinge_step_check: refuse a Gauss-Newton step of the fixed-axis fit that does not lower
            its objective and raise the damping instead (Levenberg-Marquardt,
            :func:`fit_hinge`), and stop once converged. On by default, unlike the other
            options added since issue 24: it corrects the fit's numerics. False with
            ``hinge_iters`` 10 is the plain fit as it was: every step is taken; started on
            wrong fits, the plain steps can raise the objective manyfold
            (``HingeFit.objective``), so the fit they end at depends on the iteration count
            and on round-off (docs/eye_randomized.md, "The fixed-axis fit's steps checked").
        hinge_max_cost: largest median normalised squared residual (6 dof per measured frame,
            the information scaled by ``info_scale``) of an accepted fixed-axis fit [-]. 0.5 was
            chosen on the two held-out rendered swings (release 0.35 and 0.58 rad): their fits
            gave 0.17 and 0.22; the same swings with an extra steady spin of the box about a
            camera axis (x, y or 45 deg between x and z) gave 0.29-0.64 at 0.25 deg/s (the
            fixed-axis result then still within 0.02 deg of the free one or better) and 0.53-1.7
            at 0.5 deg/s (where the fixed-axis model is worse than the free one: rejected).
            :data:`NO_EXTRAPOLATION` (the randomized benchmark, whose object is a pendulum by
            construction) uses 2.0, chosen on its development seeds, where 0.5 rejected
            whole-track fits with enough inliers; the held-out effect is mixed
            (docs/eye_randomized.md, "The fixed-axis model's cost bound").
        max_gap_s: valid frames more than this apart [s] start a new segment; each segment (first
            to last valid frame) is smoothed on its own, and a frame outside every segment (before
            the first acquisition, after a loss, in a long gap) holds the state of the nearest
            segment end (its rotation and centre, zero velocity and acceleration): nothing is
            extrapolated beyond a short gap (issue 24: over 50 unacquired frames the unsegmented
            smoother had carried the centre 3 m away). None (the default, the smoother as it was
            before issue 24): one segment over all frames, the priors extrapolating to both ends.
            0.2 in ``benchmarks/eye_randomized.py`` (:data:`NO_EXTRAPOLATION`).
        split_at_restarts: a valid frame where the causal tracker started a new filter (the
            ``restarts`` of :func:`smooth_track`: a detection after a loss, or a fit taken along
            its line of sight after the filter ran away) also starts a new segment, however
            short the gap before it. The tracker restarts because its state before belongs to
            another track (a wrong lock it lost, a filter run away in depth), and one segment
            over both would bend the new track toward the old one (development seed 115 of
            the randomized benchmark: a wrong lock 1 m off, lost after 2 frames, pulled the
            next 12 smoothed centres up to 0.9 m off although their fits were within 2 cm).
            False (the default, and :data:`NO_EXTRAPOLATION`'s): gaps alone split. Off in the
            benchmark because over its development seeds it did more harm than good: a
            restart on a wrong fit leaves a short segment whose smoothed velocity follows that
            fit (docs/eye_randomized.md, session 28).
        hinge_whole_track: fit the fixed-axis model once, robustly, over all valid frames of
            the sequence (4. above) and use it, where it is accepted, for every frame inside a
            segment it agrees with (the per-segment result elsewhere; ``acceleration`` and
            ``position_cov`` stay the per-segment ones). Needs ``hinge``. False (the default, the smoother as it was
            before); True in :data:`NO_EXTRAPOLATION` (docs/eye_randomized.md, "One hinge
            over the whole track").
        hinge_robust_scale: c0 of the Cauchy weights [-] (same units as ``hinge_max_cost``;
            chosen on the benchmark's development seeds from {0.5, 1, 3}).
        hinge_robust_passes: fits of the reweighting (each :func:`fit_hinge`).
        hinge_min_inliers: least share of the valid frames that must be inliers [-]: the model
            must explain at least half of the track (0.6 and 0.75 tried, same docs section).
        hinge_min_frames: least number of inlier frames.
        max_speed_m_s: the largest speed the tracked object can have [m/s] (a bound from its
            physics, e.g. ``randomized.max_swing_speed_m_s`` for a released pendulum). Two
            consecutive valid fits farther apart than ``max_speed_m_s`` x their time apart +
            ``jump_slack_m`` cannot both be right (a jump). The valid frames are cut into
            pieces at the gaps, the restarts (where split) and the jumps; a piece of under 4
            valid frames that a jump cuts off from a piece of 4 or more is taken as wrong
            (``SmoothedTrack.jump_rejected``): its fits are dropped from the smoothing and
            its frames bridged by the rest (the frames stay valid: the smoother does not
            decide validity). Then the jumps between the remaining fits split the track:
            each side is smoothed on its own, so a wrong lock of 4 frames or more does not
            bend the good fits next to it into a path the object cannot take (development
            seed 115 of the randomized benchmark: a lock 1 m off for 4 frames, 5 frames lost,
            pulled the next 12 smoothed centres up to 1.1 m off). The whole-track fixed-axis
            model (``hinge_whole_track``) still acts over the gap-split segments (a segment
            it agrees with takes its state on both sides of a jump), without the rejected
            fits. The same bound caps the output: a smoothed velocity faster than it is
            scaled down to it (:func:`bound_speed`; every velocity under it unchanged bit for
            bit). As the true speed is within the bound, the capped velocity is never farther
            from the true one (docs/eye_randomized.md, session 52). None (the default): no
            jump test and no cap.
        jump_slack_m: the fits' own error allowed on top of that distance [m]: at 0.1, a jump
            between two fits means at least one of them is over 5 cm off (the benchmark's
            gross error) when the speed bound holds.
        extend_backward: after smoothing, track backward in time from each re-acquisition that
            the accepted whole-track model explains, and smooth again with the frames found,
            keeping only those the model counts as inliers (:mod:`hec_jax.geometry.backward`).
            Offline only: read by :func:`hec_jax.geometry.track.track_box`, which has the
            frames; :func:`smooth_track` ignores it. Needs ``hinge_whole_track`` to find
            anything. It trusts that model: frames it admits are as far off as the model.
            False (the default, and :data:`NO_EXTRAPOLATION`'s): on the randomized
            benchmark's fresh range it added valid frames and a few gross ones
            (docs/eye_randomized.md, "Tracking backward from each re-acquisition").
        unwrap_labelling: the rotations are a cube's, each known only up to the cube's 24
            labellings of its axes (:func:`hec_jax.geometry.box_model.cube_symmetries`), and
            are unwrapped before they are smoothed (6. above): each kept valid frame's rotation
            is relabelled to the labelling nearest the previous kept frame's (the frames the
            jump test rejects are left out of the chain, so a run of wrong fits that it rejects
            does not carry its turn on; one whose centres pass it still does), and
            the whole-track fit also runs passes in which each frame's rotation is relabelled to
            the labelling nearest the model's of the pass before, from two starts, keeping the
            better (:func:`fit_hinge_robust`). A relabelling is then not read as motion. The
            chain is exact while the fitted rotations (the true turn plus the fits' errors)
            change by under 45 deg between consecutive kept frames. Costs two more runs of the
            whole-track fit's passes. False (the default,
            the smoother as it was): the rotations as given (the tracker keeps one labelling
            by snapping each fit to the last accepted one, ``TrackConfig.keep_labelling``, so a
            run of wrong fits that turns the box can leave the good fits after it relabelled).
    """

    angular_accel_psd: float = 20.0
    jerk_psd: float = 10.0
    info_scale: float = 0.01
    iters: int = 3
    hinge: bool = True
    hinge_iters: int = 100
    hinge_step_check: bool = True
    hinge_max_cost: float = 0.5
    max_gap_s: float | None = None
    split_at_restarts: bool = False
    hinge_whole_track: bool = False
    hinge_robust_scale: float = 1.0
    hinge_robust_passes: int = 5
    hinge_min_inliers: float = 0.5
    hinge_min_frames: int = 8
    max_speed_m_s: float | None = None
    jump_slack_m: float = 0.1
    extend_backward: bool = False
    unwrap_labelling: bool = False


# The smoother of the randomized benchmark (``benchmarks/eye_randomized.py``): no extrapolation
# across gaps over 0.2 s; one robust fixed-axis fit over the whole track, accepted up to a median
# inlier cost of 2 (chosen on the development seeds 0-399: docs/eye_randomized.md, session 53);
# the cube's labellings unwrapped (no parameter; kept by a no-regression rule on 200 development
# seeds it was not shaped on: docs/eye_randomized.md, "Labellings unwrapped", session 89)
NO_EXTRAPOLATION = SmootherConfig(
    max_gap_s=0.2, hinge_whole_track=True, hinge_max_cost=2.0, unwrap_labelling=True
)


class SmoothedTrack(NamedTuple):
    """Attributes: rotation (T, 3, 3) R_cam_box; position, velocity, acceleration (T, 3)
    [m, m/s, m/s^2]; position_cov (T, 3, 3) [m^2]; hinge (bool, the fixed-axis model was used);
    hinge_axis (3,) its unit axis a (camera frame); hinge_cost its median normalised squared
    residual over the measured frames (NaN where not fitted; over the inliers for the
    whole-track fit); hinge_outlier (T,) bool, valid frames whose own fit the accepted
    whole-track model down-weighted as inconsistent (their state is the model's; all False
    otherwise; None from the per-segment pass); jump_rejected (T,) bool, valid frames whose fit
    the jump test (``SmootherConfig.max_speed_m_s``) took as wrong: their state is bridged
    from the fits around them (all False where the test is off; None from the per-segment
    pass); hinge_modelled (T,) bool, the frames that took the accepted whole-track model's
    state (``SmootherConfig.hinge_whole_track``; all False otherwise; None from the per-segment
    pass).
    """

    rotation: Array
    position: Array
    velocity: Array
    acceleration: Array
    position_cov: Array
    hinge: Array
    hinge_axis: Array
    hinge_cost: Array
    hinge_outlier: Array | None = None
    jump_rejected: Array | None = None
    hinge_modelled: Array | None = None


SINGULAR_TT = 1e-9  # a frame's Lambda_tt whose eigenvalues span more than 1 / this is singular


def _split(info: Array) -> tuple[Array, Array, Array]:
    """(marginal rotation information (3, 3), Lambda_tt^-1 (3, 3), Lambda_tt^-1 Lambda_tw (3, 3)).

    A fit can leave a direction of its centre unmeasured (its points on too few edges: Lambda_tt
    singular, e.g. along the line of sight). Where Lambda_tt's smallest eigenvalue is under
    :data:`SINGULAR_TT` x its largest, they are floored there before the inverse (that direction
    then unknown to within metres); the plain inverse of such a frame overflows, and the
    rotation pass, one fit over every frame, returned NaN for the whole sequence.
    """
    lww, lwt, ltt = info[:3, :3], info[:3, 3:], info[3:, 3:]
    evals, evecs = jnp.linalg.eigh(0.5 * (ltt + ltt.T))
    floor = jnp.maximum(SINGULAR_TT * evals[-1], 1e-12)
    floored = (evecs / jnp.maximum(evals, floor)[None, :]) @ evecs.T
    # the plain inverse where well conditioned or unmeasured (zeros): the same numbers as before
    well = evals[0] >= SINGULAR_TT * evals[-1]
    ltt_inv = jnp.where(well, jnp.linalg.inv(ltt + 1e-12 * jnp.eye(3)), floored)
    cond = ltt_inv @ lwt.T
    marg = lww - lwt @ cond
    return 0.5 * (marg + marg.T), 0.5 * (ltt_inv + ltt_inv.T), cond


def smooth_rotations(rotations: Array, info_rot: Array, dt: float, cfg: SmootherConfig) -> Array:
    """Rotation pass: (T, 3, 3) measured rotations, (T, 3, 3) their information [1/rad^2]."""
    t_n = rotations.shape[0]
    sigma = jnp.sqrt(2.0 / 3.0 * cfg.angular_accel_psd * dt**3)  # [rad]
    # L^T with L L^T = information (eigen square root: zero rows where unmeasured)
    evals, evecs = jnp.linalg.eigh(info_rot)
    sqrt_info = jnp.sqrt(jnp.clip(evals, 0.0, None))[..., :, None] * jnp.swapaxes(evecs, -1, -2)

    def residuals(delta, nominal):
        r = so3_exp(delta.reshape(t_n, 3)) @ nominal
        meas = jnp.einsum("tij,tj->ti", sqrt_info, so3_log(r @ jnp.swapaxes(rotations, -1, -2)))
        omega = so3_log(r[1:] @ jnp.swapaxes(r[:-1], -1, -2))
        return jnp.concatenate([meas.reshape(-1), ((omega[1:] - omega[:-1]) / sigma).reshape(-1)])

    def step(nominal, _):
        zero = jnp.zeros(3 * t_n, rotations.dtype)
        res = residuals(zero, nominal)
        jac = jax.jacfwd(residuals)(zero, nominal)
        h = jac.T @ jac + 1e-9 * jnp.eye(3 * t_n)
        delta = -jnp.linalg.solve(h, jac.T @ res)
        return so3_exp(delta.reshape(t_n, 3)) @ nominal, None

    out, _ = jax.lax.scan(step, rotations, None, cfg.iters)
    return out


class HingeFit(NamedTuple):
    """Fixed-axis fit. Attributes: rotation (T, 3, 3), position (T, 3) [m], axis (3,) unit,
    pivot (3,) a point on the axis [m], angle (T,) theta [rad], frame_cost (T,) normalised
    squared residual of each frame (NaN where unmeasured), cost its median over measured frames,
    objective (hinge_iters + 1,) the fit's objective (the frames' whitened residuals and the
    angle's prior, squared and summed) before each iteration and at the end (after an early
    stop, the iterations not run repeat the final value). With ``hinge_step_check`` it is the
    objective each comparison used (the start's or the accepted trial's), so it never rises.
    """

    rotation: Array
    position: Array
    axis: Array
    pivot: Array
    angle: Array
    frame_cost: Array
    cost: Array
    objective: Array


def _sqrt_info(info: Array) -> Array:
    """L^T with L L^T = information (..., n, n) (eigen square root: zero rows where unmeasured)."""
    evals, evecs = jnp.linalg.eigh(info)
    return jnp.sqrt(jnp.clip(evals, 0.0, None))[..., :, None] * jnp.swapaxes(evecs, -1, -2)


def fit_hinge(
    rotations: Array,
    positions: Array,
    information: Array,
    valid: Array,
    rot_init: Array,
    pos_init: Array,
    dt: float,
    cfg: SmootherConfig,
    gravity: Array | None = None,
) -> HingeFit:
    """Rigid rotation about one fixed line (a hinge) fitted to a pose sequence (pure JAX).

    Model: R_i = exp(theta_i [a]x) R_0, t_i = p + exp(theta_i [a]x) (t_0 - p). Gauss-Newton on
    L_i^T (log(R_i Rm_i^T), t_i - tm_i) (Rm, tm the measurements, L_i L_i^T = ``information``
    (T, 6, 6), already scaled; zero where unmeasured) and the second difference of theta over
    sigma = sqrt((2/3) q_w dt^3) (white angular acceleration, as :func:`smooth_rotations`).
    Parameters: (dR_0, dt_0, da, dp) (12) and theta (T); the gauges (a shift of all theta
    against R_0 and t_0, p along a) are held by a small Marquardt damping (1e-6 of the
    diagonal). With ``cfg.hinge_step_check`` a step that does not lower the objective is
    refused and the damping raised (Levenberg-Marquardt, with the gain-ratio update of Madsen,
    Nielsen and Tingleff); an accepted step lowers it again (down to 1e-6) when it gave at least
    half the predicted decrease. So the objective never rises, and while every step gives at
    least half its predicted decrease the iterates are the plain ones. It stops once an
    accepted step lowers the objective by under 1e-10 of it (10 float epsilons in float32), or
    the damping passes 1e8 (no lower objective found), or after ``cfg.hinge_iters`` iterations
    (refused steps count).

    Started from a smoothed sequence (``rot_init``, ``pos_init``): a = the principal direction of
    the rotation vectors log(R_i R_f^T) (f the first valid frame), theta_i their component
    along a, p from (I - E_i) p = t_i - E_i t_f in least squares.

    ``gravity``: None, or a (3,) nonzero vector along gravity in the measurements' frame (the
    camera frame of a calibrated camera; normalised here, not checked: :func:`check_gravity` is
    the public boundary's check). Given, the axis is held perpendicular to it (a pendulum's
    hinge is horizontal): the start is the principal direction of the rotation vectors projected
    on the horizontal plane, and every step moves the axis within that plane (one degree of
    freedom instead of two).
    """
    t_n = rotations.shape[0]
    dtype = rotations.dtype
    sigma = jnp.sqrt(2.0 / 3.0 * cfg.angular_accel_psd * dt**3)  # [rad]
    sqrt_info = _sqrt_info(information)
    wv = valid.astype(dtype)
    f = jnp.argmax(valid)
    r_ref, t_ref = rot_init[f], pos_init[f]
    w = so3_log(rot_init @ r_ref.T) * wv[:, None]  # (T, 3) [rad]
    scatter = w.T @ w
    if gravity is not None:  # the principal direction within the plane perpendicular to gravity
        g = gravity / jnp.linalg.norm(gravity)
        flat = jnp.eye(3, dtype=dtype) - jnp.outer(g, g)
        scatter = flat @ scatter @ flat
    _, evecs = jnp.linalg.eigh(scatter)
    axis = evecs[:, -1]
    if gravity is not None:  # exactly horizontal (a scatter of zero leaves any eigenvector)
        axis = flat @ axis
        fallback = flat @ jnp.eye(3, dtype=dtype)[jnp.argmin(jnp.abs(g))]
        axis = jnp.where(jnp.linalg.norm(axis) > 0.5, axis, fallback)
        axis = axis / jnp.linalg.norm(axis)
    theta = w @ axis
    e = so3_exp(theta[:, None] * axis[None])
    a_ls = (jnp.eye(3, dtype=dtype)[None] - e) * wv[:, None, None]
    b_ls = (pos_init - e @ t_ref) * wv[:, None]
    ata = jnp.einsum("tij,tik->jk", a_ls, a_ls)
    pivot = jnp.linalg.solve(ata + 1e-9 * jnp.eye(3), jnp.einsum("tij,ti->j", a_ls, b_ls))

    def unpack(x, state):
        r0, t0, a, p = state
        r0 = so3_exp(x[:3]) @ r0
        t0 = t0 + x[3:6]
        if gravity is None:
            a = a + x[6:9] - (x[6:9] @ a) * a
        else:  # the axis moves within the horizontal plane
            da = x[6:9] - (x[6:9] @ a) * a
            a = a + (da - (da @ g) * g)
            a = a - (a @ g) * g
        a = a / jnp.linalg.norm(a)
        p = p + x[9:12]
        return r0, t0, a, p - ((p - t0) @ a) * a  # the point of the axis nearest to t0

    def frame_residual(x, theta_i, rm_i, tm_i, sqrt_info_i, state):
        """(6,) whitened residual of one frame; x = (dR_0, dt_0, da, dp, dtheta_i) (13,)."""
        r0, t0, a, p = unpack(x[:12], state)
        e = so3_exp((theta_i + x[12]) * a)
        err = jnp.concatenate([so3_log(e @ r0 @ rm_i.T), p + e @ (t0 - p) - tm_i])
        return sqrt_info_i @ err

    def frame_jacobians(state, theta):
        """Residuals (T, 6) and their Jacobians (T, 6, 13): theta_i acts on frame i only."""
        x = jnp.zeros(13, dtype)

        def one(th, rm, tm, li):
            f = lambda x: frame_residual(x, th, rm, tm, li, state)  # noqa: E731
            return f(x), jax.jacfwd(f)(x)

        return jax.vmap(one)(theta, rotations, positions, sqrt_info)

    # second difference of theta: (T - 2, T) / sigma
    second = (
        jnp.eye(t_n - 2, t_n, dtype=dtype)
        - 2.0 * jnp.eye(t_n - 2, t_n, 1, dtype=dtype)
        + jnp.eye(t_n - 2, t_n, 2, dtype=dtype)
    ) / sigma

    def residuals(state, theta):
        """(T, 6) whitened frame residuals, without their Jacobians."""
        x = jnp.zeros(13, dtype)
        one = lambda th, rm, tm, li: frame_residual(x, th, rm, tm, li, state)  # noqa: E731
        return jax.vmap(one)(theta, rotations, positions, sqrt_info)

    def objective(res, theta):
        """The frames' whitened residuals and the angle's prior, squared and summed."""
        return jnp.sum(res**2) + jnp.sum((second @ theta) ** 2)

    def step(carry, _):
        state, theta, damping, nu, cost = carry
        res, jac = frame_jacobians(state, theta)
        jg, jt = jac[..., :12], jac[..., 12]  # (T, 6, 12), (T, 6)
        h_gg = jnp.einsum("tki,tkj->ij", jg, jg)
        h_gt = jnp.einsum("tki,tk->it", jg, jt)
        h_tt = jnp.diag(jnp.sum(jt * jt, -1)) + second.T @ second
        h = jnp.block([[h_gg, h_gt], [h_gt.T, h_tt]])
        grad = jnp.concatenate(
            [jnp.einsum("tki,tk->i", jg, res), jnp.sum(jt * res, -1) + second.T @ (second @ theta)]
        )
        if not cfg.hinge_step_check:
            cost = objective(res, theta)
            h = h + jnp.diag(1e-6 * jnp.diag(h) + 1e-12)
            dx = -jnp.linalg.solve(h, grad)
            return (unpack(dx[:12], state), theta + dx[12:], damping, nu, cost), cost
        # Levenberg-Marquardt with the gain-ratio update of Madsen, Nielsen and Tingleff (2004,
        # "Methods for non-linear least squares problems", 3.2): a step that does not lower the
        # objective is refused and the damping raised by nu (doubled at each refusal in a row);
        # an accepted one scales it by max(1/3, 1 - (2 rho - 1)^3), rho the actual over the
        # predicted decrease, down to the plain steps' 1e-6
        scale = jnp.diag(h)
        h = h + jnp.diag(damping * scale + 1e-12)
        dx = -jnp.linalg.solve(h, grad)
        # ``cost`` is carried from the start or the accepted trial: every comparison, and the
        # reported trace, uses the objective of one code path (recomputed with the Jacobians it
        # could differ from the accepted trial's in the last bit)
        trial = (unpack(dx[:12], state), theta + dx[12:])
        trial_cost = objective(residuals(*trial), trial[1])
        predicted = dx @ (damping * scale * dx - grad)  # the decrease of the linearised cost
        better = jnp.isfinite(trial_cost) & (trial_cost < cost)
        rho = (cost - trial_cost) / jnp.maximum(predicted, jnp.finfo(dtype).tiny)
        state, theta = jax.tree.map(lambda n, o: jnp.where(better, n, o), trial, (state, theta))
        new_cost = jnp.where(better, trial_cost, cost)
        shrink = jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * jnp.clip(rho, 0.0, 1.0) - 1.0) ** 3)
        damping = jnp.where(better, jnp.maximum(damping * shrink, 1e-6), damping * nu)
        nu = jnp.where(better, 2.0, 2.0 * nu)
        # converged: an accepted step that lowered the objective by under 1e-10 of it, or no
        # step found (the damping past 1e8: steps of 1e-8 of a gradient step, refused)
        tol = max(1e-10, 10.0 * float(jnp.finfo(dtype).eps))
        converged = (better & (cost - trial_cost <= tol * cost)) | (damping > 1e8)
        return (state, theta, damping, nu, new_cost), (cost, converged)

    state = (r_ref, t_ref, axis, pivot)
    damping0, nu0 = jnp.asarray(1e-6, dtype), jnp.asarray(2.0, dtype)
    if not cfg.hinge_step_check:
        start = (state, theta, damping0, nu0, jnp.zeros((), dtype))  # (the cost: an output)
        (state, theta, _, _, _), costs = jax.lax.scan(step, start, None, cfg.hinge_iters)
        ran = cfg.hinge_iters
    else:  # up to ``hinge_iters`` iterations, stopped once converged

        def body(loop):
            k, carry, costs, _ = loop
            carry, (cost, converged) = step(carry, None)
            return k + 1, carry, costs.at[k].set(cost), converged

        def more(loop):
            k, _, _, converged = loop
            return (k < cfg.hinge_iters) & ~converged

        start = (state, theta, damping0, nu0, objective(residuals(state, theta), theta))
        loop = (0, start, jnp.zeros(cfg.hinge_iters, dtype), jnp.asarray(False))
        ran, (state, theta, _, _, final), costs, _ = jax.lax.while_loop(more, body, loop)
    r0, t0, a, p = state
    e = so3_exp(theta[:, None] * a[None])
    rot, pos = e @ r0, p[None, :] + jnp.einsum("tij,j->ti", e, t0 - p)
    if not cfg.hinge_step_check:
        res, _ = frame_jacobians(state, theta)
        final = objective(res, theta)
    else:
        res = residuals(state, theta)
    frame_cost = jnp.where(valid, jnp.sum(res**2, -1), jnp.nan)
    # the iterations not run (stopped once converged) hold the final objective
    costs = jnp.where(jnp.arange(cfg.hinge_iters) < ran, costs, final)
    objective = jnp.concatenate([costs, final[None]])
    return HingeFit(rot, pos, a, p, theta, frame_cost, jnp.nanmedian(frame_cost), objective)


class RobustHinge(NamedTuple):
    """Whole-track fixed-axis fit (:func:`fit_hinge_robust`). Attributes: fit (:class:`HingeFit`,
    its ``frame_cost`` unweighted, its ``cost`` the median over the inliers), velocity and
    acceleration (T, 3) of the centre from the model [m/s, m/s^2], inlier (T,) bool, accepted
    (bool).
    """

    fit: HingeFit
    velocity: Array
    acceleration: Array
    inlier: Array
    accepted: Array


def fit_hinge_robust(
    rotations: Array,
    positions: Array,
    information: Array,
    valid: Array,
    rot_init: Array,
    pos_init: Array,
    dt: float,
    cfg: SmootherConfig,
    gravity: Array | None = None,
) -> RobustHinge:
    """:func:`fit_hinge` reweighted against outlier frames (module docstring, 4.; pure JAX).

    ``information`` (T, 6, 6) is already scaled by ``cfg.info_scale`` and zero where not
    ``valid``. ``gravity``: as :func:`fit_hinge` (every pass holds the axis horizontal). Each
    pass refits from the previous pass's poses with every frame's information
    times its Cauchy weight 1 / (1 + c_i / c0); c_i is the frame's normalised squared residual
    under the unweighted information. Acceptance: finite, at least ``hinge_min_frames`` and
    ``hinge_min_inliers`` of the valid frames inliers (weight over 0.1), median inlier c_i at
    most ``hinge_max_cost``. The model's velocity and acceleration use the angle's central
    differences (one-sided at both ends of the array).

    With ``cfg.unwrap_labelling`` these passes are followed by two runs of relabelled passes, in
    which each pass fits the measured rotations relabelled to the cube labelling nearest the
    rotations it starts from (the first pass: the run's start; later ones: the pass before's
    model): one run from ``rot_init``/``pos_init``, one from the plain passes' model. The run
    with the lower robust objective (sum over the valid frames of c0 log(1 + c_i / c0), the
    Cauchy loss the reweighting minimises, plus the angle's prior) is returned (the first on a
    tie). Relabelling alone, from the smoothed poses, let a wrong axis be accepted on a
    development sequence (docs/eye_randomized.md, "Labellings unwrapped").
    """
    c0 = cfg.hinge_robust_scale
    wv = valid.astype(rotations.dtype)

    def costs(fit, weight):
        return jnp.where(valid, fit.frame_cost / weight, jnp.nan)

    def weights(cost):
        return jnp.where(valid, 1.0 / (1.0 + jnp.nan_to_num(cost) / c0), 1.0)

    def measured(r_model, relabel):
        # the measurements' labellings nearest the model's rotations (cfg.unwrap_labelling)
        return nearest_labellings(rotations, r_model) if relabel else rotations

    def irls(relabel, r_start, p_start):
        """The reweighted passes from (r_start, p_start): (the last fit, its unweighted costs)."""

        def refit(weight, r_init, p_init):
            info = information * weight[:, None, None]
            meas = measured(r_init, relabel)
            return fit_hinge(meas, positions, info, valid, r_init, p_init, dt, cfg, gravity)

        def one_pass(carry, _):
            weight, r_init, p_init = carry
            fit = refit(weight, r_init, p_init)
            return (weights(costs(fit, weight)), fit.rotation, fit.position), None

        weight = jnp.ones_like(wv)
        (weight, r_init, p_init), _ = jax.lax.scan(
            one_pass, (weight, r_start, p_start), None, cfg.hinge_robust_passes - 1
        )
        fit = refit(weight, r_init, p_init)
        return fit, costs(fit, weight)

    def robust_objective(fit, cost):
        # the Cauchy loss the reweighting minimises, plus the angle's prior; inf where any of it
        # is not finite (a run that diverged is never kept over a finite one)
        sigma = jnp.sqrt(2.0 / 3.0 * cfg.angular_accel_psd * dt**3)
        second = (fit.angle[2:] - 2.0 * fit.angle[1:-1] + fit.angle[:-2]) / sigma
        data = jnp.sum(jnp.where(valid, c0 * jnp.log1p(jnp.where(valid, cost, 0.0) / c0), 0.0))
        total = data + jnp.sum(second**2)
        return jnp.where(jnp.isfinite(total), total, jnp.inf)

    fit, cost = irls(False, rot_init, pos_init)
    if cfg.unwrap_labelling:
        # relabelled passes from two starts (the smoothed poses, and the plain passes' model);
        # the one with the lower robust objective is kept
        from_start = irls(True, rot_init, pos_init)
        from_plain = irls(True, fit.rotation, fit.position)
        first = robust_objective(*from_start) <= robust_objective(*from_plain)
        fit, cost = jax.tree.map(lambda a, b: jnp.where(first, a, b), from_start, from_plain)
    inlier = valid & (weights(cost) > 0.1)
    n_in = jnp.sum(inlier)
    median = jnp.nanmedian(jnp.where(inlier, cost, jnp.nan))
    finite = jnp.all(jnp.isfinite(fit.rotation)) & jnp.all(jnp.isfinite(fit.position))
    accepted = (
        finite
        & (n_in >= cfg.hinge_min_frames)
        & (n_in >= cfg.hinge_min_inliers * jnp.sum(wv))
        & (median <= cfg.hinge_max_cost)
    )
    omega = jnp.gradient(fit.angle, dt)  # [rad/s]
    alpha = jnp.gradient(omega, dt)  # [rad/s^2]
    arm = fit.position - fit.pivot[None]
    a_x_arm = jnp.cross(fit.axis[None], arm)
    velocity = omega[:, None] * a_x_arm
    acceleration = alpha[:, None] * a_x_arm + (omega**2)[:, None] * jnp.cross(
        fit.axis[None], a_x_arm
    )
    fit = fit._replace(frame_cost=cost, cost=median)
    return RobustHinge(fit, velocity, acceleration, inlier, accepted)


def _smooth(rotations, positions, information, valid, dt, cfg: SmootherConfig, gravity=None):
    info = jnp.where(valid[:, None, None], cfg.info_scale * information, 0.0)
    marg, ltt_inv, cond = jax.vmap(_split)(info)
    rot = smooth_rotations(rotations, marg, dt, cfg)
    shift = so3_log(rot @ jnp.swapaxes(rotations, -1, -2))
    pos = positions - jnp.einsum("tij,tj->ti", cond, shift)
    nan = jnp.full((), jnp.nan, rotations.dtype)
    hinge, axis, cost = jnp.asarray(False), jnp.full(3, nan), nan
    if cfg.hinge:
        fit = fit_hinge(rotations, positions, info, valid, rot, pos, dt, cfg, gravity)
        finite = jnp.all(jnp.isfinite(fit.rotation)) & jnp.all(jnp.isfinite(fit.position))
        hinge = finite & (fit.cost <= cfg.hinge_max_cost)
        rot = jnp.where(hinge, fit.rotation, rot)
        # the model's centres as the smoother's measurements (velocity and acceleration by the
        # RTS smoother below; its covariance then treats them as independent, i.e. too small)
        pos = jnp.where(hinge, fit.position, pos)
        axis, cost = fit.axis, fit.cost
    fcfg = kf.FilterConfig(dt=dt, jerk_psd=cfg.jerk_psd)
    filt, pred = kf.filter_sequence(fcfg, pos, ltt_inv, valid)
    sm = kf.rts_smooth(fcfg, filt, pred)
    m = sm.mean
    return SmoothedTrack(rot, m[:, :3], m[:, 3:6], m[:, 6:], sm.cov[:, :3, :3], hinge, axis, cost)


_JIT: dict = {}
PAD = 32  # sequence lengths are padded to a multiple of this (one compilation per size)


def smooth_track(
    rotations,
    positions,
    information,
    valid,
    dt: float,
    cfg: SmootherConfig = SmootherConfig(),
    restarts=None,
    gravity_cam=None,
) -> SmoothedTrack:
    """Smooth a tracked sequence (NumPy in and out), segment by segment (``cfg.max_gap_s``,
    ``cfg.split_at_restarts``, ``cfg.max_speed_m_s``).

    A segment with fewer than 4 valid frames is not smoothed: its valid frames keep their
    measurements (zero velocity and acceleration), the others hold the nearest valid frame's.
    With fewer than 4 valid frames in all, the inputs are returned unchanged (positions zeroed
    where not valid), with zero velocity and acceleration.
    ``hinge``, ``hinge_axis`` and ``hinge_cost`` are those of the longest smoothed segment, or
    of the whole-track fit where ``cfg.hinge_whole_track`` and it is accepted.

    Args:
        rotations: (T, 3, 3) per-frame R_cam_box (a guess where not valid, e.g. coasted).
        positions: (T, 3) per-frame centres [m] (any finite value where not valid).
        information: (T, 6, 6) information of (dw, dt) [1/rad^2, 1/m^2].
        valid: (T,) bool.
        dt: frame interval [s].
        cfg: the smoother's settings.
        restarts: (T,) bool, the frames where the causal tracker started a new filter
            (``TrackStep.restarted``); used with ``cfg.split_at_restarts``. None: none.
        gravity_cam: (3,) the direction of gravity in the camera frame (any length; from a
            calibrated camera's extrinsics, e.g. ``R_world_cam.T @ (0, 0, -1)``), or None. Given,
            every fixed-axis fit (``cfg.hinge``, per segment and over the whole track) keeps its
            axis horizontal, as a pendulum's hinge is (:func:`fit_hinge`). None: the axis is free
            (as before).

    Computed in float64 whatever ``jax_enable_x64`` says (``jax.enable_x64`` around the jitted
    fits): in float32 the fixed-axis fit returns NaN on many sequences and is silently dropped.

    Raises:
        ValueError: ``restarts`` not of ``valid``'s shape; ``cfg.max_speed_m_s`` not positive
            or ``cfg.jump_slack_m`` negative; ``gravity_cam`` not a finite nonzero (3,) vector.
    """
    if cfg.max_speed_m_s is not None and not cfg.max_speed_m_s > 0:
        raise ValueError(f"max_speed_m_s must be positive or None, got {cfg.max_speed_m_s}")
    if not cfg.jump_slack_m >= 0:
        raise ValueError(f"jump_slack_m must be >= 0, got {cfg.jump_slack_m}")
    gravity = check_gravity(gravity_cam)
    with jax.enable_x64(True):
        return _smooth_track(rotations, positions, information, valid, dt, cfg, restarts, gravity)


def check_gravity(gravity_cam) -> np.ndarray | None:
    """``gravity_cam`` as a (3,) float64 unit vector, or None where None (the public boundary's
    check of :func:`smooth_track`'s argument).

    Raises:
        ValueError: not a finite nonzero (3,) vector.
    """
    if gravity_cam is None:
        return None
    gravity = np.asarray(gravity_cam, np.float64)
    if gravity.shape != (3,) or not np.all(np.isfinite(gravity)) or not np.linalg.norm(gravity) > 0:
        raise ValueError(f"gravity_cam must be a finite nonzero (3,) vector, got {gravity_cam!r}")
    return gravity / np.linalg.norm(gravity)


def _smooth_track(
    rotations, positions, information, valid, dt, cfg, restarts, gravity=None
) -> SmoothedTrack:
    """:func:`smooth_track` under float64 (the same arguments, all given)."""
    valid = np.asarray(valid, bool)
    t_n = len(valid)
    split = cfg.split_at_restarts and restarts is not None
    if split:
        restarts = np.asarray(restarts, bool)
        if restarts.shape != valid.shape:
            raise ValueError(f"restarts {restarts.shape} does not match valid {valid.shape}")
    rotations = np.asarray(rotations, np.float64)
    positions = np.where(valid[:, None], np.asarray(positions, np.float64), 0.0)
    information = np.asarray(information, np.float64)
    z = np.zeros((t_n, 3))
    out = SmoothedTrack(
        rotations.copy(),
        positions.copy(),
        z.copy(),
        z.copy(),
        np.tile(np.eye(3), (t_n, 1, 1)),
        np.bool_(False),
        np.full(3, np.nan),
        np.float64(np.nan),
        np.zeros(t_n, bool),
        np.zeros(t_n, bool),
        np.zeros(t_n, bool),
    )
    idx = np.flatnonzero(valid)
    if idx.size < 4:
        return out
    if cfg.max_gap_s is None and not split and cfg.max_speed_m_s is None:
        if cfg.unwrap_labelling:
            rotations = unwrap_labellings(rotations, idx)
        seg = _smooth_segment(rotations, positions, information, valid, dt, cfg, gravity)
        out = seg._replace(
            hinge_outlier=np.zeros(t_n, bool),
            jump_rejected=np.zeros(t_n, bool),
            hinge_modelled=np.zeros(t_n, bool),
        )
        if cfg.hinge and cfg.hinge_whole_track:
            out, modelled = _whole_track(
                out, rotations, positions, information, valid, [(0, t_n)], dt, cfg, gravity
            )
            out = out._replace(hinge_modelled=modelled)
        return out
    gap = t_n if cfg.max_gap_s is None else max(int(np.floor(cfg.max_gap_s / dt + 1e-9)), 1)
    rejected = np.zeros(t_n, bool)

    def gap_breaks(idx):  # (len(idx) - 1,) bool: a long gap or a restart before the next frame
        long_gap = np.diff(idx) > gap + 1
        return long_gap | restarts[idx[1:]] if split else long_gap

    new_segment = gap_breaks(idx)
    starts, ends = _segments(idx, new_segment)
    model_segments = list(zip(starts, ends, strict=True))  # where the whole-track model may act
    if cfg.max_speed_m_s is not None:
        jump = ~new_segment & _jumps(positions, idx, dt, cfg)
        piece = np.concatenate([[0], np.cumsum(new_segment | jump)])  # each valid frame's piece
        size = np.bincount(piece)[piece]
        # a short piece cut off by a jump from a long one: its fits are taken as wrong
        next_long = np.concatenate([jump & (size[1:] >= 4), [False]])
        prev_long = np.concatenate([[False], jump & (size[:-1] >= 4)])
        bad = np.isin(piece, piece[(size < 4) & (next_long | prev_long)])
        if bad.any():
            valid = valid.copy()
            valid[idx[bad]] = False
            rejected[idx[bad]] = True
            idx = idx[~bad]
            new_segment = gap_breaks(idx)
        new_segment |= _jumps(positions, idx, dt, cfg)
        starts, ends = _segments(idx, new_segment)
    if cfg.unwrap_labelling:  # over the kept fits: the rejected ones do not carry their turn
        rotations = unwrap_labellings(rotations, idx)
    longest = -1
    for a, b in zip(starts, ends, strict=True):
        sl = slice(a, b)
        if valid[sl].sum() >= 4:
            seg = _smooth_segment(
                rotations[sl], positions[sl], information[sl], valid[sl], dt, cfg, gravity
            )
            for name in ("rotation", "position", "velocity", "acceleration", "position_cov"):
                getattr(out, name)[sl] = getattr(seg, name)
            if b - a > longest:
                longest = b - a
                out = out._replace(
                    hinge=seg.hinge, hinge_axis=seg.hinge_axis, hinge_cost=seg.hinge_cost
                )
        else:  # too short to smooth: measurements, held over its own gaps
            near = idx[(idx >= a) & (idx < b)]
            j = near[np.abs(np.arange(a, b)[:, None] - near[None, :]).argmin(1)]
            out.rotation[sl], out.position[sl] = rotations[j], positions[j]
    inside = np.zeros(t_n, bool)
    ends_all = []
    for a, b in zip(starts, ends, strict=True):
        inside[a:b] = True
        ends_all += [a, b - 1]
    ends_all = np.asarray(ends_all)
    if cfg.hinge and cfg.hinge_whole_track:
        out, modelled = _whole_track(
            out, rotations, positions, information, valid, model_segments, dt, cfg, gravity
        )
        inside |= modelled  # the model's state across a jump inside a segment it agrees with
        out = out._replace(hinge_modelled=modelled)
    # frames outside every segment hold the nearest segment end (no extrapolation)
    for t in np.flatnonzero(~inside):
        e = ends_all[np.argmin(np.abs(ends_all - t))]
        out.rotation[t], out.position[t] = out.rotation[e], out.position[e]
        out.velocity[t], out.acceleration[t] = 0.0, 0.0
        out.position_cov[t] = out.position_cov[e]
    if cfg.max_speed_m_s is not None:
        out = out._replace(velocity=bound_speed(out.velocity, cfg.max_speed_m_s))
    return out._replace(jump_rejected=rejected)


def warm_up(
    t_n: int, dt: float, cfg: SmootherConfig = SmootherConfig(), gravity: bool = False
) -> int:
    """Compile every jitted fit that :func:`smooth_track` with ``dt`` and ``cfg`` can call on a
    track of ``t_n`` frames, so that a timed caller does not time a compilation (each takes
    seconds on first use): the per-segment fit for each padded segment length (a multiple of
    ``PAD`` up to ``t_n``'s; a segment's length depends on where the gaps, restarts and jumps
    fall) and, with ``cfg.hinge`` and ``cfg.hinge_whole_track``, the whole-track fit. Runs
    ``smooth_track`` on synthetic tracks (a slow straight motion, one valid segment of each
    padded length) and returns how many tracks it ran (not how many programs compiled: a
    program compiled earlier is not compiled again); their results are discarded. ``gravity``:
    compile the fits that hold the axis horizontal (``smooth_track``'s ``gravity_cam`` given).

    Raises:
        ValueError: ``t_n`` not an integer >= 1 or ``dt`` not positive.
    """
    if isinstance(t_n, bool) or not isinstance(t_n, (int, np.integer)) or t_n < 1:
        raise ValueError(f"t_n must be an integer >= 1, got {t_n!r}")
    if not dt > 0:
        raise ValueError(f"dt must be positive, got {dt!r}")
    t_n = int(t_n)
    # 1 cm/s along x, 1 m in front of the camera: no jump, no gap but the one made below
    positions = np.zeros((t_n, 3))
    positions[:, 0] = 0.01 * dt * np.arange(t_n)
    positions[:, 2] = 1.0
    rotations = np.tile(np.eye(3), (t_n, 1, 1))
    information = np.tile(np.diag([1e4, 1e4, 1e4, 1e6, 1e6, 1e6]), (t_n, 1, 1))
    runs = 0
    for padded in range(PAD, -(-t_n // PAD) * PAD + 1, PAD):
        length = min(padded, t_n)  # one valid segment of this length pads to ``padded``
        if length < 4:  # too short to smooth: nothing is compiled for it
            continue
        valid = np.zeros(t_n, bool)
        valid[:length] = True
        gravity_cam = np.array([0.0, 1.0, 0.0]) if gravity else None
        restarts = np.zeros(t_n, bool)
        smooth_track(rotations, positions, information, valid, dt, cfg, restarts, gravity_cam)
        runs += 1
    return runs


def unwrap_labellings(rotations: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """(T, 3, 3) ``rotations`` with each frame of ``idx`` (sorted) after the first relabelled
    to the cube labelling nearest the frame of ``idx`` before it (already relabelled): a chain,
    as a phase is unwrapped (module docstring, 6.). The other frames and the first of ``idx``
    are returned as given. Right whenever the fitted rotations of consecutive frames of ``idx``
    differ by under 45 deg (up to their labelling).
    """
    out = np.array(rotations, np.float64)
    for before, t in zip(idx[:-1], idx[1:], strict=True):
        out[t] = snap_to_symmetry(out[t], out[before])
    return out


def bound_speed(velocity: np.ndarray, max_speed: float) -> np.ndarray:
    """``velocity`` (..., 3) [m/s] with every vector faster than ``max_speed`` [m/s] scaled down
    to that speed, its direction kept: the projection onto the ball of the speeds an object
    bounded by ``max_speed`` can have. Vectors within the bound are returned bit for bit.
    """
    velocity = np.asarray(velocity, np.float64)
    speed = np.linalg.norm(velocity, axis=-1, keepdims=True)
    over = speed > max_speed
    return np.where(over, velocity * (max_speed / np.where(over, speed, 1.0)), velocity)


def _jumps(positions: np.ndarray, idx: np.ndarray, dt: float, cfg: SmootherConfig) -> np.ndarray:
    """(len(idx) - 1,) bool: consecutive valid fits ``idx`` farther apart than the object can
    move (``cfg.max_speed_m_s``) plus ``cfg.jump_slack_m``.
    """
    dist = np.linalg.norm(np.diff(positions[idx], axis=0), axis=-1)
    return dist > cfg.max_speed_m_s * dt * np.diff(idx) + cfg.jump_slack_m


def _unsplit(cfg: SmootherConfig) -> SmootherConfig:
    """``cfg`` with the fields that only split segments or act outside the smoother (not used
    inside the jitted fits) at their defaults: one compilation for all their values.
    """
    return dataclasses.replace(
        cfg,
        max_gap_s=None,
        split_at_restarts=False,
        max_speed_m_s=None,
        jump_slack_m=0.1,
        extend_backward=False,
    )


# The real-valued settings the jitted fits read. They enter the fits as a traced (6,) float64
# argument, not as constants of the program, so settings that differ only in them share one
# compilation (a sweep over them compiles once per sequence length).
_TRACED_NUMBERS = (
    "angular_accel_psd",
    "jerk_psd",
    "info_scale",
    "hinge_max_cost",
    "hinge_robust_scale",
    "hinge_min_inliers",
)


def _compiled_form(cfg: SmootherConfig) -> tuple[SmootherConfig, np.ndarray]:
    """(the settings a jitted fit is compiled for: :func:`_unsplit`'s with every field of
    ``_TRACED_NUMBERS`` at its default, those fields' values (6,) float64 to pass it).
    """
    numbers = np.array([float(getattr(cfg, name)) for name in _TRACED_NUMBERS], np.float64)
    defaults = {name: getattr(SmootherConfig, name) for name in _TRACED_NUMBERS}
    return dataclasses.replace(_unsplit(cfg), **defaults), numbers


def _with_numbers(static: SmootherConfig, numbers: Array) -> SmootherConfig:
    """``static`` with the fields of ``_TRACED_NUMBERS`` set from ``numbers`` (traced inside a
    jitted fit: the settings object then holds scalars of the trace).
    """
    return dataclasses.replace(static, **dict(zip(_TRACED_NUMBERS, numbers, strict=True)))


def _segments(idx: np.ndarray, new_segment: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(starts, ends) [a, b) of the segments of the valid frames ``idx`` (sorted), a new one
    after each ``new_segment`` (len(idx) - 1,) break.
    """
    breaks = np.flatnonzero(new_segment)
    starts = np.concatenate([[idx[0]], idx[breaks + 1]])
    ends = np.concatenate([idx[breaks], [idx[-1]]]) + 1
    return starts, ends


def _smooth_segment(rotations, positions, information, valid, dt, cfg, gravity=None):
    """:func:`_smooth` on one segment (>= 4 valid frames), padded to a multiple of ``PAD``
    (a :class:`SmoothedTrack`).
    """
    t_n = len(valid)
    static, numbers = _compiled_form(cfg)
    key = (static, float(dt), gravity is not None)
    if key not in _JIT:
        _JIT[key] = jax.jit(
            lambda r, p, i, v, x, g=None: _smooth(r, p, i, v, dt, _with_numbers(static, x), g)
        )
    # padded to a multiple of PAD frames to share compilations
    args = (*_pad_inputs(rotations, positions, information, valid), numbers)
    out = _JIT[key](*args) if gravity is None else _JIT[key](*args, gravity)
    per_frame = (np.array(x)[:t_n] for x in out[:5])
    return SmoothedTrack(*per_frame, *(np.asarray(x) for x in out[5:8]))


def _pad_inputs(rotations, positions, information, valid):
    """Pad (T, ...) arrays to a multiple of ``PAD`` frames (unmeasured: only the priors act)."""
    t_n = len(valid)
    pad = -(-t_n // PAD) * PAD - t_n

    def ext(x, fill):
        x = np.asarray(x, np.float64)
        return np.concatenate([x, np.repeat(fill, pad, axis=0)]) if pad else x

    return (
        ext(rotations, np.asarray(rotations)[-1:]),
        ext(positions, np.zeros((1, 3))),
        ext(information, np.zeros((1, 6, 6))),
        np.concatenate([valid, np.zeros(pad, bool)]),
    )


def _whole_track(out, rotations, positions, information, valid, segments, dt, cfg, gravity=None):
    """The robust whole-track fixed-axis fit (module docstring, 4.) on top of the per-segment
    result ``out`` (its poses start the fit). Where accepted, each segment [a, b) of
    ``segments`` in which at least half the valid frames are inliers takes the model's state; a
    segment the model disagrees with keeps its own (the model's state there would be carried
    across the gap from other segments); the acceleration stays the per-segment one. NumPy in
    and out: (out, (T,) bool the frames that took the model's state).
    """
    t_n = len(valid)
    static, numbers = _compiled_form(cfg)
    key = ("whole", static, float(dt), gravity is not None)
    if key not in _JIT:

        def run(r, p, i, v, r0, p0, x, g=None):
            traced = _with_numbers(static, x)
            info = jnp.where(v[:, None, None], traced.info_scale * i, 0.0)
            return fit_hinge_robust(r, p, info, v, r0, p0, dt, traced, g)

        _JIT[key] = jax.jit(run)
    r, p, i, v = _pad_inputs(rotations, positions, information, valid)
    r0, p0, _, _ = _pad_inputs(out.rotation, out.position, information, valid)  # the start
    args = (r, p, i, v, r0, p0, numbers)
    robust = _JIT[key](*args) if gravity is None else _JIT[key](*args, gravity)
    if not bool(robust.accepted):
        return out, np.zeros(t_n, bool)
    fit = robust.fit
    take = {
        "rotation": np.asarray(fit.rotation)[:t_n],
        "position": np.asarray(fit.position)[:t_n],
        "velocity": np.asarray(robust.velocity)[:t_n],
    }
    inlier = np.asarray(robust.inlier)[:t_n]
    use = np.zeros(t_n, bool)
    for a, b in segments:
        use[a:b] = 2 * np.sum(inlier[a:b]) >= np.sum(valid[a:b])
    for name, model in take.items():
        getattr(out, name)[use] = model[use]
    out = out._replace(
        hinge=np.bool_(True),
        hinge_axis=np.asarray(fit.axis),
        hinge_cost=np.float64(fit.cost),
        hinge_outlier=valid & ~inlier & use,
    )
    return out, use
