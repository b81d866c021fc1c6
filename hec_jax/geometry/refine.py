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
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array

from hec_jax.geometry.box_model import (
    EDGE_FAMILY,
    EDGES,
    FACES,
    Pose,
    box_corners,
    corner_visibility,
    edge_visibility,
    image_face_visibility,
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
    """pose (+) delta, delta = (dw, dt) (6,): R <- exp(dw) R, t <- t + dt."""
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
    """x = a^-1 b for a small symmetric positive definite a (n, n), b (n,): Cholesky unrolled into
    elementwise operations, so that a vmapped batch runs as vector code instead of a loop of
    LAPACK calls (the LM step's 6x6 system)."""
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
    residual_fn, pose: Pose, weights: Array, iters: int = 10, huber: float | None = None
) -> Fit:
    """Minimise sum_i w_i rho(r_i(pose)) by Levenberg-Marquardt (Marquardt scaling, IRLS for Huber).

    Args:
        residual_fn: pose -> (m,) raw residuals [px].
        pose: initial :class:`Pose`.
        weights: (m,) non-negative weights (0 removes a residual).
        iters: fixed number of iterations (a rejected step only raises the damping).
        huber: Huber threshold [px], or None for least squares.
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

    def step(carry, _):
        p, lam, c = carry
        r, jac = residual_fn(p), jax.jacfwd(lambda d: residual_fn(retract(p, d)))(zero)
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
    r = residual_fn(p)
    jac = jax.jacfwd(lambda d: residual_fn(retract(p, d)))(zero)
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
    is scalar: under ``vmap`` one vector over the batch)."""
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


def _corner_rows(rot: list, t: list, pixels: Array, size, intrinsics: Array, jacobian: bool):
    """:func:`_corner_terms` on scalars: 16 residuals (u, v per corner, the order of
    :func:`corner_residuals`) and, if ``jacobian``, their 16 rows of 6."""
    res, rows = [], []
    for j in range(8):
        obj = [float(c) * size for c in CUBE_CORNERS_UNIT[j]]
        ru, rv, ju, jv = _projection_terms(
            rot, t, obj, (pixels[j, 0], pixels[j, 1]), intrinsics, jacobian
        )
        res += [ru, rv]
        rows += [ju, jv]
    return res, rows


def _corner_lm(pose: Pose, pixels, weights, size, intrinsics, iters: int):
    """The iteration of :func:`levenberg_marquardt` (least squares, Marquardt scaling, a rejected
    step only raises the damping) on the corners, with the analytic Jacobian, the normal
    equations, the Cholesky step and the pose update all on scalars: under ``vmap`` every
    quantity is one vector over the batch, so a batch runs as fused vector code. Returns
    (R (3, 3), t (3,), cost)."""
    dtype = pose.translation.dtype
    w = [weights[j // 2] for j in range(16)]

    def normal(rot, t):
        r, rows = _corner_rows(rot, t, pixels, size, intrinsics, True)
        a = [
            [
                sum(w[m] * rows[m][i] * rows[m][j] for m in range(16)) if j <= i else None
                for j in range(6)
            ]
            for i in range(6)
        ]
        a = [[a[i][j] if j <= i else a[j][i] for j in range(6)] for i in range(6)]
        g = [sum(w[m] * rows[m][i] * r[m] for m in range(16)) for i in range(6)]
        return a, g

    def cost(rot, t):
        r, _ = _corner_rows(rot, t, pixels, size, intrinsics, False)
        return sum(w[m] * r[m] * r[m] for m in range(16))

    def mat(rot9):
        return [list(rot9[3 * i : 3 * i + 3]) for i in range(3)]

    def step(carry, _):
        rot9, t3, lam, c = carry
        rot3 = mat(rot9)
        a, g = normal(rot3, list(t3))
        damped = [
            [a[i][j] + (lam * (a[i][i] + 1e-12) if i == j else 0.0) for j in range(6)]
            for i in range(6)
        ]
        delta = [-x for x in _solve_spd_lists(damped, g)]
        e = _so3_exp_lists(delta[:3])
        new_rot = [sum(e[i][k] * rot3[k][j] for k in range(3)) for i in range(3) for j in range(3)]
        new_t = [t3[i] + delta[3 + i] for i in range(3)]
        c_new = cost(mat(new_rot), new_t)
        ok = jnp.isfinite(c_new) & (c_new < c)
        rot9 = tuple(jnp.where(ok, x, y) for x, y in zip(new_rot, rot9, strict=True))
        t3 = tuple(jnp.where(ok, x, y) for x, y in zip(new_t, t3, strict=True))
        lam = jnp.where(ok, lam * 0.3, lam * 10.0)
        return (rot9, t3, lam, jnp.where(ok, c_new, c)), None

    r0, t0 = pose.rotation, pose.translation
    rot9 = tuple(r0[i, j] for i in range(3) for j in range(3))
    t3 = tuple(t0[i] for i in range(3))
    init = (rot9, t3, jnp.asarray(1e-3, dtype), cost(mat(rot9), list(t3)))
    (rot9, t3, _, c), _ = jax.lax.scan(step, init, None, iters)
    return jnp.stack([jnp.stack(row) for row in mat(rot9)]), jnp.stack(t3), c


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
    rot, t, c = _corner_lm(pose, pixels, weights, size, intrinsics, iters)
    rms, info, _, _ = _corner_summary(rot, t, pixels, weights, size, intrinsics)
    return Fit(Pose(rot, t), c, rms, info)


@_refine_corners.defjvp
def _refine_corners_jvp(iters, primals, tangents):
    """Implicit derivative at the optimum: the cost's gradient over the pose perturbation,
    g = J^T W r, vanishes there, so dp = -(dg/dp)^-1 (dg/d(data) d(data)) with the exact Hessian
    dg/dp (curvature of the residuals included); the start pose has no influence."""
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


# ---------------------------------------------------------------------------------------------
# Initialisation.


def face_pose_from_homography(pixels4: Array, face: Array, size, intrinsics: Array) -> Pose:
    """Box pose from the 4 image corners (4, 2) [px] of one face (corner ids ``face`` (4,)).

    DLT homography from the face plane to normalised image coordinates, H ~ [r_u r_v p0] (with
    h33 = 1, normal equations), then the nearest orthonormal pair to (r_u, r_v) (the symmetric
    split of their angle error). Sign chosen so that the face lies in front of the camera.
    """
    obj = box_corners(size)[face]  # (4, 3)
    u = obj[1] - obj[0]
    v = obj[3] - obj[0]
    su, sv = jnp.linalg.norm(u), jnp.linalg.norm(v)
    u_hat, v_hat = u / su, v / sv
    w_hat = jnp.cross(u_hat, v_hat)
    rel = obj - obj[:1]
    plane = jnp.stack([rel @ u_hat / su, rel @ v_hat / sv], -1)  # (4, 2) in [0, 1]
    x = pixel_to_normalized(pixels4, intrinsics)  # (4, 2)
    one, zero = jnp.ones(4, x.dtype), jnp.zeros(4, x.dtype)
    pa, pb = plane[:, 0], plane[:, 1]
    rows1 = jnp.stack([pa, pb, one, zero, zero, zero, -x[:, 0] * pa, -x[:, 0] * pb, -x[:, 0]], -1)
    rows2 = jnp.stack([zero, zero, zero, pa, pb, one, -x[:, 1] * pa, -x[:, 1] * pb, -x[:, 1]], -1)
    a = jnp.concatenate([rows1, rows2], 0)  # (8, 9)
    # h33 = 1 (the third column is the face corner p0, in front of the camera): 8 unknowns from
    # the normal equations, solved as vector code (a batched SVD is a loop of LAPACK calls)
    a8 = a[:, :8]
    h = jnp.concatenate([solve_spd(a8.T @ a8, -a8.T @ a[:, 8]), jnp.ones(1, a.dtype)])
    h = h.reshape(3, 3) / jnp.stack([su, sv, jnp.ones_like(su)])[None, :]  # plane in [m] again
    scale = 2.0 / (jnp.linalg.norm(h[:, 0]) + jnp.linalg.norm(h[:, 1]))
    h = h * scale * jnp.where(h[2, 2] < 0, -1.0, 1.0)  # p0 (third column) in front: z > 0
    # orthonormal pair closest to the (noisy) columns r_u, r_v, errors split evenly between them
    r_u = h[:, 0] / jnp.linalg.norm(h[:, 0])
    r_v = h[:, 1] / jnp.linalg.norm(h[:, 1])
    c = (r_u + r_v) / jnp.linalg.norm(r_u + r_v)
    d = (r_u - r_v) / jnp.linalg.norm(r_u - r_v)
    e_u, e_v = (c + d) / jnp.sqrt(2.0), (c - d) / jnp.sqrt(2.0)
    rot = jnp.stack([e_u, e_v, jnp.cross(e_u, e_v)], -1) @ jnp.stack([u_hat, v_hat, w_hat], 0)
    t = h[:, 2] - rot @ obj[0]
    return Pose(rot, t)


def largest_visible_face(pixels: Array) -> tuple[Array, Array, Array]:
    """(face index, (6,) visible, (6,) area) of the largest visible face in the image."""
    visible, area = image_face_visibility(pixels)
    return jnp.argmax(jnp.where(visible, area, -1.0)), visible, area


def pose_from_corners(pixels: Array, size, intrinsics: Array, iters: int = 10) -> tuple[Fit, Array]:
    """Pose from labelled corner pixels (8, 2): homography on the largest visible face, then LM on
    all visible corners. Returns (fit, (8,) visible corners)."""
    face, visible, _ = largest_visible_face(pixels)
    ids = jnp.asarray(FACES)[face]
    init = face_pose_from_homography(pixels[ids], ids, size, intrinsics)
    wc = corner_visibility(visible).astype(pixels.dtype)
    return refine_corners(init, pixels, wc, size, intrinsics, iters), wc


def _best_parallel_pair(pixels: Array, visible_edges: Array) -> Array:
    """Corner ids (A, B, C, D) (4,) of the two longest visible image edges of one family."""
    e = jnp.asarray(EDGES)
    length = jnp.linalg.norm(pixels[e[:, 1]] - pixels[e[:, 0]], axis=-1)
    length = jnp.where(visible_edges, length, 0.0).reshape(3, 4)
    top2 = jnp.sort(length, axis=-1)[:, -2:]  # (3, 2)
    fam = jnp.argmax(top2[:, 0])  # family whose second-longest edge is longest
    order = jnp.argsort(-length[fam])
    i, j = fam * 4 + order[0], fam * 4 + order[1]
    return jnp.stack([e[i, 0], e[i, 1], e[j, 0], e[j, 1]])


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
    fit0, _ = pose_from_corners(pixels_before, size, intrinsics, iters)
    fit1, w1 = pose_from_corners(pixels_after, size, intrinsics, iters)
    # The paper's method (Eqs. 7-38) on the best visible pair, as a second start.
    vis_b, _ = image_face_visibility(pixels_before)
    vis_a, _ = image_face_visibility(pixels_after)
    pair = _best_parallel_pair(pixels_after, edge_visibility(vis_b) & edge_visibility(vis_a))
    nb = pixel_to_normalized(pixels_before[pair], intrinsics)
    na = pixel_to_normalized(pixels_after[pair], intrinsics)
    est = estimate_motion_core(nb, na, jnp.asarray(size, nb.dtype))
    p0 = fit0.pose
    start = Pose(est.rotation @ p0.rotation, est.rotation @ p0.translation + est.translation)
    fit1p = refine_corners(start, pixels_after, w1, size, intrinsics, iters)
    use_paper = est.valid & jnp.isfinite(fit1p.cost) & (fit1p.cost < fit1.cost)
    fit1 = jax.tree.map(lambda x, y: jnp.where(use_paper, x, y), fit1p, fit1)
    p1 = fit1.pose
    phi = p1.rotation @ p0.rotation.T
    gamma = p1.translation - phi @ p0.translation
    finite = jnp.all(jnp.isfinite(phi)) & jnp.all(jnp.isfinite(gamma))
    valid = finite & (fit0.rms < max_rms_px) & (fit1.rms < max_rms_px)
    valid = valid & (p0.translation[2] > 0) & (p1.translation[2] > 0)
    return TwoFrameMotion(phi, gamma, p0, p1, use_paper, valid)


__all__ = [
    "EDGE_FAMILY",
    "Fit",
    "TwoFrameMotion",
    "corner_residuals",
    "edge_residuals",
    "face_pose_from_homography",
    "levenberg_marquardt",
    "pose_from_corners",
    "refine_corners",
    "refine_edges",
    "retract",
    "so3_exp",
    "so3_log",
    "two_frame_motion",
]
