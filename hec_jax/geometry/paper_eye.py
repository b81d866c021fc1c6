"""The paper's own eye online: a pair of 3D-parallel cube edges per frame, the motion between
consecutive frames from Eqs. 1-38, composed into a pose and filtered into the cube's state.

:class:`PaperEye` has :class:`~hec_jax.geometry.track.BoxTracker`'s interface (``update(frame)``
per camera frame, ``reset()``), so the hand-eye loop can take either (``--eye paper`` /
``--eye camera``). Per frame:

1. **Edges (NumPy/OpenCV; ours, the paper takes them as given).** The moving blobs (colour
   difference to the static scene's background, dark pixels excluded, opened) are split into
   faces by Canny edges; the largest region whose outline has four dominant sides (the four
   longest edges of its polygon, :func:`outline_sides`: a bump such as the inpainted hand next
   to the cube is left out) is the most visible face. Its sides are refined by sub-pixel edge
   points (:func:`detect.edge_points`) and robust line fits, its corners are where adjacent
   sides meet (:func:`face_quads`); they are searched first near the previous face. Opposite
   sides of a face of a cube are parallel in 3D: AB = (q0, q1) with CD = (q3, q2), and the other
   pair (q1, q2) with (q0, q3) (:data:`PAIRS`). The corners are matched to the previous frame's
   (cyclic order, :func:`match_quad`; a jump of more than ``max_corner_step`` sides is another
   face or a wrong detection: no pair this frame).
2. **The paper (Eqs. 1-38, :func:`~hec_jax.geometry.parallel_motion.estimate_motion`).** On
   each pair, before (frame t-1) and after (frame t): t1, t2 (Eqs. 18-23), N, K (Eqs. 8-13), the
   virtual lines and t3 (Eqs. 24-38), Phi (Eq. 14) and Gamma (Eq. 1), and so the depths of A, B,
   C, D in both frames (:func:`pair_estimate`). Not the paper's: the metric scale from the known
   edge |AB| = L (Z_B = L / |N1|, docs/paper_readings.md); ``discriminant_tol`` (under image
   noise Eq. 37's quadratic often has no real root; the clamped candidates then go to the root
   choice instead of the frame being lost; ``None`` is the paper's strict reading); and a check
   that the pair's 3D points are two opposite sides of a square of edge L
   (:func:`face_shape_error`, ``max_shape_error``), knowledge of the cube the paper's method for
   any two parallel segments does not use.
3. **Pose (ours).** A face and the known edge give the cube (:func:`cube_from_face`): its centre
   is the face's centre pushed L/2 along the face normal away from the camera, its axes the
   face's sides and normal. The centre at t is the pair's own cube centre at t-1 moved by the
   pair's increment, c_t = Phi c_{t-1} + Gamma (Eq. 1), the mean over the valid pairs. The
   rotation is composed over frames, R_t = Phi_t R_{t-1}, from the face's axes at the first
   valid pair (reported, not used by the controller; it drifts as the increments' errors add
   up). The centre is not composed over frames: with L known every pair fixes the depth anew,
   where a composed centre would random-walk.
4. **Filter (ours; :mod:`~hec_jax.geometry.filter`'s model).** A constant-acceleration Kalman
   filter on the centre (camera frame) with a measurement covariance elongated along the
   viewing ray (``measurement_std``: the depth from |AB| = L errs along the ray). It starts at
   the first valid pair with the pair's own velocity (c_t - c_{t-1}) fps; a measurement outside
   the ``gate_nis`` gate is rejected (an outlier), ``restart_after`` rejections in a row restart
   the filter from the measurement (an impact). After ``lost_after`` frames without a valid
   pair the state is dropped (``initialised`` False): nothing is extrapolated further.

Invalid frames are flagged (``valid`` False) with the reason in ``status``: ``"no_face"`` (no
quadrilateral face found), ``"first"`` (no previous face to pair with), ``"jump"`` (the face's
corners moved too far: another face, or a wrong detection), ``"degenerate"`` (the paper's
estimate is invalid for every pair: Eqs. 20-23 singular, no motion, points behind the camera, a
rigidity residual above ``residual_tol``, not a face of the cube), ``"gated"`` (the filter's
gate rejected it). Measured accuracy and the loop's results: docs/eye_pipeline.md, "--eye paper".
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import NamedTuple

import cv2
import jax
import numpy as np

from hec_jax.geometry import detect
from hec_jax.geometry import filter as kf
from hec_jax.geometry.camera import check_camera_args
from hec_jax.geometry.parallel_motion import estimate_motion

# The two pairs of opposite sides of a face quad (q0, q1, q2, q3): (A, B, C, D) with AB || CD in
# 3D and the same sense (q0 -> q1 and q3 -> q2; q1 -> q2 and q0 -> q3).
PAIRS = np.array([[0, 1, 3, 2], [1, 2, 0, 3]])
STATUSES = ("ok", "no_face", "first", "jump", "degenerate", "gated")


@dataclass(frozen=True)
class PaperEyeConfig:
    """Static parameters of :class:`PaperEye` (hashable).

    Attributes:
        diff_threshold: colour difference to the background of a moving pixel [grey levels].
        dark_threshold: pixels whose channels are all at or below this are not the cube (the
            loop paints the robot's own image black) [grey levels].
        open_px: opening of the moving mask (removes the rod, ~1 px wide) [px].
        blobs: moving blobs tried, largest first [-].
        canny: Canny thresholds that split a blob into faces [grey levels].
        min_face_px: smallest face region [px^2].
        min_side_px: shortest visible side of a face [px].
        outline_eps: polygon approximation of a face region's outline, in perimeters [-].
        merge_deg: consecutive edges of that polygon closer than this in direction are one side
            [deg].
        min_outline_fraction: the four longest edges of that polygon (the sides) make up at least
            this fraction of the perimeter [-].
        max_area_ratio: the refined quadrilateral's area and the region's agree within this
            factor [-].
        max_corner_fit_px: a refined corner further than this from where the unrefined sides
            meet is a failed refinement (no face) [px].
        edge_spacing_px, edge_search_px, edge_blur_px: sub-pixel edge points along each side
            (:func:`detect.edge_points`) [px].
        max_corner_step: largest corner displacement between consecutive frames, in mean side
            lengths of the face [-] (beyond: ``"jump"``).
        roi_margin: the face is searched first in a window around the previous one, this many
            of its sizes wider on every side (then in the whole frame) [-].
        both_pairs: the paper's estimate on both pairs of opposite sides (the centre is the mean
            of the valid ones); False: only AB = (q0, q1), CD = (q3, q2), as the paper's one pair.
        discriminant_tol: passed to :func:`~hec_jax.geometry.parallel_motion.estimate_motion`;
            1.0 accepts any negative discriminant of Eq. 37 (the clamped candidates), None is the
            paper's strict reading (real roots only).
        residual_tol: largest rigidity residual of a valid estimate (``estimate_motion``) [-].
        max_shape_error: largest :func:`face_shape_error` of a valid pair, before and after (the
            cube's known shape as a check; not in the paper) [-].
        measurement_std: standard deviations of the measured centre across and along its
            viewing ray [m]: the paper's depths err along the rays (Z_B = L / |N1|), the face
            normal's tilt across them; measured on a rendered swing (docs/eye_pipeline.md).
        jerk_psd: white-jerk spectral density of the filter [m^2/s^5].
        init_std: standard deviations of (p, v, a) at the filter's start [m, m/s, m/s^2] (p and
            v are the first pair's).
        gate_nis: a measurement whose normalised innovation squared exceeds this is rejected
            (chi-square, 3 dof; 16.3 is p = 0.001) [-].
        restart_after: rejected measurements in a row after which the filter restarts from the
            last one (an impact changed the velocity) [-].
        lost_after: frames without a valid pair after which the state is dropped [-].
    """

    diff_threshold: int = 20
    dark_threshold: int = 8
    open_px: int = 5
    blobs: int = 3
    canny: tuple[int, int] = (20, 60)
    min_face_px: float = 60.0
    min_side_px: float = 6.0
    outline_eps: float = 0.015
    merge_deg: float = 12.0
    min_outline_fraction: float = 0.7
    max_area_ratio: float = 1.3
    max_corner_fit_px: float = 4.0
    edge_spacing_px: float = 1.0
    edge_search_px: float = 3.0
    edge_blur_px: float = 0.8
    max_corner_step: float = 0.6
    roi_margin: float = 1.0
    both_pairs: bool = True
    discriminant_tol: float | None = 1.0
    residual_tol: float = 0.05
    max_shape_error: float = 0.2
    measurement_std: tuple[float, float] = (0.008, 0.03)
    jerk_psd: float = 20.0
    init_std: tuple[float, float, float] = (0.01, 0.3, 5.0)
    gate_nis: float = 16.3
    restart_after: int = 2
    lost_after: int = 3

    def __post_init__(self):
        for name in (
            "min_face_px",
            "min_side_px",
            "outline_eps",
            "merge_deg",
            "min_outline_fraction",
            "max_area_ratio",
            "max_corner_fit_px",
            "max_corner_step",
            "roi_margin",
            "max_shape_error",
        ):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"PaperEyeConfig.{name} must be finite and > 0, got {v}")
        for name in ("blobs", "restart_after", "lost_after"):
            v = getattr(self, name)
            if not (isinstance(v, int) and v >= 1):
                raise ValueError(f"PaperEyeConfig.{name} must be an integer >= 1, got {v}")
        if len(self.measurement_std) != 2 or not all(s > 0 for s in self.measurement_std):
            raise ValueError(f"measurement_std must be 2 values > 0, got {self.measurement_std}")


class PaperStep(NamedTuple):
    """Output of :meth:`PaperEye.update` for one frame (NumPy; camera frame of the intrinsics).

    Causal: the filter after this frame's measurement, or its prediction where there was none.

    Attributes:
        frame: index of the frame since construction / :meth:`PaperEye.reset`.
        valid: bool, this frame gave a valid pair that updated the filter.
        initialised: bool, the filter holds a state (else position, velocity, acceleration are
            zeros).
        status: why the frame is (in)valid, one of :data:`STATUSES`.
        position, velocity, acceleration: (3,) filtered cube centre [m, m/s, m/s^2].
        position_cov: (3, 3) its covariance [m^2] (identity where not initialised).
        pose_rotation: (3, 3) the composed rotation R_t = Phi_t R_{t-1} (a labelling of the
            cube's axes; identity before the first valid pair).
        measured_position: (3,) this frame's centre from the paper's estimate [m] (NaN if none).
        motion_rotation, motion_translation: (3, 3), (3,) Phi and Gamma (Eq. 1) of the frame's
            lowest-residual valid pair (identity, zeros where none) [-, m].
        pairs_valid: (2,) bool, which pair of opposite sides gave a valid estimate.
        quad: (4, 2) the face's corners [px, intrinsics convention] (NaN where none).
        segments: (4, 2, 2) its sides [px] (NaN where none), for drawing.
        timing_ms: {"detection_ms", "estimation_ms", "total_ms"} of this frame [ms].
    """

    frame: int
    valid: np.bool_
    initialised: np.bool_
    status: str
    position: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray
    position_cov: np.ndarray
    pose_rotation: np.ndarray
    measured_position: np.ndarray
    motion_rotation: np.ndarray
    motion_translation: np.ndarray
    pairs_valid: np.ndarray
    quad: np.ndarray
    segments: np.ndarray
    timing_ms: dict


def _signed_area(quad: np.ndarray) -> float:
    x, y = quad[:, 0], quad[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def _intersect(p1, d1, p2, d2) -> np.ndarray | None:
    """Intersection of the lines p1 + s d1 and p2 + u d2 (None if parallel)."""
    a = np.array([d1, -d2]).T
    if abs(np.linalg.det(a)) < 1e-9:
        return None
    s = np.linalg.solve(a, p2 - p1)
    return p1 + s[0] * d1


def outline_sides(contour: np.ndarray, config: PaperEyeConfig) -> np.ndarray | None:
    """The four sides (4, 2, 2) [px], in cyclic order, of a face region's outline (N, 2) [px]:
    the outline's polygon approximation (``outline_eps`` of the perimeter), consecutive edges
    within ``merge_deg`` of one direction merged, its four longest edges. A bump on the outline
    (the inpainted hand touching the cube, a shadow) gives short extra edges that are left out.
    None if the four do not make up ``min_outline_fraction`` of the perimeter or one is shorter
    than ``min_side_px``.
    """
    closed = contour.reshape(-1, 1, 2).astype(np.int32)
    perimeter = cv2.arcLength(closed, True)
    poly = cv2.approxPolyDP(closed, config.outline_eps * perimeter, True).reshape(-1, 2)
    nxt = np.roll(poly, -1, axis=0)
    edges = [np.array([a, b], np.float64) for a, b in zip(poly, nxt, strict=True)]
    cos_merge = np.cos(np.deg2rad(config.merge_deg))

    def unit(e):
        d = e[1] - e[0]
        return d / max(float(np.linalg.norm(d)), 1e-9)

    merged = True
    while merged and len(edges) > 4:
        merged = False
        for i in range(len(edges)):
            j = (i + 1) % len(edges)
            if unit(edges[i]) @ unit(edges[j]) > cos_merge:
                edges[i] = np.array([edges[i][0], edges[j][1]])
                del edges[j]
                merged = True
                break
    if len(edges) < 4:
        return None
    edges = np.stack(edges)
    length = np.linalg.norm(edges[:, 1] - edges[:, 0], axis=-1)
    four = np.sort(np.argsort(-length)[:4])
    if length[four].min() < config.min_side_px:
        return None
    if length[four].sum() < config.min_outline_fraction * perimeter:
        return None
    return edges[four]


def refine_quad(gray: np.ndarray, sides: np.ndarray, config: PaperEyeConfig) -> np.ndarray | None:
    """Sub-pixel corners (4, 2) [px] of a face from the visible parts of its four sides (4, 2, 2)
    [px, cyclic]: edge points along each (:func:`detect.edge_points`), a robust (Huber) line per
    side, the corners where adjacent lines meet (corner i: sides i-1 and i). None where a side
    has fewer than 4 points, adjacent lines are parallel or a corner lies more than
    ``max_corner_fit_px`` from where the unrefined sides meet.
    """
    pts, ids = detect.edge_points(
        gray,
        sides,
        np.ones(4, bool),
        spacing=config.edge_spacing_px,
        search=config.edge_search_px,
        blur=config.edge_blur_px,
    )
    lines = []
    for i in range(4):
        p = pts[ids == i]
        if len(p) < 4:
            return None
        vx, vy, x0, y0 = cv2.fitLine(p.astype(np.float32), cv2.DIST_HUBER, 0, 0.01, 0.01).ravel()
        lines.append((np.array([x0, y0], float), np.array([vx, vy], float)))
    corners = []
    for i in range(4):
        c = _intersect(*lines[i - 1], *lines[i])
        rough = _intersect(
            sides[i - 1, 0],
            sides[i - 1, 1] - sides[i - 1, 0],
            sides[i, 0],
            sides[i, 1] - sides[i, 0],
        )
        if c is None or rough is None or np.linalg.norm(c - rough) > config.max_corner_fit_px:
            return None
        corners.append(c)
    return np.asarray(corners)


def _convex(quad: np.ndarray) -> bool:
    """All four turns of ``quad`` (4, 2) in one sense."""
    d = np.roll(quad, -1, axis=0) - quad
    turn = d[:, 0] * np.roll(d, -1, axis=0)[:, 1] - d[:, 1] * np.roll(d, -1, axis=0)[:, 0]
    return bool(np.all(turn > 0) or np.all(turn < 0))


def face_quads(
    frame: np.ndarray, background: np.ndarray, config: PaperEyeConfig, roi=None
) -> list[tuple[float, np.ndarray]]:
    """Candidate faces of the cube in ``frame`` ((H, W, 3) uint8 RGB) against ``background``
    (the static scene, same shape), inside ``roi`` = (x0, y0, x1, y1) [px] if given: per moving
    blob (largest ``config.blobs``) the largest face region (the blob split by Canny edges) with
    four sides (:func:`outline_sides`) that refine to a convex quadrilateral
    (:func:`refine_quad`) of about the region's area, as (area [px^2], corners (4, 2) [px,
    intrinsics convention], clockwise on the screen, y down).
    """
    if roi is not None:
        box = detect.clip_roi(roi, frame.shape[1], frame.shape[0])
        if box is None:
            return []
        x0, y0, x1, y1 = box
        found = face_quads(frame[y0:y1, x0:x1], background[y0:y1, x0:x1], config)
        return [(area, quad + np.array([x0, y0], float)) for area, quad in found]
    diff = cv2.absdiff(frame, background).max(axis=-1)
    moving = (diff > config.diff_threshold) & (frame.max(axis=-1) > config.dark_threshold)
    k = np.ones((config.open_px, config.open_px), np.uint8)
    moving = cv2.morphologyEx(moving.astype(np.uint8), cv2.MORPH_OPEN, k)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(moving, connectivity=8)
    if n <= 1:
        return []
    gray = detect.to_gray(frame)
    h, w = gray.shape
    out = []
    for b in 1 + np.argsort(-stats[1:, cv2.CC_STAT_AREA])[: config.blobs]:
        if stats[b, cv2.CC_STAT_AREA] < config.min_face_px:
            break
        x, y, bw, bh = stats[b, :4]
        x0, y0 = max(x - 4, 0), max(y - 4, 0)
        x1, y1 = min(x + bw + 4, w), min(y + bh + 4, h)
        blob = labels[y0:y1, x0:x1] == b
        patch = cv2.GaussianBlur(gray[y0:y1, x0:x1], (0, 0), 1.0)
        edges = cv2.dilate(cv2.Canny(patch, *config.canny), np.ones((3, 3), np.uint8))
        regions = (blob & (edges == 0)).astype(np.uint8)
        n_r, lab_r, st_r, _ = cv2.connectedComponentsWithStats(regions, connectivity=4)
        for r in 1 + np.argsort(-st_r[1:, cv2.CC_STAT_AREA]):
            if st_r[r, cv2.CC_STAT_AREA] < 0.5 * config.min_face_px:
                break
            grown = cv2.dilate((lab_r == r).astype(np.uint8), np.ones((3, 3), np.uint8))
            contours, _ = cv2.findContours(grown, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
            contour = max(contours, key=cv2.contourArea).reshape(-1, 2)
            area = float(cv2.contourArea(contour))
            sides = outline_sides(contour, config)
            if sides is None:
                continue
            offset = np.array([x0, y0]) + detect.PIXEL_OFFSET
            corners = refine_quad(gray, sides + offset, config)
            if corners is None or not _convex(corners):
                continue
            quad_area = abs(_signed_area(corners))
            if not (
                1.0 / config.max_area_ratio <= quad_area / max(area, 1.0) <= config.max_area_ratio
            ):
                continue
            if _signed_area(corners) < 0:  # clockwise on the screen (y down)
                corners = corners[::-1].copy()
            out.append((quad_area, corners))
            break  # the largest region that is a face
    return out


def face_quad(
    frame: np.ndarray, background: np.ndarray, config: PaperEyeConfig, previous=None
) -> np.ndarray | None:
    """The face (4, 2) [px] to pair with ``previous`` (4, 2) (the candidate of
    :func:`face_quads` nearest to it, matched by :func:`match_quad`; searched first in a window
    around it, ``roi_margin`` of its size wide on every side), or the largest candidate without
    one; None if there is none.
    """
    cands = []
    if previous is not None:
        lo, hi = previous.min(axis=0), previous.max(axis=0)
        pad = config.roi_margin * float(np.max(hi - lo)) + 8.0
        cands = face_quads(frame, background, config, (*(lo - pad), *(hi + pad)))
    if not cands:
        cands = face_quads(frame, background, config)
    if not cands:
        return None
    if previous is None:
        return max(cands, key=lambda c: c[0])[1]
    matched = [match_quad(previous, q) for _, q in cands]
    return min(matched, key=lambda q: float(np.sum(np.linalg.norm(q - previous, axis=-1))))


def match_quad(previous: np.ndarray, quad: np.ndarray) -> np.ndarray:
    """``quad`` (4, 2) cyclically shifted to match ``previous`` corner by corner (both in the
    same sense on the screen, :func:`face_quads`).
    """
    shifts = [np.roll(quad, -s, axis=0) for s in range(4)]
    cost = [float(np.sum(np.linalg.norm(q - previous, axis=-1))) for q in shifts]
    return shifts[int(np.argmin(cost))]


def cube_from_face(points: np.ndarray, size: float) -> tuple[np.ndarray, np.ndarray]:
    """(R_cam_cube (3, 3), centre (3,) [m]) of the cube behind the face whose 3D corners are the
    pair's A, B, C, D ((4, 3), AB || CD, camera frame): axes AB, the in-face normal to it and the
    face normal pointing away from the camera; centre = face centre + ``size`` / 2 along it.
    """
    a, b, c, d = points
    u1 = (b - a) + (d - c)
    u1 = u1 / np.linalg.norm(u1)
    n = np.cross(u1, (c - a) + (d - b))
    n = n / np.linalg.norm(n)
    centre = points.mean(axis=0)
    if n @ centre < 0:  # the cube lies beyond its visible face
        n = -n
    u2 = np.cross(n, u1)
    return np.stack([u1, u2, n], axis=1), centre + 0.5 * size * n


def face_shape_error(points: np.ndarray, size: float) -> float:
    """How far the pair's A, B, C, D ((4, 3) [m], AB || CD) are from two opposite sides of a
    square face of edge ``size``: the largest relative deviation of |CD| and of the distance
    between the lines AB and CD from ``size`` [-] (|AB| = size by the metric scale). The paper's
    estimate knows only that the segments are parallel: under image noise it can put them tens
    of centimetres apart in depth with a small rigidity residual.
    """
    a, b, c, d = points
    u = (b - a) / np.linalg.norm(b - a)
    gap = (c - a) - ((c - a) @ u) * u  # A to line CD, across AB
    cd = np.linalg.norm(d - c)
    return float(max(abs(cd - size), abs(np.linalg.norm(gap) - size)) / size)


def ray_covariance(position: np.ndarray, std: tuple[float, float]) -> np.ndarray:
    """(3, 3) covariance [m^2] of a point measured with ``std`` = (across, along) its viewing
    ray from the camera centre [m].
    """
    ray = position / np.linalg.norm(position)
    across, along = std
    return across**2 * np.eye(3) + (along**2 - across**2) * np.outer(ray, ray)


class PairEstimate(NamedTuple):
    """What the paper's estimate on one pair of frames gives the eye (camera frame).

    Attributes:
        centre_before: (3,) the cube's centre at t-1 [m]: the face of A, B, C, D before the
            motion (depths from Eqs. 7-38, metric by |AB| = L) pushed L/2 behind itself.
        centre_after: (3,) at t [m]: that centre moved by the pair's increment,
            Phi c + Gamma (Eq. 1). Both are means over the valid pairs of sides.
        phi, gamma: (3, 3), (3,) Phi and Gamma (Eq. 1) of the lowest-residual valid pair [-, m].
        rot_before: (3, 3) R_cam_cube at t-1 of that pair (:func:`cube_from_face`).
        pairs_valid: (2,) bool, which pair of opposite sides gave a valid estimate.
    """

    centre_before: np.ndarray
    centre_after: np.ndarray
    phi: np.ndarray
    gamma: np.ndarray
    rot_before: np.ndarray
    pairs_valid: np.ndarray


def pair_estimate(
    before: np.ndarray, after: np.ndarray, intrinsics, size: float, config: PaperEyeConfig
) -> PairEstimate | None:
    """The paper's motion (Eqs. 1-38, :func:`~hec_jax.geometry.parallel_motion.estimate_motion`)
    between two images of one face, and the cube's centre before and after it.

    Args:
        before: (4, 2) the face's corners [px, intrinsics convention] in frame t-1, in cyclic
            order (so that q0 q1 || q3 q2 and q1 q2 || q0 q3, :data:`PAIRS`).
        after: (4, 2) the same corners in frame t (corner i the same physical corner).
        intrinsics: (3, 3) camera matrix.
        size: the cube's edge L [m] (|AB|).
        config: ``both_pairs``, ``residual_tol``, ``discriminant_tol``.

    Returns:
        :class:`PairEstimate`, or None where the estimate is invalid for every pair used.
    """
    k_inv = np.linalg.inv(np.asarray(intrinsics, np.float64))
    pairs = PAIRS if config.both_pairs else PAIRS[:1]

    def normalised(px):
        return px[pairs] @ k_inv[:2, :2].T + k_inv[:2, 2]

    est = estimate_motion(
        normalised(np.asarray(before, np.float64)),
        normalised(np.asarray(after, np.float64)),
        size,
        residual_tol=config.residual_tol,
        discriminant_tol=config.discriminant_tol,
    )
    est = jax.tree_util.tree_map(np.asarray, est)
    ok = np.zeros(2, bool)
    ok[: len(pairs)] = est.valid
    for i in np.flatnonzero(ok):  # ours: the pair must be two sides of a face of the cube
        ok[i] = face_shape_error(est.points_before[i], size) <= config.max_shape_error
        ok[i] &= face_shape_error(est.points_after[i], size) <= config.max_shape_error
    if not ok.any():
        return None
    use = np.flatnonzero(ok)
    then = [cube_from_face(est.points_before[i], size)[1] for i in use]
    now = [est.rotation[i] @ c + est.translation[i] for i, c in zip(use, then, strict=True)]
    best = min(use, key=lambda i: est.residual[i])
    rot_before, _ = cube_from_face(est.points_before[best], size)
    return PairEstimate(
        np.mean(then, 0), np.mean(now, 0), est.rotation[best], est.translation[best], rot_before, ok
    )


def _correct(mean, cov, position, r) -> tuple[np.ndarray, np.ndarray]:
    """Kalman measurement update of (p, v, a) with a position (3,) of covariance ``r`` (NumPy;
    :func:`filter.correct`'s Joseph form).
    """
    h = np.hstack([np.eye(3), np.zeros((3, 6))])
    gain = np.linalg.solve(h @ cov @ h.T + r, h @ cov).T
    ikh = np.eye(9) - gain @ h
    return mean + gain @ (position - mean[:3]), ikh @ cov @ ikh.T + gain @ r @ gain.T


class PaperEye:
    """The paper's eye (Eqs. 1-38 on consecutive frames) as an online tracker of a cube.

    Same use as :class:`~hec_jax.geometry.track.BoxTracker`: ``update(frame)`` per camera frame,
    ``reset()`` at a new throw; see the module docstring for what is the paper's and what is
    added.

    Args:
        intrinsics: (3, 3) camera matrix (pinhole, image on [0, W] x [0, H]).
        size: the cube's edge L [m] (the metric scale).
        fps: frame rate [1/s] (the filter's step; velocities are per 1 / fps).
        config: :class:`PaperEyeConfig`.
        background: (H, W, 3) uint8 RGB image of the static scene without the cube (a calibration
            shot of the fixed camera).

    Raises:
        ValueError: bad intrinsics, size, fps or background.
    """

    def __init__(
        self,
        intrinsics,
        size: float,
        fps: float,
        config: PaperEyeConfig = PaperEyeConfig(),
        background=None,
    ):
        check_camera_args(intrinsics, size, fps)
        background = None if background is None else np.asarray(background)
        if background is None or background.dtype != np.uint8 or background.ndim != 3:
            raise ValueError("background must be an (H, W, 3) uint8 RGB image of the static scene")
        self.config = config
        self.size = float(size)
        self.fps = float(fps)
        self.intrinsics = np.asarray(intrinsics, np.float64)
        self.background = background
        self._f, self._q = kf.transition_np(config.jerk_psd, 1.0 / self.fps)
        self.reset()

    def reset(self) -> None:
        """Forget the track (the next frame starts from scratch, frame index 0)."""
        self._frame = 0
        self._quad = None  # the previous frame's face (4, 2) [px]
        self._mean = np.zeros(9)
        self._cov = np.eye(9)
        self._started = False
        self._misses = self.config.lost_after
        self._rejected = 0
        self._rotation = None  # composed R_cam_cube
        self._rotation_current = False  # _rotation is the previous frame's (a chain unbroken)

    @property
    def frame(self) -> int:
        """Number of frames processed since construction / :meth:`reset`."""
        return self._frame

    def _start(self, centre: np.ndarray, velocity: np.ndarray) -> None:
        std = np.repeat(np.asarray(self.config.init_std, float), 3)
        self._mean = np.concatenate([centre, velocity, np.zeros(3)])
        self._cov = np.diag(std * std)
        self._started = True
        self._rejected = 0

    def update(self, frame) -> PaperStep:
        """Process the next camera frame ((H, W, 3) uint8 RGB, 1 / fps after the previous one).

        Raises:
            ValueError: frame not (H, W, 3) uint8 or not the background's size.
        """
        frame = np.asarray(frame)
        if frame.dtype != np.uint8 or frame.shape != self.background.shape:
            raise ValueError(
                f"frame must be uint8 of the background's shape {self.background.shape}, got "
                f"{frame.dtype} {frame.shape}"
            )
        cfg = self.config
        t0 = time.perf_counter()
        previous = self._quad
        quad = face_quad(frame, self.background, cfg, previous)
        t1 = time.perf_counter()
        status, got = "ok", None
        if quad is None:
            status = "no_face"
        elif previous is None:
            status = "first"
        else:
            side = float(np.mean(np.linalg.norm(previous - np.roll(previous, -1, 0), axis=-1)))
            if np.max(np.linalg.norm(quad - previous, axis=-1)) > cfg.max_corner_step * side:
                status = "jump"
            else:
                got = pair_estimate(previous, quad, self.intrinsics, self.size, cfg)
                status = "ok" if got is not None else "degenerate"
        self._quad = quad
        measured = np.full(3, np.nan)
        phi, gamma, pairs_ok = np.eye(3), np.zeros(3), np.zeros(2, bool)
        if self._started:  # one frame ahead
            self._mean = self._f @ self._mean
            self._cov = self._f @ self._cov @ self._f.T + self._q
        if got is not None:
            phi, gamma, pairs_ok = got.phi, got.gamma, got.pairs_valid
            centre = got.centre_after
            velocity = (centre - got.centre_before) * self.fps
            measured = centre
            r = ray_covariance(centre, cfg.measurement_std)
            if not self._started:
                self._start(centre, velocity)
            else:
                nu = centre - self._mean[:3]
                nis = float(nu @ np.linalg.solve(self._cov[:3, :3] + r, nu))
                if nis <= cfg.gate_nis:
                    self._mean, self._cov = _correct(self._mean, self._cov, centre, r)
                    self._rejected = 0
                else:
                    self._rejected += 1
                    status = "gated"
                    if self._rejected >= cfg.restart_after:  # an impact: start again from here
                        self._start(centre, velocity)
                        status = "ok"
            if status == "ok":
                # Phi covers the last frame only: after a frame without a motion (no face, a
                # jump, degenerate, gated) the chain restarts from this pair's own pose
                start = self._rotation is None or not self._rotation_current
                self._rotation = phi @ (got.rot_before if start else self._rotation)
        valid = status == "ok"
        self._rotation_current = valid
        self._misses = 0 if valid else self._misses + 1
        if self._misses >= cfg.lost_after and self._started:
            self._started = False  # lost: nothing is extrapolated further
            self._rotation = None
        t2 = time.perf_counter()
        self._frame += 1
        if self._started:
            pos, vel, acc = self._mean[:3].copy(), self._mean[3:6].copy(), self._mean[6:].copy()
            pos_cov = self._cov[:3, :3].copy()
        else:
            pos = vel = acc = np.zeros(3)
            pos_cov = np.eye(3)
        quad_out = np.full((4, 2), np.nan) if quad is None else quad
        segs = np.stack([np.stack([quad_out[i], quad_out[(i + 1) % 4]]) for i in range(4)])
        timing = {"detection_ms": 1e3 * (t1 - t0), "estimation_ms": 1e3 * (t2 - t1)}
        timing["total_ms"] = timing["detection_ms"] + timing["estimation_ms"]
        return PaperStep(
            frame=self._frame - 1,
            valid=np.bool_(valid),
            initialised=np.bool_(self._started),
            status=status,
            position=pos,
            velocity=vel,
            acceleration=acc,
            position_cov=pos_cov,
            pose_rotation=np.eye(3) if self._rotation is None else self._rotation.copy(),
            measured_position=measured,
            motion_rotation=phi,
            motion_translation=gamma,
            pairs_valid=pairs_ok,
            quad=quad_out,
            segments=segs,
            timing_ms=timing,
        )


__all__ = [
    "PAIRS",
    "STATUSES",
    "PairEstimate",
    "PaperEye",
    "PaperEyeConfig",
    "PaperStep",
    "cube_from_face",
    "face_quad",
    "face_quads",
    "face_shape_error",
    "match_quad",
    "outline_sides",
    "pair_estimate",
    "ray_covariance",
    "refine_quad",
]
