"""Photometric refinement of a box's pose on a known background (pure JAX).

The edge fits (:mod:`hec_jax.geometry.refine`, :func:`hec_jax.geometry.track.refine_points`)
take each model edge's image position from a grey-level step. Where a face is seen nearly edge-on,
its two edges lie under a pixel or two apart and their steps merge, so the edge points of both
sit on the stronger step; a small box seen face on then comes out 5-50 cm nearer
than it is (docs/eye_randomized.md, "Thin faces"). Here the pose is fitted to the pixels
themselves instead:

    image(x) = sum_f c_f * g * a_f(x) + g * ((1 - sum_f a_f) * background)(x) + noise,

with ``a_f(x)`` the exact area of face ``f``'s projected polygon inside pixel ``x`` (so a face
0.3 px wide adds 0.3 of its colour to the pixels it crosses), ``g`` a Gaussian point spread of
``PhotometricConfig.blur_px``, ``background`` the image of the empty scene (the tracker's
``background``), and ``c_f`` each visible face's colour, one constant a face and channel, solved
linearly for every pose (variable projection). The pose minimises the Huber-weighted sum of
squared residuals over a square window by Levenberg-Marquardt with forward-mode derivatives
(the coverage is continuous and piecewise smooth in the pose).

What the model leaves out: texture (wood grain) and shading within a face, specular highlights,
the rod and anything else in front of the box, the box's shadow on the background, and motion
blur. The Huber weights cap what such pixels can pull; they are taken once, from the start
pose's residuals, so a start far off also down-weights the box's own edge pixels (a choice kept
as measured in session 93, not a tuned one). The background is blurred with the box, although
the empty scene's image already is a camera's: away from the box the model reads ``g * b`` where
the frame shows ``b`` (found in review; kept as measured).

Pixel convention: pixel (row i, column j) covers ``[j, j + 1) x [i, i + 1)`` in the intrinsics'
pixel coordinates (its centre at ``(j + 0.5, i + 0.5)``), the convention of the tests' drawn box
(tests/test_eye_photometric.py) and the one under which the scene's renders fit (the cost at
the true pose is lower with it: docs/eye_randomized.md, "Photometric refinement of small
boxes").
"""

from __future__ import annotations

import dataclasses
import functools
import time
from typing import NamedTuple

import cv2
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from hec_jax.geometry import box_model


@dataclasses.dataclass(frozen=True)
class PhotometricConfig:
    """Static settings of :func:`refine_photometric`.

    Attributes:
        window_px: side of the square image window the fit reads [px] (static: one compiled
            function a size).
        blur_px: sigma of the Gaussian point spread [px].
        iterations: the most Levenberg-Marquardt iterations (a rejected step raises the
            damping; ``relative_tolerance`` can stop them earlier).
        huber_sigmas: residuals beyond this many robust sigmas (1.4826 x the median absolute
            residual at the start pose, floored at ``min_noise``) are down-weighted (Huber).
        min_noise: floor of the robust sigma [grey levels].
        damping: the initial Levenberg-Marquardt damping (relative to the normal matrix's
            diagonal).
        relative_tolerance: the iterations stop early once a taken step lowers the cost by at
            most this fraction of it (0: always ``iterations``; 1e-5 chosen in session 94 by a
            rule written before its run on the development sequences, docs/eye_randomized.md
            "A faster photometric fit").
        margin_px: :func:`refine_measurements` refines a frame only where the measured pose's
            projected box is at most ``window_px - 2 margin_px`` across (larger boxes keep
            their edge fit); the window is centred on it, so the box lies about this far inside
            all round, except where the window is moved back into the frame at its border (a
            fit whose corners leave the window is not valid).
    """

    window_px: int = 48
    blur_px: float = 0.8
    iterations: int = 10
    huber_sigmas: float = 3.0
    min_noise: float = 1.0
    damping: float = 1e-3
    margin_px: int = 4
    relative_tolerance: float = 1e-5

    def __post_init__(self):
        if int(self.window_px) != self.window_px or self.window_px < 8:
            raise ValueError(f"window_px must be an integer >= 8, got {self.window_px!r}")
        if not (0.0 <= self.blur_px <= 5.0):
            raise ValueError(f"blur_px must lie in [0, 5], got {self.blur_px!r}")
        if int(self.iterations) != self.iterations or self.iterations < 1:
            raise ValueError(f"iterations must be a positive integer, got {self.iterations!r}")
        if not self.huber_sigmas > 0 or not self.min_noise > 0 or not self.damping > 0:
            raise ValueError("huber_sigmas, min_noise and damping must be positive")
        if not 0.0 <= self.relative_tolerance < 1.0:
            raise ValueError(
                f"relative_tolerance must lie in [0, 1), got {self.relative_tolerance!r}"
            )
        if int(self.margin_px) != self.margin_px or not 0 <= 2 * self.margin_px < self.window_px:
            raise ValueError(
                f"margin_px must be an integer in [0, window_px / 2), got {self.margin_px!r}"
            )


class PhotometricFit(NamedTuple):
    """Result of :func:`refine_photometric`.

    Attributes:
        rotation: (3, 3) refined R (object axes in the camera frame).
        translation: (3,) refined t [m].
        cost: Huber-weighted sum of squared residuals at the refined pose [grey levels^2], with the
            weights of the start pose's residuals.
        start_cost: the same weights at the start pose, with the face colours solved unweighted
            (so it lies above the weighted cost the iterations compare, by 0.2-1.4% in a
            reviewer's runs; kept as measured).
        colours: (3, C) fitted colours of the three faces turned most towards the camera at the
            refined pose (a hidden one's is not determined).
        noise: the robust sigma of the start pose's residuals [grey levels] (floored at
            ``PhotometricConfig.min_noise``), which sets the Huber bar.
        valid: the fit is finite and its projection lies inside the window.
        steps: the iterations run (``cfg.iterations`` unless ``cfg.relative_tolerance`` stopped
            them early).
        information: (6, 6) Gauss-Newton information of the pose increment (dw, dt) [1/rad^2,
            1/m^2] at the refined pose: J^T W J / noise^2, J the residuals' derivatives (the
            colours solved at each pose), W the Huber weights. The increment is the edge fits'
            (R <- exp(dw) R, t <- t + dt: :func:`hec_jax.geometry.refine.retract`). Neighbouring
            pixels share their error (the blur, the model's omissions), so it over-counts them
            like the edge fits' information does; a consumer scales it.
    """

    rotation: Array
    translation: Array
    cost: Array
    start_cost: Array
    colours: Array
    noise: Array
    valid: Array
    steps: Array
    information: Array


def pixel_coverage(polygon: Array, offsets: Array) -> Array:
    """Exact area of a convex polygon inside unit pixels.

    Args:
        polygon: (K, 2) vertices [px] of a convex polygon, either turning sense.
        offsets: (N, 2) the pixels' centres [px]; pixel n is the unit square about ``offsets[n]``.

    Returns:
        (N,) the area of the polygon inside each pixel, in [0, 1].

    The area is the integral of the winding number over the pixel, summed edge by edge: each
    edge, clipped to the pixel's rows, adds the integral over y of the part of the pixel's width
    left of it, signed by its direction in y (exact for a closed polygon; continuous and
    piecewise smooth in the vertices). Each pixel's coordinates are taken about its own corner,
    and the mean width is taken without a difference quotient wherever the clipped edge lies
    within one piece of the clip (float32 keeps about 1e-6 of a pixel's area).

    Derivatives (forward mode, a ``jax.custom_jvp``): the area's rate is the boundary's normal
    velocity integrated over the part of each edge inside the pixel (Reynolds' transport
    theorem), with a point at fraction s along the edge moving as ``(1 - s)`` of its first vertex
    and ``s`` of its second. That is the derivative of the area formula above wherever it has
    one (tests compare the two, and finite differences); it costs two clipped fractions per
    pixel and edge instead of the formula's derivative through every branch.
    """
    polygon = jnp.asarray(polygon, jnp.result_type(polygon, offsets, float))
    offsets = jnp.asarray(offsets, polygon.dtype)  # (integer centres would get no tangent)
    q = jnp.roll(polygon, -1, axis=0)
    shoelace = jnp.sum(polygon[:, 0] * q[:, 1] - q[:, 0] * polygon[:, 1])
    poly = jnp.where(shoelace < 0, polygon[::-1], polygon)  # positive shoelace (x right, y down)
    return _oriented_coverage(poly, offsets)


def _coverage_formula(poly: Array, offsets: Array) -> Array:
    """:func:`pixel_coverage` of a polygon of positive shoelace sum (the value; its own
    derivatives by automatic differentiation are the tests' reference for the custom JVP).
    """
    start = poly[None, :, :] - offsets[:, None, :] + 0.5  # (N, K, 2) about each pixel's corner
    d = jnp.roll(start, -1, axis=1) - start
    y0, dy = start[..., 1], d[..., 1]
    flat = dy == 0
    safe_dy = jnp.where(flat, 1.0, dy)
    sa, sb = (0.0 - y0) / safe_dy, (1.0 - y0) / safe_dy
    s0 = jnp.where(flat, 0.0, jnp.clip(jnp.minimum(sa, sb), 0.0, 1.0))
    s1 = jnp.where(flat, 1.0, jnp.clip(jnp.maximum(sa, sb), 0.0, 1.0))
    xa, xb = start[..., 0] + s0 * d[..., 0], start[..., 0] + s1 * d[..., 0]
    # the signed span of the edge within the row (0 for a horizontal edge, whose derivative in
    # its vertices' y is not 0)
    height = jnp.clip(y0 + dy, 0.0, 1.0) - jnp.clip(y0, 0.0, 1.0)

    def ramp(u):  # the integral of clip(u, 0, 1)
        return jnp.where(u < 0, 0.0, jnp.where(u > 1, u - 0.5, 0.5 * u * u))

    lo, hi = jnp.minimum(xa, xb), jnp.maximum(xa, xb)
    span = xb - xa
    short = jnp.abs(span) < jnp.sqrt(jnp.finfo(span.dtype).eps)
    safe_span = jnp.where(short, 1.0, span)
    middle = 0.5 * (xa + xb)
    mean_width = jnp.where(  # the mean of clip(x, 0, 1) along the clipped edge
        (lo >= 0) & (hi <= 1),
        middle,
        jnp.where(
            lo >= 1,
            1.0,
            jnp.where(
                hi <= 0,
                0.0,
                jnp.where(short, jnp.clip(middle, 0.0, 1.0), (ramp(xb) - ramp(xa)) / safe_span),
            ),
        ),
    )
    return jnp.clip(jnp.sum(height * mean_width, axis=1), 0.0, 1.0)


def _edge_fractions_inside(poly: Array, offsets: Array) -> tuple[Array, Array, Array]:
    """Each edge's part inside each pixel, for the boundary integral of :func:`pixel_coverage`.

    Returns ``(m0, m1, normal)``: (N, K) integrals of ``1 - s`` and of ``s`` over the fractions s
    of edge k (from vertex k to vertex k + 1) that lie inside pixel n (a closed unit square, so
    an edge along a pixel border counts in both pixels, a set of measure zero), and (K, 2) each
    edge's outward normal scaled by its length (positive shoelace sum).
    """
    a = poly[None, :, :] - offsets[:, None, :] + 0.5  # (N, K, 2) about each pixel's corner
    d = jnp.roll(poly, -1, axis=0) - poly  # (K, 2)
    enter = jnp.zeros(a.shape[:2], a.dtype)
    leave = jnp.ones(a.shape[:2], a.dtype)
    for axis in range(2):  # Liang-Barsky: the fractions within 0 <= coordinate <= 1
        da = d[None, :, axis]
        flat = da == 0
        safe = jnp.where(flat, 1.0, da)
        sa, sb = -a[..., axis] / safe, (1.0 - a[..., axis]) / safe
        outside = flat & ((a[..., axis] < 0) | (a[..., axis] > 1))
        enter = jnp.where(flat, enter, jnp.maximum(enter, jnp.minimum(sa, sb)))
        leave = jnp.where(
            outside, enter, jnp.where(flat, leave, jnp.minimum(leave, jnp.maximum(sa, sb)))
        )
    leave = jnp.maximum(leave, enter)
    m1 = 0.5 * (leave * leave - enter * enter)
    m0 = (leave - enter) - m1
    normal = jnp.stack([d[:, 1], -d[:, 0]], axis=-1)
    return m0, m1, normal


@jax.custom_jvp
def _oriented_coverage(poly: Array, offsets: Array) -> Array:
    return _coverage_formula(poly, offsets)


@_oriented_coverage.defjvp
def _oriented_coverage_jvp(primals, tangents):
    poly, offsets = primals
    poly_dot, offsets_dot = tangents
    area = _coverage_formula(poly, offsets)
    m0, m1, normal = _edge_fractions_inside(poly, offsets)
    first = jnp.sum(normal * poly_dot, axis=-1)  # (K,) each edge's normal rate at its first vertex
    second = jnp.sum(normal * jnp.roll(poly_dot, -1, axis=0), axis=-1)  # ... at its second
    rate = m0 @ first + m1 @ second
    # a pixel moved by o_dot is the polygon moved by -o_dot
    rate = rate - jnp.sum(((m0 + m1) @ normal) * offsets_dot, axis=-1)
    return area, rate


def _gaussian_matrix(n: int, sigma: float) -> np.ndarray:
    """(n, n) Gaussian blur along one axis, truncated at the window's border and each row
    renormalised (not OpenCV's replicated border).
    """
    if sigma <= 0:
        return np.eye(n)
    i = np.arange(n)
    g = np.exp(-0.5 * ((i[:, None] - i[None, :]) / sigma) ** 2)
    return g / g.sum(axis=1, keepdims=True)


def _rotation_from_vector(w: Array) -> Array:
    """Rodrigues' formula, safe (and differentiable) at w = 0."""
    theta2 = jnp.sum(w * w)
    theta = jnp.sqrt(jnp.where(theta2 > 1e-12, theta2, 1.0))
    small = theta2 <= 1e-12
    a = jnp.where(small, 1.0 - theta2 / 6.0, jnp.sin(theta) / theta)
    b = jnp.where(small, 0.5 - theta2 / 24.0, (1.0 - jnp.cos(theta)) / theta**2)
    k = jnp.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    return jnp.eye(3) + a * k + b * (k @ k)


def _front_faces(rotation: Array, translation: Array, size) -> tuple[Array, Array]:
    """The three faces turned most towards the camera: indices (3,) and their visibility (3,)."""
    corners = box_model.corners_camera(box_model.Pose(rotation, translation), size)
    centres = jnp.mean(corners[jnp.asarray(box_model.FACES)], axis=1)
    normals = jnp.asarray(box_model.FACE_NORMALS) @ rotation.T
    facing = -jnp.sum(normals * centres, axis=-1)  # > 0: turned towards the camera
    order = jnp.argsort(-facing)[:3]
    return order, facing[order] > 0


def face_coverage(
    rotation: Array, translation: Array, size, intrinsics: Array, origin: Array, window_px: int
) -> Array:
    """(3, W, W) area of each of the three front faces inside each window pixel (0 if hidden).

    ``origin`` (2,) [px] is the window's top-left pixel (column, row); pixel (i, j) of the window
    covers ``[origin_x + j, origin_x + j + 1) x [origin_y + i, origin_y + i + 1)``.
    """
    faces, visible = _front_faces(rotation, translation, size)
    pixels = box_model.project_corners(box_model.Pose(rotation, translation), size, intrinsics)
    rows, cols = jnp.mgrid[0:window_px, 0:window_px]
    centres = jnp.stack([cols.ravel(), rows.ravel()], axis=-1) + origin[None, :] + 0.5
    polygons = pixels[jnp.asarray(box_model.FACES)[faces]]  # (3, 4, 2)
    cover = jax.vmap(pixel_coverage, in_axes=(0, None))(polygons, centres)
    return (cover * visible[:, None]).reshape(3, window_px, window_px)


def _residual(
    rotation, translation, image, background, origin, size, intrinsics, weights, cfg, blur
):
    """Residuals (W*W, C) after the faces' colours are solved (weighted least squares)."""
    w = cfg.window_px
    cover = face_coverage(rotation, translation, size, intrinsics, origin, w)
    blurred = jnp.einsum("ij,fjk,lk->fil", blur, cover, blur).reshape(3, -1).T  # (N, 3)
    rest = (1.0 - jnp.sum(cover, axis=0))[..., None] * background  # (W, W, C)
    offset = jnp.einsum("ij,jkc,lk->ilc", blur, rest, blur).reshape(w * w, -1)
    target = image.reshape(w * w, -1) - offset
    aw = blurred * weights[:, None]
    normal = aw.T @ blurred + 1e-6 * jnp.eye(3)
    colours = jnp.linalg.solve(normal, aw.T @ target)  # (3, C)
    return target - blurred @ colours, colours


def _window_arrays(image, background, origin, cfg: PhotometricConfig):
    """The window's image and background as (W, W, C) floats, the origin and the blur matrix."""
    w = cfg.window_px
    image = jnp.asarray(image, jnp.result_type(float)).reshape(w, w, -1)
    background = jnp.asarray(background, image.dtype).reshape(w, w, -1)
    blur = jnp.asarray(_gaussian_matrix(w, cfg.blur_px), image.dtype)
    return image, background, jnp.asarray(origin, image.dtype), blur


def refine_photometric(
    rotation: Array,
    translation: Array,
    image: Array,
    background: Array,
    origin: Array,
    size,
    intrinsics: Array,
    cfg: PhotometricConfig = PhotometricConfig(),
) -> PhotometricFit:
    """Fit a box's pose to the pixels of one window (the model in the module's docstring).

    Args:
        rotation: (3, 3) the start pose's R (object axes in the camera frame).
        translation: (3,) the start pose's t [m].
        image: (W, W, C) the frame's window, grey levels (C channels, 1 or 3), W =
            ``cfg.window_px``.
        background: (W, W, C) the empty scene's image over the same pixels.
        origin: (2,) [px] the window's top-left pixel (column, row) in the frame.
        size: the cube's edge [m].
        intrinsics: (3, 3) K.
        cfg: static settings.

    Returns:
        :class:`PhotometricFit`. Jittable and vmappable; ``cfg`` is static; not
        reverse-differentiable (a ``lax.while_loop``). The caller checks that the start
        pose's projection fits inside the window (``valid`` is False where the refined one does
        not).
    """
    w = cfg.window_px
    image, background, origin, blur = _window_arrays(image, background, origin, cfg)
    args = (image, background, origin, size, intrinsics)

    def residual_at(delta, rot, trans, weights):
        r = _rotation_from_vector(delta[:3]) @ rot
        return _residual(r, trans + delta[3:], *args, weights, cfg, blur)[0]

    ones = jnp.ones(w * w, image.dtype)
    r0 = residual_at(jnp.zeros(6), rotation, translation, ones)
    norms = jnp.sqrt(jnp.sum(r0 * r0, axis=-1))
    channels = r0.shape[-1]
    sigma = jnp.maximum(1.4826 * jnp.median(norms) / jnp.sqrt(channels), cfg.min_noise)
    bar = cfg.huber_sigmas * sigma * jnp.sqrt(channels)
    weights = jnp.where(norms <= bar, 1.0, bar / jnp.maximum(norms, 1e-12))
    weights = jax.lax.stop_gradient(weights)

    def cost_of(r):
        return jnp.sum(weights[:, None] * r * r)

    start_cost = cost_of(r0)

    zero = jnp.zeros(6, image.dtype)

    def linearised(rot, trans):
        """The residual (W*W*C,) at a pose and its six directional derivatives (W*W*C, 6), from
        one linearisation.
        """
        r, tangent = jax.linearize(lambda d: residual_at(d, rot, trans, weights).ravel(), zero)
        return r, jax.vmap(tangent, out_axes=1)(jnp.eye(6, dtype=image.dtype))

    pixel_weights = jnp.repeat(weights, channels)

    def step(carry):
        rot, trans, lam, cost, r, jac, count, _ = carry
        jw = jac * pixel_weights[:, None]
        h = jw.T @ jac
        g = jw.T @ r
        delta = -jnp.linalg.solve(h + lam * jnp.diag(jnp.diag(h) + 1e-12), g)
        new_rot = _rotation_from_vector(delta[:3]) @ rot
        new_trans = trans + delta[3:]
        # the candidate's residual and derivatives, kept for the next step if it is taken
        new_r, new_jac = linearised(new_rot, new_trans)
        new_cost = jnp.sum(pixel_weights * new_r * new_r)
        better = jnp.isfinite(new_cost) & (new_cost < cost)
        settled = better & jnp.isfinite(cost) & (cost - new_cost <= cfg.relative_tolerance * cost)

        def pick(new, old):
            return jnp.where(better, new, old)

        return (
            pick(new_rot, rot),
            pick(new_trans, trans),
            jnp.where(better, jnp.maximum(lam / 3.0, 1e-7), lam * 4.0),
            pick(new_cost, cost),
            pick(new_r, r),
            pick(new_jac, jac),
            count + 1,
            settled,
        )

    lam0 = jnp.asarray(cfg.damping, image.dtype)
    r_start, jac_start = linearised(rotation, translation)
    rot, trans, _, cost, _, jac, steps, _ = jax.lax.while_loop(
        lambda carry: (carry[6] < cfg.iterations) & ~carry[7],
        step,
        (rotation, translation, lam0, start_cost, r_start, jac_start, 0, False),
    )
    _, colours = _residual(rot, trans, *args, weights, cfg, blur)
    corners = (
        box_model.project_corners(box_model.Pose(rot, trans), size, intrinsics) - origin[None, :]
    )
    inside = jnp.all((corners >= 0) & (corners <= w))
    valid = inside & jnp.isfinite(cost) & jnp.all(jnp.isfinite(trans)) & (trans[2] > 0)
    # the carried derivatives are those of the kept pose (a rejected step keeps the old ones)
    information = (jac * pixel_weights[:, None]).T @ jac / (sigma * sigma)
    information = 0.5 * (information + information.T)
    return PhotometricFit(rot, trans, cost, start_cost, colours, sigma, valid, steps, information)


def window_cost(
    rotation: Array,
    translation: Array,
    image: Array,
    background: Array,
    origin: Array,
    size,
    intrinsics: Array,
    noise,
    cfg: PhotometricConfig = PhotometricConfig(),
) -> Array:
    """The Huber cost of a pose on a window (bar ``cfg.huber_sigmas`` x ``noise`` per channel):
    sum of r^2 / 2 within the bar, bar (|r| - bar / 2) beyond, over pixels (|r| over channels).
    Compares poses on the same window and noise, whatever they were refined from.
    """
    w = cfg.window_px
    image, background, origin, blur = _window_arrays(image, background, origin, cfg)
    ones = jnp.ones(w * w, image.dtype)
    r, _ = _residual(
        rotation,
        translation,
        image,
        background,
        origin,
        size,
        intrinsics,
        ones,
        cfg,
        blur,
    )
    norms = jnp.sqrt(jnp.sum(r * r, axis=-1))
    bar = cfg.huber_sigmas * noise * jnp.sqrt(r.shape[-1])
    return jnp.sum(jnp.where(norms <= bar, 0.5 * norms**2, bar * (norms - 0.5 * bar)))


def silhouette_contrast(frame, background, rotation, translation, size, intrinsics, noise) -> float:
    """How far a posed box's projected silhouette stands out from the empty scene, in units of
    a fit's noise (NumPy, on the host): the median over the pixels whose centres lie inside the
    convex hull of the projected corners of the largest channel's |frame - background|, over
    ``noise`` (:attr:`PhotometricFit.noise`).

    Args:
        frame: (H, W, C) or (H, W) image (grey levels).
        background: the empty scene's image, of the frame's shape.
        rotation: (3, 3) R of the pose (object axes in the camera frame).
        translation: (3,) t of the pose [m].
        size: the cube's edge [m].
        intrinsics: (3, 3) K.
        noise: [grey levels], positive.

    Returns:
        The contrast [-]; 0.0 where the silhouette covers no pixel centre, or the pose is not in
        front of the camera or not finite.

    Raises:
        ValueError: frame and background of different shapes, or ``noise`` not positive.
    """
    frame, background = np.asarray(frame), np.asarray(background)  # (only the crop as floats)
    if frame.shape != background.shape or frame.ndim not in (2, 3):
        raise ValueError(
            f"frame and background must be (H, W[, C]) of one shape, got {frame.shape} and "
            f"{background.shape}"
        )
    if not float(noise) > 0:
        raise ValueError(f"noise must be positive, got {noise!r}")
    rotation, translation = np.asarray(rotation, float), np.asarray(translation, float)
    if not (np.all(np.isfinite(rotation)) and np.all(np.isfinite(translation))):
        return 0.0
    if translation[2] <= 0:
        return 0.0
    corners = box_model.project_corners_np(rotation, translation, size, intrinsics)
    if not np.all(np.isfinite(corners)):
        return 0.0
    order = cv2.convexHull(corners.astype(np.float32), returnPoints=False).ravel()
    hull = corners[order]  # the exact corners, in the hull's order
    # the pixels whose centres (column + 0.5, row + 0.5) can lie inside: the hull's bounding box
    height, width = frame.shape[:2]
    lo = np.maximum(np.ceil(hull.min(axis=0) - 0.5), 0).astype(int)
    hi = np.minimum(np.floor(hull.max(axis=0) - 0.5), [width - 1, height - 1]).astype(int)
    if np.any(hi < lo):
        return 0.0
    xs = np.arange(lo[0], hi[0] + 1)[None, :] + 0.5
    ys = np.arange(lo[1], hi[1] + 1)[:, None] + 0.5
    ahead = np.roll(hull, -1, axis=0)
    turn = np.sign(np.sum(hull[:, 0] * ahead[:, 1] - ahead[:, 0] * hull[:, 1]))
    if turn == 0:  # no area
        return 0.0
    inside = np.ones((len(ys), xs.shape[1]), bool)
    for a, b in zip(hull, ahead, strict=True):  # on the inner side of every hull edge
        inside &= turn * ((b[0] - a[0]) * (ys - a[1]) - (b[1] - a[1]) * (xs - a[0])) >= 0
    rows, cols = slice(lo[1], hi[1] + 1), slice(lo[0], hi[0] + 1)
    difference = np.abs(frame[rows, cols].astype(float) - background[rows, cols].astype(float))
    if difference.ndim == 3:
        difference = difference.max(axis=-1)
    pixels = difference[inside]
    if pixels.size == 0:
        return 0.0
    return float(np.median(pixels) / float(noise))


class RefinedMeasurements(NamedTuple):
    """Result of :func:`refine_measurements` (NumPy arrays).

    Attributes:
        rotation: (T, 3, 3) R_cam_box, refined where ``refined`` (else as given).
        position: (T, 3) box centre [m], likewise.
        refined: (T,) bool, the frames whose pose was replaced by a photometric fit.
        carried: (T,) bool, the refined frames whose kept fit started from the previous frame's
            correction (else from the frame's own measurement).
        frame_seconds: (T,) wall time of each frame's refinement [s] (0 where none ran; the
            compilation is done before the first frame and not counted).
    """

    rotation: np.ndarray
    position: np.ndarray
    refined: np.ndarray
    carried: np.ndarray
    frame_seconds: np.ndarray


def refine_measurements(
    frames,
    background,
    rotation,
    position,
    valid,
    size: float,
    intrinsics,
    cfg: PhotometricConfig = PhotometricConfig(),
) -> RefinedMeasurements:
    """A tracker's per-frame poses of a small box refined on the frames' pixels (causal).

    For each valid frame whose measured pose projects into a box that fits the window with
    ``cfg.margin_px`` to spare, :func:`refine_photometric` runs from (a) the measured pose and
    (b) the previous frame's correction carried onto it (the previous refined pose times the
    inverse of the previous measured one, where the previous frame was refined); the fit of
    lower :func:`window_cost` on the window about the measured pose, at (a)'s noise, is kept.
    Only the frame and the one before it are used, so the pass can run online.

    Args:
        frames: (T, H, W, 3) or (T, H, W) uint8.
        background: the empty scene, (H, W, 3) or (H, W) as the frames.
        rotation: (T, 3, 3) measured R_cam_box.
        position: (T, 3) measured centres [m].
        valid: (T,) bool, the frames with a measurement.
        size: the cube's edge [m].
        intrinsics: (3, 3) K.
        cfg: static settings.

    Returns:
        :class:`RefinedMeasurements`; frames not refined keep their poses. A kept fit is not
        compared with the measured pose itself, and nothing here tells a fit that stopped in
        another minimum (docs/eye_randomized.md, "Photometric refinement of small boxes").

    Raises:
        ValueError: shapes that do not match, a background of another size than the frames.
    """
    frames = np.asarray(frames)
    if frames.ndim == 3:
        frames = frames[..., None]
    background = np.asarray(background, float)
    if background.ndim == 2:
        background = background[..., None]
    n, height, width = frames.shape[:3]
    rotation = np.array(rotation, float)
    position = np.array(position, float)
    valid = np.asarray(valid, bool)
    if frames.ndim != 4 or background.shape != frames.shape[1:]:
        raise ValueError(
            f"frames (T, H, W[, C]) and a background of one frame's shape needed, got "
            f"{frames.shape} and {background.shape}"
        )
    if rotation.shape != (n, 3, 3) or position.shape != (n, 3) or valid.shape != (n,):
        raise ValueError(
            f"rotation (T, 3, 3), position (T, 3) and valid (T,) for T = {n} frames needed, got "
            f"{rotation.shape}, {position.shape}, {valid.shape}"
        )
    k = np.asarray(intrinsics, float)
    w = cfg.window_px
    if w > min(height, width):
        raise ValueError(f"window_px {w} larger than the frames ({height} x {width})")
    fit, cost = _compiled(cfg)
    if valid.any():  # compiled before the frames are timed
        dummy = np.zeros((w, w, frames.shape[-1]))
        pose = (np.eye(3), np.array([0.0, 0.0, 1.0]))
        jax.block_until_ready(fit(*pose, dummy, dummy, np.zeros(2), size, k))
        # the noise as a 0-d float array, as the fits return it (a Python float compiles anew)
        jax.block_until_ready(cost(*pose, dummy, dummy, np.zeros(2), size, k, np.asarray(1.0)))
    refined = np.zeros(n, bool)
    carried = np.zeros(n, bool)
    out_r, out_t = rotation.copy(), position.copy()
    seconds = np.zeros(n)
    previous = None  # (measured R, t, refined R, t) of the previous frame
    for i in range(n):
        t0 = time.perf_counter()
        r_m, t_m = rotation[i], position[i]
        usable = valid[i] and np.all(np.isfinite(r_m)) and np.all(np.isfinite(t_m))
        px = box_model.project_corners_np(r_m, t_m, size, k) if usable and t_m[2] > 0 else None
        if px is None or np.any(px.max(0) - px.min(0) > w - 2 * cfg.margin_px):
            previous = None
            continue
        centre = 0.5 * (px.min(0) + px.max(0))
        origin = np.clip(np.round(centre - w / 2), 0, [width - w, height - w]).astype(int)
        rows, cols = slice(origin[1], origin[1] + w), slice(origin[0], origin[0] + w)
        image, empty = frames[i, rows, cols].astype(float), background[rows, cols]
        o = origin.astype(float)
        own = fit(r_m, t_m, image, empty, o, size, k)
        best = (np.asarray(own.rotation), np.asarray(own.translation)) if bool(own.valid) else None
        if previous is not None:
            r_pm, t_pm, r_pr, t_pr = previous
            other = fit(r_pr @ r_pm.T @ r_m, t_m + (t_pr - t_pm), image, empty, o, size, k)
            if bool(other.valid) and (
                best is None
                or float(
                    cost(other.rotation, other.translation, image, empty, o, size, k, own.noise)
                )
                < float(cost(*best, image, empty, o, size, k, own.noise))
            ):
                best = (np.asarray(other.rotation), np.asarray(other.translation))
                carried[i] = True
        seconds[i] = time.perf_counter() - t0
        if best is None:
            previous = None
            continue
        out_r[i], out_t[i] = best
        refined[i] = True
        previous = (r_m, t_m, out_r[i], out_t[i])
    return RefinedMeasurements(out_r, out_t, refined, carried, seconds)


@functools.lru_cache(maxsize=8)
def _compiled(cfg: PhotometricConfig):
    """The jitted fit and cost for one configuration (size and intrinsics traced)."""
    fit = jax.jit(
        lambda r, t, im, bg, o, size, k: refine_photometric(r, t, im, bg, o, size, k, cfg)
    )
    cost = jax.jit(
        lambda r, t, im, bg, o, size, k, noise: window_cost(r, t, im, bg, o, size, k, noise, cfg)
    )
    return fit, cost
