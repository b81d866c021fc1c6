"""Pose of the known box from its image: planar initialisation and Levenberg-Marquardt refinement.

Pure JAX, jittable and vmappable; fixed iteration counts (``lax.scan``). The pose is updated on
the left, ``R <- exp([dw]x) R``, ``t <- t + dt``; Jacobians by forward-mode autodiff of the image
residuals (``jax.jacfwd`` over the 6-vector (dw, dt)).

Two residuals:

* corners: pixel reprojection error of labelled corners (synthetic two-frame problems);
* edges: signed distance [px] of detected segment end points to the projected model edge they
  were associated with (tracking on images). Robust (Huber, iteratively reweighted).

:func:`two_frame_motion` is the answer to the foundation benchmark: both poses from all visible
corners, initialised by a homography on the largest visible face and by the paper's
``estimate_motion_core`` on the longest visible parallel pair (whichever fits better), then
Phi = R1 R0^T, Gamma = t1 - Phi t0 (Eq. 1).

Speed of the batched (``vmap``) corner path on a CPU: it is written on scalars (nested lists of
arrays), so that every quantity is one vector over the batch and XLA emits fused vector loops;
no gathers, sorts, small batched matrix products or LAPACK calls (each runs as a slow loop over
the batch). XLA:CPU recomputes a cheap expression inside every kernel that uses it, so values
with many uses are made to end in a division (which it does not duplicate): the projected
corners, the trial cost of the LM (:func:`_materialize`), the unit quaternion of
``parallel_motion._special_polar``; data-dependent choices with many uses are ``jnp.argmax``
reductions (computed once).
"""

from __future__ import annotations

import functools
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array

from hec_jax.geometry.box_model import (
    EDGE_FACES,
    EDGE_FAMILY,
    EDGES,
    FACE_ORIENTATION,
    FACES,
    Pose,
    box_corners,
    project_corners,
)
from hec_jax.geometry.camera import pixel_to_normalized
from hec_jax.geometry.parallel_motion import estimate_motion_core
from hec_jax.geometry.synthetic import CUBE_CORNERS_UNIT


def so3_exp(w: Array) -> Array:
    """Rotation matrix (..., 3, 3) of the rotation vector w (..., 3) [rad] (Rodrigues, safe at 0)."""
    theta2 = jnp.sum(w * w, axis=-1)
    small = theta2 < 1e-12
    theta = jnp.sqrt(jnp.where(small, 1.0, theta2))
    a = jnp.where(small, 1.0 - theta2 / 6.0, jnp.sin(theta) / theta)
    b = jnp.where(
        small, 0.5 - theta2 / 24.0, (1.0 - jnp.cos(theta)) / jnp.where(small, 1.0, theta2)
    )
    zero = jnp.zeros_like(w[..., 0])
    kx = jnp.stack(
        [
            jnp.stack([zero, -w[..., 2], w[..., 1]], -1),
            jnp.stack([w[..., 2], zero, -w[..., 0]], -1),
            jnp.stack([-w[..., 1], w[..., 0], zero], -1),
        ],
        -2,
    )
    eye = jnp.broadcast_to(jnp.eye(3, dtype=w.dtype), kx.shape)
    return eye + a[..., None, None] * kx + b[..., None, None] * (kx @ kx)


def so3_log(rotation: Array) -> Array:
    """Rotation vector (..., 3) of a rotation matrix (angles below pi)."""
    cos = jnp.clip(0.5 * (jnp.trace(rotation, axis1=-2, axis2=-1) - 1.0), -1.0, 1.0)
    v = 0.5 * jnp.stack(
        [
            rotation[..., 2, 1] - rotation[..., 1, 2],
            rotation[..., 0, 2] - rotation[..., 2, 0],
            rotation[..., 1, 0] - rotation[..., 0, 1],
        ],
        -1,
    )
    sin = jnp.sqrt(jnp.sum(v * v, axis=-1))
    angle = jnp.arctan2(sin, cos)
    scale = jnp.where(sin > 1e-12, angle / jnp.where(sin > 1e-12, sin, 1.0), 1.0)
    return v * scale[..., None]


def retract(pose: Pose, delta: Array) -> Pose:
    """Pose (+) delta, delta = (dw, dt) (6,): R <- exp(dw) R, t <- t + dt."""
    return Pose(so3_exp(delta[:3]) @ pose.rotation, pose.translation + delta[3:])


class Fit(NamedTuple):
    """Result of a refinement (a pytree).

    Attributes:
        pose: the refined :class:`Pose`.
        cost: robust cost at the solution (sum of Huber losses of the residuals) [px^2].
        rms: RMS of the raw residuals over the used (non-zero weight) entries [px].
        information: (6, 6) J^T W J at the solution (inverse covariance of (dw, dt) per px^2).
    """

    pose: Pose
    cost: Array
    rms: Array
    information: Array


def solve_spd(a: Array, b: Array) -> Array:
    """X = a^-1 b for a small symmetric positive definite a (n, n), b (n,): Cholesky unrolled into
    elementwise operations, so that a vmapped batch runs as vector code instead of a loop of
    LAPACK calls (the LM step's 6x6 system).
    """
    n = a.shape[-1]
    return jnp.stack(_solve_spd_lists([[a[i, j] for j in range(n)] for i in range(n)], list(b)))


def _solve_spd_lists(a: list, b: list) -> list:
    """:func:`solve_spd` on scalars: a nested list (n x n, lower triangle read), b a list (n)."""
    n = len(b)
    low = [[None] * n for _ in range(n)]
    for j in range(n):
        d = a[j][j] - sum(low[j][k] * low[j][k] for k in range(j))
        ljj = jnp.sqrt(jnp.maximum(d, 1e-300))
        low[j][j] = ljj
        for i in range(j + 1, n):
            low[i][j] = (a[i][j] - sum(low[i][k] * low[j][k] for k in range(j))) / ljj
    y = []
    for i in range(n):  # L y = b
        y.append((b[i] - sum(low[i][k] * y[k] for k in range(i))) / low[i][i])
    x = [None] * n
    for i in reversed(range(n)):  # L^T x = y
        x[i] = (y[i] - sum(low[k][i] * x[k] for k in range(i + 1, n))) / low[i][i]
    return x


def _huber_rho(r: Array, delta: float) -> Array:
    a = jnp.abs(r)
    return jnp.where(a <= delta, r * r, 2.0 * delta * a - delta * delta)


def levenberg_marquardt(
    residual_fn,
    pose: Pose,
    weights: Array,
    iters: int = 10,
    huber: float | None = None,
    residual_jacobian_fn=None,
) -> Fit:
    """Minimise sum_i w_i rho(r_i(pose)) by Levenberg-Marquardt (Marquardt scaling, IRLS for Huber).

    Args:
        residual_fn: pose -> (m,) raw residuals [px].
        pose: initial :class:`Pose`.
        weights: (m,) non-negative weights (0 removes a residual).
        iters: fixed number of iterations (a rejected step only raises the damping).
        huber: Huber threshold [px], or None for least squares.
        residual_jacobian_fn: optional pose -> (residuals (m,), their Jacobian (m, 6) over the
            left perturbation (dw, dt) at 0); None: forward-mode autodiff of ``residual_fn``.
    """
    dtype = pose.translation.dtype

    def rho(r):
        return r * r if huber is None else _huber_rho(r, huber)

    def cost(p):
        return jnp.sum(weights * rho(residual_fn(p)))

    def irls(r):
        if huber is None:
            return weights
        a = jnp.abs(r)
        return weights * jnp.where(a <= huber, 1.0, huber / jnp.maximum(a, huber))

    zero = jnp.zeros(6, dtype)

    def residual_jacobian(p):
        if residual_jacobian_fn is not None:
            return residual_jacobian_fn(p)
        return residual_fn(p), jax.jacfwd(lambda d: residual_fn(retract(p, d)))(zero)

    def step(carry, _):
        p, lam, c = carry
        r, jac = residual_jacobian(p)
        w = irls(r)
        a = jac.T @ (w[:, None] * jac)
        g = jac.T @ (w * r)
        damp = lam * (jnp.diag(a) + 1e-12)
        delta = -solve_spd(a + jnp.diag(damp), g)
        new = retract(p, delta)
        c_new = cost(new)
        ok = jnp.isfinite(c_new) & (c_new < c)
        p = jax.tree.map(lambda x, y: jnp.where(ok, x, y), new, p)
        lam = jnp.where(ok, lam * 0.3, lam * 10.0)
        return (p, lam, jnp.where(ok, c_new, c)), None

    (p, _, c), _ = jax.lax.scan(step, (pose, jnp.asarray(1e-3, dtype), cost(pose)), None, iters)
    r, jac = residual_jacobian(p)
    w = irls(r)
    info = jac.T @ (w[:, None] * jac)
    used = jnp.maximum(jnp.sum(weights > 0), 1)
    rms = jnp.sqrt(jnp.sum(jnp.where(weights > 0, r * r, 0.0)) / used)
    return Fit(p, c, rms, info)


# ---------------------------------------------------------------------------------------------
# Residuals.


def corner_residuals(pose: Pose, pixels: Array, size, intrinsics: Array) -> Array:
    """(16,) reprojection errors [px] of the 8 corners (x and y interleaved per corner)."""
    return (project_corners(pose, size, intrinsics) - pixels).reshape(-1)


def edge_residuals(pose: Pose, endpoints: Array, edge_ids: Array, size, intrinsics: Array) -> Array:
    """(2 M,) signed distances [px] of segment end points (M, 2, 2) to their model edges' lines.

    ``edge_ids`` (M,) indexes the 12 edges (``box_model.EDGES``); padded rows carry any id and a
    zero weight.
    """
    corners = project_corners(pose, size, intrinsics)  # (8, 2)
    a = corners[jnp.asarray(EDGES)[edge_ids, 0]]  # (M, 2)
    b = corners[jnp.asarray(EDGES)[edge_ids, 1]]
    d = b - a
    length = jnp.sqrt(jnp.sum(d * d, axis=-1) + 1e-12)
    rel = endpoints - a[:, None, :]  # (M, 2, 2)
    cross = d[:, None, 0] * rel[..., 1] - d[:, None, 1] * rel[..., 0]
    return (cross / length[:, None]).reshape(-1)


def _so3_exp_lists(w: list) -> list:
    """:func:`so3_exp` on scalars: w a list (3) [rad] -> nested list (3 x 3)."""
    theta2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    small = theta2 < 1e-12
    theta = jnp.sqrt(jnp.where(small, 1.0, theta2))
    a = jnp.where(small, 1.0 - theta2 / 6.0, jnp.sin(theta) / theta)
    b = jnp.where(
        small, 0.5 - theta2 / 24.0, (1.0 - jnp.cos(theta)) / jnp.where(small, 1.0, theta2)
    )
    # I + a [w]x + b [w]x^2, [w]x^2 = w w^T - |w|^2 I
    kx = [[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]]
    return [
        [
            (1.0 if i == j else 0.0)
            + a * kx[i][j]
            + b * (w[i] * w[j] - (theta2 if i == j else 0.0))
            for j in range(3)
        ]
        for i in range(3)
    ]


def _projection_terms(rot: list, t: list, obj: list, uv: tuple, intrinsics: Array, jacobian: bool):
    """Reprojection residuals (u, v) [px] of object points and, if ``jacobian``, their
    derivatives over the left perturbation (dw, dt) of the pose (two lists of six): with
    q = R X and P = q + t, dP/ddw = -[q]x and dP/ddt = I, so d(u)/d(dw) = q x d(u)/dP (d(u, v)/dP
    the pinhole derivative of :func:`hec_jax.geometry.camera.project_to_pixels`, skew included).

    ``rot`` nested list (3 x 3) and ``t`` list (3) of scalars; ``obj`` the three coordinates
    [m] and ``uv`` the measured pixels [px], each an (n,) array or one scalar (then everything
    is scalar: under ``vmap`` one vector over the batch).
    """
    k = intrinsics
    fx, skew, cx, fy, cy = k[0, 0], k[0, 1], k[0, 2], k[1, 1], k[1, 2]
    q = [rot[i][0] * obj[0] + rot[i][1] * obj[1] + rot[i][2] * obj[2] for i in range(3)]
    iz = 1.0 / (q[2] + t[2])
    x, y = (q[0] + t[0]) * iz, (q[1] + t[1]) * iz
    ru = fx * x + skew * y + cx - uv[0]
    rv = fy * y + cy - uv[1]
    if not jacobian:
        return ru, rv, None, None
    zero = jnp.zeros_like(iz)
    jac = []
    for d in ((fx * iz, skew * iz, -(fx * x + skew * y) * iz), (zero, fy * iz, -fy * y * iz)):
        jac.append(
            [q[1] * d[2] - q[2] * d[1], q[2] * d[0] - q[0] * d[2], q[0] * d[1] - q[1] * d[0], *d]
        )
    return ru, rv, jac[0], jac[1]


def _corner_terms(rot: list, t: list, pixels: Array, size, intrinsics: Array, jacobian: bool):
    """:func:`_projection_terms` of the 8 corners ((8,) arrays) against ``pixels`` (8, 2)."""
    obj = CUBE_CORNERS_UNIT * size  # (8, 3) [m]
    uv = (pixels[:, 0], pixels[:, 1])
    return _projection_terms(rot, t, [obj[:, i] for i in range(3)], uv, intrinsics, jacobian)


def _materialize(x, one):
    """``x / one`` with ``one`` equal to 1 at run time: the same value, bit for bit. XLA counts a
    division as expensive and so computes ``x`` once into a buffer; without it, it fuses (and
    recomputes) the whole expression of ``x`` into each of its consumers.
    """
    return x / one


def _corner_project(rot: list, t: list, size) -> tuple[list, list, list]:
    """Normalised image points (x, y) and inverse depths of the 8 corners at a pose (lists of 8).
    The divisions make XLA compute them once, for all their uses.
    """
    half = 0.5 * size
    col = [[half * rot[i][j] for i in range(3)] for j in range(3)]  # R e_j size / 2
    xs, ys, izs = [], [], []
    for corner in CUBE_CORNERS_UNIT:
        p = [
            t[i] + sum(c[i] if s > 0 else -c[i] for c, s in zip(col, corner, strict=True))
            for i in range(3)
        ]
        xs.append(p[0] / p[2])
        ys.append(p[1] / p[2])
        izs.append(1.0 / p[2])
    return xs, ys, izs


def _corner_cost(xs, ys, pixels, weights, intrinsics) -> tuple[Array, Array]:
    """(sum w r^2, sum of r^2 over the corners of non-zero weight) from the projected corners."""
    k = intrinsics
    fx, skew, cx, fy, cy = k[0, 0], k[0, 1], k[0, 2], k[1, 1], k[1, 2]
    cost = rss = 0.0
    for n in range(8):
        ru = fx * xs[n] + skew * ys[n] + cx - pixels[n, 0]
        rv = fy * ys[n] + cy - pixels[n, 1]
        sq = ru * ru + rv * rv
        cost = cost + weights[n] * sq
        rss = rss + jnp.where(weights[n] > 0, sq, 0.0)
    return cost, rss


def _corner_normal(rot: list, xs, ys, izs, pixels, weights, size, intrinsics):
    """Normal equations of the corner reprojection error at a pose: a = J^T W J (nested 6 x 6,
    symmetric) and g = J^T W r (6), with the analytic Jacobian of :func:`_projection_terms` (left
    perturbation (dw, dt): d(u)/d(dw) = q x d(u)/dP, q = R X) from the projected corners, its
    known zeros left out.
    """
    k = intrinsics
    fx, skew, cx, fy, cy = k[0, 0], k[0, 1], k[0, 2], k[1, 1], k[1, 2]
    half = 0.5 * size
    col = [[half * rot[i][j] for i in range(3)] for j in range(3)]
    a = [[0.0] * 6 for _ in range(6)]
    g = [0.0] * 6
    for n, corner in enumerate(CUBE_CORNERS_UNIT):
        q = [
            sum(c[i] if s > 0 else -c[i] for c, s in zip(col, corner, strict=True))
            for i in range(3)
        ]
        x, y, iz, w = xs[n], ys[n], izs[n], weights[n]
        up = fx * x + skew * y
        ru, rv = up + cx - pixels[n, 0], fy * y + cy - pixels[n, 1]
        du = (fx * iz, skew * iz, -up * iz)  # d(u)/dP
        dv1, dv2 = fy * iz, -fy * y * iz  # d(v)/dP = (0, dv1, dv2)
        ju = [q[1] * du[2] - q[2] * du[1], q[2] * du[0] - q[0] * du[2], q[0] * du[1] - q[1] * du[0]]
        ju += list(du)
        jv = [q[1] * dv2 - q[2] * dv1, -q[0] * dv2, q[0] * dv1, None, dv1, dv2]
        for r, jac in ((ru, ju), (rv, jv)):
            for i in range(6):
                if jac[i] is None:
                    continue
                wj = w * jac[i]
                g[i] = g[i] + wj * r
                for m in range(i + 1):
                    if jac[m] is not None:
                        a[i][m] = a[i][m] + wj * jac[m]
    a = [[a[i][m] if m <= i else a[m][i] for m in range(6)] for i in range(6)]
    return a, g


def _corner_lm(pose: Pose, pixels, weights, size, intrinsics, iters: int):
    """The iteration of :func:`levenberg_marquardt` (least squares, Marquardt scaling, a rejected
    step only raises the damping) on the corners, with the analytic Jacobian, the normal
    equations, the Cholesky step and the pose update all on scalars: under ``vmap`` every
    quantity is one vector over the batch, so a batch runs as fused vector code.

    The projected corners (:func:`_corner_project`) are carried with the pose, so the normal
    equations of the next step reuse those of the accepted trial pose; the trial cost is
    materialised once (:func:`_materialize`) for the acceptance test and its many selects.
    Returns (R (3, 3), t (3,), cost, rss, projected corners (xs, ys, izs)).
    """
    dtype = pose.translation.dtype

    def mat(rot9):
        return [list(rot9[3 * i : 3 * i + 3]) for i in range(3)]

    def project(rot9, t3):
        xs, ys, izs = _corner_project(mat(rot9), list(t3), size)
        c, _ = _corner_cost(xs, ys, pixels, weights, intrinsics)
        return (tuple(xs), tuple(ys), tuple(izs)), c

    def step(carry, _):
        rot9, t3, lam, proj, c = carry
        rot3 = mat(rot9)
        a, g = _corner_normal(rot3, *proj, pixels, weights, size, intrinsics)
        damped = [
            [a[i][j] + (lam * (a[i][i] + 1e-12) if i == j else 0.0) for j in range(6)]
            for i in range(6)
        ]
        delta = [-x for x in _solve_spd_lists(damped, g)]
        e = _so3_exp_lists(delta[:3])
        new_rot = tuple(
            sum(e[i][k] * rot3[k][j] for k in range(3)) for i in range(3) for j in range(3)
        )
        new_t = tuple(t3[i] + delta[3 + i] for i in range(3))
        new_proj, c_new = project(new_rot, new_t)
        # a runtime 1 (finite lam: min(lam, 1) * 0 == 0)
        c_new = _materialize(c_new, 1.0 + 0.0 * jnp.minimum(lam, 1.0))
        ok = jnp.isfinite(c_new) & (c_new < c)
        pick = lambda x, y: jnp.where(ok, x, y)  # noqa: E731
        rot9, t3, proj, c = jax.tree.map(
            pick, (new_rot, new_t, new_proj, c_new), (rot9, t3, proj, c)
        )
        lam = jnp.where(ok, lam * 0.3, lam * 10.0)
        return (rot9, t3, lam, proj, c), None

    r0, t0 = pose.rotation, pose.translation
    rot9 = tuple(r0[i, j] for i in range(3) for j in range(3))
    t3 = tuple(t0[i] for i in range(3))
    proj, c = project(rot9, t3)
    init = (rot9, t3, jnp.asarray(1e-3, dtype), proj, c)
    (rot9, t3, _, proj, c), _ = jax.lax.scan(step, init, None, iters)
    _, rss = _corner_cost(proj[0], proj[1], pixels, weights, intrinsics)
    rot = jnp.stack([jnp.stack(row) for row in mat(rot9)])
    return rot, jnp.stack(t3), c, rss, proj


def _corner_summary(rot, t, pixels, weights, size, intrinsics):
    """(rms, information (6, 6), jacobian (16, 6), residuals (16,)) at a pose."""
    rot3 = [[rot[i, j] for j in range(3)] for i in range(3)]
    ru, rv, ju, jv = _corner_terms(rot3, [t[i] for i in range(3)], pixels, size, intrinsics, True)
    r = jnp.stack([ru, rv], -1).reshape(-1)
    jac = jnp.stack([jnp.stack(ju, -1), jnp.stack(jv, -1)], 1).reshape(16, 6)
    wv = jnp.repeat(weights, 2)
    used = jnp.maximum(jnp.sum(wv > 0), 1)
    rms = jnp.sqrt(jnp.sum(jnp.where(wv > 0, r * r, 0.0)) / used)
    return rms, jac.T @ (wv[:, None] * jac), jac, r


def refine_corners(
    pose: Pose, pixels: Array, weights: Array, size, intrinsics: Array, iters: int = 10
) -> Fit:
    """LM on the reprojection error of the corners with per-corner weights (8,).

    The iteration (:func:`_corner_lm`) is not differentiated through: the derivative is the
    implicit one of the optimum (:func:`_refine_corners_jvp`), exact at convergence (matches
    central differences in ``tests/test_eye_refine.py``) and cheap to compile.
    """
    dtype = pose.translation.dtype
    return _refine_corners(
        iters, pose, pixels, weights, jnp.asarray(size, dtype), jnp.asarray(intrinsics, dtype)
    )


@partial(jax.custom_jvp, nondiff_argnums=(0,))
def _refine_corners(iters, pose, pixels, weights, size, intrinsics):
    rot, t, c, rss, proj = _corner_lm(pose, pixels, weights, size, intrinsics, iters)
    a, _ = _corner_normal(_lists(rot), *proj, pixels, weights, size, intrinsics)
    used = jnp.maximum(jnp.sum(weights > 0), 1)
    return Fit(Pose(rot, t), c, jnp.sqrt(rss / (2 * used)), _mat(a))


@_refine_corners.defjvp
def _refine_corners_jvp(iters, primals, tangents):
    """Implicit derivative at the optimum: the cost's gradient over the pose perturbation,
    g = J^T W r, vanishes there, so dp = -(dg/dp)^-1 (dg/d(data) d(data)) with the exact Hessian
    dg/dp (curvature of the residuals included); the start pose has no influence.
    """
    pose, pixels, weights, size, intrinsics = primals
    _, d_pixels, d_weights, d_size, d_k = tangents
    fit = _refine_corners(iters, *primals)
    rot, t = fit.pose
    zero6 = jnp.zeros(6, rot.dtype)

    def gradient(delta, px, w, s, k):
        p = retract(Pose(rot, t), delta)
        rot3 = [[p.rotation[i, j] for j in range(3)] for i in range(3)]
        ru, rv, ju, jv = _corner_terms(rot3, [p.translation[i] for i in range(3)], px, s, k, True)
        return jnp.stack([jnp.sum(w * (ju[i] * ru + jv[i] * rv)) for i in range(6)])

    hess = jax.jacfwd(gradient)(zero6, pixels, weights, size, intrinsics)
    _, d_g = jax.jvp(
        lambda px, w, s, k: gradient(zero6, px, w, s, k),
        (pixels, weights, size, intrinsics),
        (d_pixels, d_weights, d_size, d_k),
    )
    delta = -jnp.linalg.solve(0.5 * (hess + hess.T), d_g)
    zero = jnp.zeros((), rot.dtype)
    hat = jnp.stack(
        [
            jnp.stack([zero, -delta[2], delta[1]]),
            jnp.stack([delta[2], zero, -delta[0]]),
            jnp.stack([-delta[1], delta[0], zero]),
        ]
    )
    d_rot, d_t = hat @ rot, delta[3:]

    def summary(rot, t, px, w, s, k):
        rms, info, _, r = _corner_summary(rot, t, px, w, s, k)
        return jnp.sum(jnp.repeat(w, 2) * r * r), rms, info

    _, (d_c, d_rms, d_info) = jax.jvp(
        summary,
        (rot, t, pixels, weights, size, intrinsics),
        (d_rot, d_t, d_pixels, d_weights, d_size, d_k),
    )
    return fit, Fit(Pose(d_rot, d_t), d_c, d_rms, d_info)


def edge_lines(pose: Pose, size, intrinsics: Array) -> tuple[Array, Array]:
    """Lines of the 12 projected edges: unit normals (12, 2) and offsets (12,) [px], such that
    ``normal . x - offset`` is the signed distance [px] of :func:`edge_residuals` (the cross
    product of the edge's direction with ``x - a`` over its length, ``a`` its first corner).
    """
    corners = project_corners(pose, size, intrinsics)  # (8, 2)
    a, b = corners[_EDGE_FIRST], corners[_EDGE_SECOND]
    d = b - a
    length = jnp.sqrt(jnp.sum(d * d, axis=-1) + 1e-12)
    normal = jnp.stack([-d[:, 1], d[:, 0]], -1) / length[:, None]
    return normal, jnp.sum(normal * a, axis=-1)


_EDGE_FIRST, _EDGE_SECOND = EDGES[:, 0], EDGES[:, 1]


def refine_edges(
    pose: Pose,
    endpoints: Array,
    edge_ids: Array,
    weights: Array,
    size,
    intrinsics: Array,
    iters: int = 8,
    huber: float = 1.0,
) -> Fit:
    """Robust LM on point-to-model-edge distances of associated segment end points.

    endpoints (M, 2, 2) [px], edge_ids (M,), weights (M,) (e.g. segment length, 0 for padding).
    """
    w = jnp.repeat(weights, 2)
    return levenberg_marquardt(
        lambda p: edge_residuals(p, endpoints, edge_ids, size, intrinsics), pose, w, iters, huber
    )


def refine_edges_batched(
    pose: Pose,
    endpoints: Array,
    edge_ids: Array,
    weights: Array,
    size,
    intrinsics: Array,
    iters: int = 8,
    huber: float = 1.0,
) -> Fit:
    """:func:`refine_edges` in a form for a vmapped batch of starts (the tracker's multi-start
    searches, ``TrackConfig.batched_search``): the same steps, damping, acceptance, cost, rms
    and information, equal to round-off (``tests/test_eye_refine.py``).

    The Jacobian is taken of the 12 edges' lines (:func:`edge_lines`, forward mode over the
    6-vector (dw, dt)), and each segment picks its line and the line's derivatives by a one-hot
    product over the 12 edges instead of a gather: under ``vmap`` a gather runs as a loop over
    the batch on the CPU (timings in ``docs/eye_randomized.md``; a single pose gains nothing).
    ``edge_ids`` outside 0-11 pick no line (residual 0).
    """
    dtype = pose.translation.dtype
    onehot = (edge_ids[:, None] == jnp.arange(12)[None, :]).astype(dtype)  # (M, 12)
    zero = jnp.zeros(6, dtype)

    def pick(x):  # per edge (12, ...) -> per segment (M, ...)
        return jnp.tensordot(onehot, x, axes=1)

    def distances(normal, offset):  # of the end points to their lines, per edge (12, 2, ...)
        # and (12, ...): (M, 2, ...) [px]
        return jnp.einsum("mpk,mk...->mp...", endpoints, pick(normal)) - pick(offset)[:, None]

    def residuals(p):  # (2 M,) [px], as edge_residuals
        return distances(*edge_lines(p, size, intrinsics)).reshape(-1)

    def residuals_jacobian(p):  # (2 M,), (2 M, 6): d r / d (dw, dt) at 0
        d_lines = jax.jacfwd(lambda d: edge_lines(retract(p, d), size, intrinsics))(zero)
        return residuals(p), distances(*d_lines).reshape(-1, 6)

    w = jnp.repeat(weights, 2)
    return levenberg_marquardt(residuals, pose, w, iters, huber, residuals_jacobian)


# ---------------------------------------------------------------------------------------------
# Initialisation.
#
# Written on scalars (nested lists of arrays, a Python loop over the 8 corners, 6 faces, 12
# edges): under ``vmap`` every quantity is one vector over the batch, and a data-dependent choice
# (largest face, best edge pair) is a chain of selects instead of a gather, a sort or a small
# batched matrix product (each of those runs as a slow per-item loop on the CPU).


def _select(index: Array, options: list):
    """``options[index]`` for a traced integer index (a chain of selects; the last match wins, and
    the indices are distinct).
    """
    out = options[0]
    for i in range(1, len(options)):
        out = jnp.where(index == i, options[i], out)
    return out


def _face_visibility_lists(pixels: Array) -> tuple[list, list]:
    """:func:`hec_jax.geometry.box_model.image_face_visibility` on scalars: (6 visible, 6 areas)."""
    p = [(pixels[c, 0], pixels[c, 1]) for c in range(8)]
    visible, area = [], []
    for f in range(6):
        ids = FACES[f]
        shoelace = 0.5 * sum(
            p[ids[k]][0] * p[ids[(k + 1) % 4]][1] - p[ids[k]][1] * p[ids[(k + 1) % 4]][0]
            for k in range(4)
        )
        signed = -shoelace * float(FACE_ORIENTATION[f])
        visible.append(signed > 0)
        area.append(jnp.maximum(signed, 0.0))
    return visible, area


def _corner_visibility_lists(visible: list) -> list:
    """A corner is visible iff one of its faces is (8 bools)."""
    return [
        functools.reduce(jnp.logical_or, [visible[f] for f in range(6) if c in FACES[f]])
        for c in range(8)
    ]


def _edge_visibility_lists(visible: list) -> list:
    """An edge of a convex box is visible iff one of its two faces is (12 bools)."""
    return [visible[f0] | visible[f1] for f0, f1 in EDGE_FACES]


def _cross(a, b) -> list:
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]


def _norm(a) -> Array:
    return jnp.sqrt(sum(x * x for x in a))


def _face_pose_lists(x: list, obj: list) -> tuple[list, list]:
    """:func:`face_pose_from_homography` on scalars: ``x`` the 4 corners' normalised image points
    (pairs), ``obj`` their object points (triples) [m], a parallelogram in cyclic order. Returns
    (R nested 3 x 3, t (3)).
    """
    u = [obj[1][i] - obj[0][i] for i in range(3)]
    v = [obj[3][i] - obj[0][i] for i in range(3)]
    su, sv = _norm(u), _norm(v)
    u_hat, v_hat = [c / su for c in u], [c / sv for c in v]
    w_hat = _cross(u_hat, v_hat)
    # The face plane in units of its edges is the unit square (0,0), (1,0), (1,1), (0,1): the DLT
    # system (h33 = 1, 8 equations, 8 unknowns) has the closed-form solution of the square-to-
    # quadrilateral map (Heckbert 1989), the same solution as the normal equations.
    (x0, y0), (x1, y1), (x2, y2), (x3, y3) = x
    sx, sy = x0 - x1 + x2 - x3, y0 - y1 + y2 - y3
    dx1, dx2, dy1, dy2 = x1 - x2, x3 - x2, y1 - y2, y3 - y2
    den = dx1 * dy2 - dx2 * dy1
    g, h = (sx * dy2 - dx2 * sy) / den, (dx1 * sy - sx * dy1) / den
    one = jnp.ones_like(g)
    hm = [  # columns: r_u / su, r_v / sv (plane in [m] again), p0
        [(x1 - x0 + g * x1) / su, (x3 - x0 + h * x3) / sv, x0],
        [(y1 - y0 + g * y1) / su, (y3 - y0 + h * y3) / sv, y0],
        [g / su, h / sv, one],
    ]
    col = [[hm[i][j] for i in range(3)] for j in range(3)]
    scale = 2.0 / (_norm(col[0]) + _norm(col[1]))
    scale = scale * jnp.where(hm[2][2] < 0, -1.0, 1.0)  # p0 (third column) in front: z > 0
    col = [[c * scale for c in cj] for cj in col]
    # orthonormal pair closest to the (noisy) columns r_u, r_v, errors split evenly between them
    r_u = [c / _norm(col[0]) for c in col[0]]
    r_v = [c / _norm(col[1]) for c in col[1]]
    c = [a + b for a, b in zip(r_u, r_v, strict=True)]
    d = [a - b for a, b in zip(r_u, r_v, strict=True)]
    nc, nd = _norm(c), _norm(d)
    c, d = [a / nc for a in c], [a / nd for a in d]
    root2 = jnp.sqrt(jnp.asarray(2.0, g.dtype))
    e_u = [(a + b) / root2 for a, b in zip(c, d, strict=True)]
    e_v = [(a - b) / root2 for a, b in zip(c, d, strict=True)]
    e_w = _cross(e_u, e_v)
    rot = [
        [e_u[i] * u_hat[j] + e_v[i] * v_hat[j] + e_w[i] * w_hat[j] for j in range(3)]
        for i in range(3)
    ]
    t = [col[2][i] - sum(rot[i][j] * obj[0][j] for j in range(3)) for i in range(3)]
    return rot, t


def _mat(rows: list) -> Array:
    return jnp.stack([jnp.stack(row, -1) for row in rows], -2)


def face_pose_from_homography(pixels4: Array, face: Array, size, intrinsics: Array) -> Pose:
    """Box pose from the 4 image corners (4, 2) [px] of one face (corner ids ``face`` (4,), in
    cyclic order).

    DLT homography from the face plane to normalised image coordinates, H ~ [r_u r_v p0] (with
    h33 = 1; the plane coordinates of the face are the unit square, so the 8 x 8 system has a
    closed-form solution), then the nearest orthonormal pair to (r_u, r_v) (the symmetric split
    of their angle error). Sign chosen so that the face lies in front of the camera.
    """
    obj = box_corners(size)[face]  # (4, 3)
    x = pixel_to_normalized(pixels4, intrinsics)  # (4, 2)
    rot, t = _face_pose_lists(
        [(x[k, 0], x[k, 1]) for k in range(4)], [[obj[k, i] for i in range(3)] for k in range(4)]
    )
    return Pose(_mat(rot), jnp.stack(t, -1))


def largest_visible_face(pixels: Array) -> tuple[Array, Array, Array]:
    """(face index, (6,) visible, (6,) area) of the largest visible face in the image."""
    visible, area = _face_visibility_lists(pixels)
    return _largest(visible, area), jnp.stack(visible, -1), jnp.stack(area, -1)


def _largest(visible: list, area: list) -> Array:
    """Index of the largest visible face (``jnp.argmax``: a reduction, which XLA computes once
    rather than in each of its uses).
    """
    return jnp.argmax(
        jnp.stack([jnp.where(v, a, -1.0) for v, a in zip(visible, area, strict=True)])
    )


def _init_pose(normalized: list, visible: list, area: list, size) -> tuple[list, list]:
    """Homography start on the largest visible face: (R nested 3 x 3, t (3)) from the 8 corners'
    normalised image points (pairs) and the face visibility lists.
    """
    face = _largest(visible, area)
    x = [
        tuple(_select(face, [normalized[FACES[f][k]][i] for f in range(6)]) for i in range(2))
        for k in range(4)
    ]
    obj = [
        [
            _select(face, [float(CUBE_CORNERS_UNIT[FACES[f][k]][i]) for f in range(6)]) * size
            for i in range(3)
        ]
        for k in range(4)
    ]
    return _face_pose_lists(x, obj)


def _normalized_lists(pixels: Array, intrinsics: Array) -> list:
    x = pixel_to_normalized(pixels, intrinsics)
    return [(x[c, 0], x[c, 1]) for c in range(8)]


def _pose_from_corners(pixels, normalized, visible, area, size, intrinsics, iters):
    rot, t = _init_pose(normalized, visible, area, size)
    wc = jnp.stack(_corner_visibility_lists(visible), -1).astype(pixels.dtype)
    return refine_corners(
        Pose(_mat(rot), jnp.stack(t, -1)), pixels, wc, size, intrinsics, iters
    ), wc


def pose_from_corners(pixels: Array, size, intrinsics: Array, iters: int = 10) -> tuple[Fit, Array]:
    """Pose from labelled corner pixels (8, 2): homography on the largest visible face, then LM on
    all visible corners. Returns (fit, (8,) visible corners).
    """
    visible, area = _face_visibility_lists(pixels)
    normalized = _normalized_lists(pixels, intrinsics)
    return _pose_from_corners(pixels, normalized, visible, area, size, intrinsics, iters)


def _best_parallel_pair_lists(pixels: Array, visible_edges: list) -> list:
    """Corner ids [A, B, C, D] of the two longest visible image edges of one family (the family
    whose second-longest visible edge is longest; ties to the lower index, as a stable sort).

    The three choices are ``jnp.argmax`` reductions: XLA computes a reduction once, where it
    would recompute a chain of selects in every one of its many uses.
    """
    length = []
    for e, (a, b) in enumerate(EDGES):
        d = [pixels[b, i] - pixels[a, i] for i in range(2)]
        length.append(jnp.where(visible_edges[e], jnp.sqrt(d[0] * d[0] + d[1] * d[1]), 0.0))

    def second_largest(a, b, c, d):
        return jnp.maximum(
            jnp.minimum(jnp.maximum(a, b), jnp.maximum(c, d)),
            jnp.maximum(jnp.minimum(a, b), jnp.minimum(c, d)),
        )

    fam = jnp.argmax(jnp.stack([second_largest(*length[4 * f : 4 * f + 4]) for f in range(3)]))
    sel = [_select(fam, [length[4 * f + k] for f in range(3)]) for k in range(4)]
    i1 = jnp.argmax(jnp.stack(sel))  # first of a stable descending sort
    i2 = jnp.argmax(jnp.stack([jnp.where(i1 == k, -jnp.inf, x) for k, x in enumerate(sel)]))
    i, j = 4 * fam + i1, 4 * fam + i2
    ends = [[int(EDGES[e][s]) for e in range(12)] for s in range(2)]
    return [_select(i, ends[0]), _select(i, ends[1]), _select(j, ends[0]), _select(j, ends[1])]


def _best_parallel_pair(pixels: Array, visible_edges: Array) -> Array:
    """Corner ids (A, B, C, D) (4,) of the two longest visible image edges of one family."""
    return jnp.stack(_best_parallel_pair_lists(pixels, [visible_edges[e] for e in range(12)]))


def _lists(m: Array) -> list:
    return [[m[i, j] for j in range(3)] for i in range(3)]


def _matmul(a: list, b: list) -> list:
    return [[sum(a[i][k] * b[k][j] for k in range(3)) for j in range(3)] for i in range(3)]


class TwoFrameMotion(NamedTuple):
    """Motion between two images of the box (a pytree).

    Attributes:
        rotation: (3, 3) Phi of Eq. 1 (camera frame), P' = Phi P + Gamma.
        translation: (3,) Gamma of Eq. 1 [m].
        pose_before, pose_after: the refined box poses.
        used_paper_init: bool, the paper's estimate gave the better start for the second frame.
        valid: bool, finite and with a small reprojection residual.
    """

    rotation: Array
    translation: Array
    pose_before: Pose
    pose_after: Pose
    used_paper_init: Array
    valid: Array


def two_frame_motion(
    pixels_before: Array,
    pixels_after: Array,
    size,
    intrinsics: Array,
    iters: int = 10,
    max_rms_px: float = 5.0,
) -> TwoFrameMotion:
    """Phi, Gamma (Eq. 1) from labelled corner pixels (8, 2) of the box in two images.

    Per image: the faces turned to the camera are read off the image (corner polygon orientation),
    the pose is initialised by a homography on the largest visible face and refined by LM on all
    visible corners. The second image is also started from the first pose moved by the paper's
    estimate (``estimate_motion_core`` on the longest visible parallel pair, |AB| = size); the
    start that ends with the lower cost wins. Jittable and vmappable.
    """
    vis_b, area_b = _face_visibility_lists(pixels_before)
    vis_a, area_a = _face_visibility_lists(pixels_after)
    norm_b = _normalized_lists(pixels_before, intrinsics)
    norm_a = _normalized_lists(pixels_after, intrinsics)
    fit0, _ = _pose_from_corners(pixels_before, norm_b, vis_b, area_b, size, intrinsics, iters)
    fit1, w1 = _pose_from_corners(pixels_after, norm_a, vis_a, area_a, size, intrinsics, iters)
    # The paper's method (Eqs. 7-38) on the best visible pair, as a second start.
    edges_b, edges_a = _edge_visibility_lists(vis_b), _edge_visibility_lists(vis_a)
    both = [b & a for b, a in zip(edges_b, edges_a, strict=True)]
    pair = _best_parallel_pair_lists(pixels_after, both)

    def points(normalized):
        return jnp.stack(
            [
                jnp.stack([_select(c, [normalized[k][i] for k in range(8)]) for i in range(2)], -1)
                for c in pair
            ],
            -2,
        )

    nb, na = points(norm_b), points(norm_a)
    est = estimate_motion_core(nb, na, jnp.asarray(size, nb.dtype))
    p0 = fit0.pose
    e, r0, t0 = _lists(est.rotation), _lists(p0.rotation), [p0.translation[i] for i in range(3)]
    start = Pose(
        _mat(_matmul(e, r0)),
        jnp.stack([sum(e[i][k] * t0[k] for k in range(3)) + est.translation[i] for i in range(3)]),
    )
    fit1p = refine_corners(start, pixels_after, w1, size, intrinsics, iters)
    use_paper = est.valid & jnp.isfinite(fit1p.cost) & (fit1p.cost < fit1.cost)
    fit1 = jax.tree.map(lambda x, y: jnp.where(use_paper, x, y), fit1p, fit1)
    p1 = fit1.pose
    phi = _matmul(_lists(p1.rotation), [list(row) for row in zip(*r0, strict=True)])  # R1 R0^T
    gamma = [p1.translation[i] - sum(phi[i][k] * t0[k] for k in range(3)) for i in range(3)]
    phi, gamma = _mat(phi), jnp.stack(gamma, -1)
    finite = jnp.all(jnp.isfinite(phi)) & jnp.all(jnp.isfinite(gamma))
    valid = finite & (fit0.rms < max_rms_px) & (fit1.rms < max_rms_px)
    valid = valid & (p0.translation[2] > 0) & (p1.translation[2] > 0)
    return TwoFrameMotion(phi, gamma, p0, p1, use_paper, valid)


__all__ = [
    "EDGE_FAMILY",
    "Fit",
    "TwoFrameMotion",
    "corner_residuals",
    "edge_lines",
    "edge_residuals",
    "face_pose_from_homography",
    "levenberg_marquardt",
    "pose_from_corners",
    "refine_corners",
    "refine_edges",
    "refine_edges_batched",
    "retract",
    "so3_exp",
    "so3_log",
    "two_frame_motion",
]
