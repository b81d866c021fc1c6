"""OpenCV baselines for the two-frame motion of a cube seen in two images (NumPy/OpenCV boundary).

All take the noisy pixel coordinates of the 8 cube corners in both frames ((8, 2) [px], corner
order of :data:`hec_jax.geometry.synthetic.CUBE_CORNERS_UNIT`) and return the motion in the
camera frame as ``(Phi (3, 3), Gamma (3,) [m] or None)`` (P' = Phi P + Gamma, Eq. 1), or None
where OpenCV finds no solution:

* :func:`opencv_pnp`: ``cv2.solvePnP(SOLVEPNP_IPPE_SQUARE)`` on one square face in each frame;
  Phi = R2 R1^T, Gamma = t2 - Phi t1.
* :func:`opencv_homography`: ``cv2.findHomography`` on one face between the frames,
  ``cv2.decomposeHomographyMat``, the candidate closest to the truth (an oracle choice);
  rotation only.
* :func:`opencv_essential`: ``cv2.findEssentialMat`` (LMedS) on all 8 corners and
  ``cv2.recoverPose``; rotation only.

The face is the one whose outward normal points most towards the camera (:func:`frontal_face`,
chosen from the true corners).
"""

from __future__ import annotations

import time
from typing import NamedTuple

import cv2
import numpy as np

from hec_jax.geometry.synthetic import CUBE_FACES, CubeMotionScenes, rotation_error_deg

BASELINES = ("pnp_ippe_square", "homography", "essential")


def frontal_face(corners_camera: np.ndarray) -> tuple[int, ...]:
    """Corner indices (cyclic) of the face whose outward normal points most towards the camera.

    Args:
        corners_camera: (8, 3) cube corners in the camera frame [m].
    """
    centre = corners_camera.mean(0)
    best, best_score = None, -np.inf
    for idx, _ in CUBE_FACES:
        face_centre = corners_camera[list(idx)].mean(0)
        normal = face_centre - centre
        score = -normal @ face_centre / (np.linalg.norm(normal) * np.linalg.norm(face_centre))
        if score > best_score:
            best, best_score = idx, score
    return best


def _square_object_points(edge: float) -> np.ndarray:
    """The corners of a square face of edge ``edge`` [m] in IPPE_SQUARE's required order."""
    h = edge / 2.0
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


def opencv_pnp(pixels_before, pixels_after, face, intrinsics, edge: float):
    """Two-frame IPPE_SQUARE on one face -> (Phi, Gamma [m]) or None."""
    obj = _square_object_points(edge)
    poses = []
    for pix in (pixels_before, pixels_after):
        ok, rvec, tvec = cv2.solvePnP(
            obj,
            pix[list(face)].astype(np.float64),
            intrinsics,
            None,
            flags=cv2.SOLVEPNP_IPPE_SQUARE,
        )
        if not ok:
            return None
        poses.append((cv2.Rodrigues(rvec)[0], tvec.ravel()))
    (r1, t1), (r2, t2) = poses
    rot = r2 @ r1.T
    return rot, t2 - rot @ t1


def opencv_homography(pixels_before, pixels_after, face, intrinsics, true_rotation):
    """Homography between the frames on one face, decomposed; the candidate closest to
    ``true_rotation`` (oracle choice) -> (Phi, None) or None.
    """
    h, _ = cv2.findHomography(pixels_before[list(face)], pixels_after[list(face)], 0)
    if h is None:
        return None
    n, rots, _, _ = cv2.decomposeHomographyMat(h, intrinsics)
    if n == 0:
        return None
    errs = [rotation_error_deg(np.asarray(r), true_rotation) for r in rots]
    return np.asarray(rots[int(np.argmin(errs))]), None


def opencv_essential(pixels_before, pixels_after, intrinsics):
    """Essential matrix on all 8 corners (LMedS) and recoverPose -> (Phi, None) or None."""
    e, _ = cv2.findEssentialMat(pixels_before, pixels_after, intrinsics, method=cv2.LMEDS)
    if e is None or e.shape != (3, 3):
        return None
    _, rot, _, _ = cv2.recoverPose(e, pixels_before, pixels_after, intrinsics)
    return rot, None


def run_baselines(scenes: CubeMotionScenes, intrinsics, edge: float, index: int) -> dict:
    """Every baseline on scene ``index`` -> {name: (Phi, Gamma or None) or None}."""
    pb, pa = scenes.pixels_before[index], scenes.pixels_after[index]
    face = frontal_face(scenes.corners_before[index])
    return {
        "pnp_ippe_square": opencv_pnp(pb, pa, face, intrinsics, edge),
        "homography": opencv_homography(pb, pa, face, intrinsics, scenes.rotation[index]),
        "essential": opencv_essential(pb, pa, intrinsics),
    }


def pnp_rotation_errors(scenes: CubeMotionScenes, intrinsics, edge: float) -> np.ndarray:
    """Rotation error [deg] (n,) of :func:`opencv_pnp` on every scene (frontal face each).

    Raises:
        RuntimeError: OpenCV found no solution for a scene.
    """
    out = np.empty(len(scenes.pair))
    for i in range(len(out)):
        res = opencv_pnp(
            scenes.pixels_before[i],
            scenes.pixels_after[i],
            frontal_face(scenes.corners_before[i]),
            intrinsics,
            edge,
        )
        if res is None:
            raise RuntimeError(f"solvePnP found no pose for scene {i}")
        out[i] = rotation_error_deg(res[0], scenes.rotation[i])
    return out


# ---------------------------------------------------------------------------------------------
# Baselines on camera frames (issue 24): the visible face as a quadrilateral, then either
# solvePnP (IPPE_SQUARE) per frame or the paper's two-frame method on its opposite sides.


class FrameTrack(NamedTuple):
    """Per-frame output of a frame-based baseline (NumPy; camera frame of the intrinsics).

    Attributes:
        position: (T, 3) box centre [m] (zeros where not valid).
        rotation: (T, 3, 3) R_cam_box (a labelling of the cube's axes; identity where not valid).
        velocity: (T, 3) [m/s] (NaN where the method gives none).
        valid: (T,) bool.
        quads: (T, 4, 2) the face's corners [px, intrinsics convention] (NaN where none).
        time_ms: mean time per frame [ms].
    """

    position: np.ndarray
    rotation: np.ndarray
    velocity: np.ndarray
    valid: np.ndarray
    quads: np.ndarray
    time_ms: float


def _intersect(l1, l2):
    """Intersection of two lines (vx, vy, x0, y0) (cv2.fitLine), or None if parallel."""
    d1, p1, d2, p2 = l1[:2], l1[2:], l2[:2], l2[2:]
    a = np.array([d1, -d2]).T
    if abs(np.linalg.det(a)) < 1e-9:
        return None
    s = np.linalg.solve(a, p2 - p1)
    return p1 + s[0] * d1


def face_quad(
    frame: np.ndarray,
    background: np.ndarray,
    threshold: int = 18,
    min_area_px: float = 40.0,
) -> np.ndarray | None:
    """The largest convex quadrilateral region of the moving blob: the most visible face (4, 2)
    [px, intrinsics convention], or None.

    Foreground: the largest blob of the colour difference to ``background`` (max over channels,
    above ``threshold``, opened). Inside it, the regions between Canny edges are the faces; each
    region's contour is approximated by a polygon, a convex one with 4 vertices is a face
    candidate; its sides are refined by line fits to the contour points and the corners are the
    intersections of adjacent sides.
    """
    diff = cv2.absdiff(frame, background).max(axis=-1)
    mask = (diff > threshold).astype(np.uint8)
    mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    if n <= 1:
        return None
    best = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    x, y, w, h, _ = stats[best]
    pad = 3
    x0, y0 = max(x - pad, 0), max(y - pad, 0)
    x1, y1 = min(x + w + pad, frame.shape[1]), min(y + h + pad, frame.shape[0])
    blob = (labels[y0:y1, x0:x1] == best).astype(np.uint8)
    gray = cv2.GaussianBlur(cv2.cvtColor(frame[y0:y1, x0:x1], cv2.COLOR_RGB2GRAY), (0, 0), 1.0)
    edges = cv2.Canny(gray, 20, 60)
    edges = cv2.dilate(edges, np.ones((3, 3), np.uint8))
    regions = blob & (edges == 0).astype(np.uint8)
    n_r, lab_r, st_r, _ = cv2.connectedComponentsWithStats(regions, connectivity=4)
    found, best_area = None, min_area_px
    for r in range(1, n_r):
        if st_r[r, cv2.CC_STAT_AREA] < best_area * 0.5:
            continue
        reg = cv2.dilate((lab_r == r).astype(np.uint8), np.ones((3, 3), np.uint8))
        cont, _ = cv2.findContours(reg, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        if not cont:
            continue
        c = max(cont, key=cv2.contourArea)
        area = cv2.contourArea(c)
        if area <= best_area:
            continue
        poly = cv2.approxPolyDP(c, 0.04 * cv2.arcLength(c, True), True)
        if len(poly) != 4 or not cv2.isContourConvex(poly):
            continue
        found, best_area = (c.reshape(-1, 2).astype(np.float64), poly.reshape(4, 2)), area
    if found is None:
        return None
    pts, poly = found
    # refine: fit a line to the contour points of each side (away from its corners)
    lines = []
    for i in range(4):
        a, b = poly[i].astype(float), poly[(i + 1) % 4].astype(float)
        d = b - a
        length = np.linalg.norm(d)
        u = d / max(length, 1e-9)
        rel = pts - a
        along = rel @ u
        dist = np.abs(rel @ np.array([-u[1], u[0]]))
        sel = (along > 0.15 * length) & (along < 0.85 * length) & (dist < 2.5)
        if sel.sum() < 3:
            lines.append(np.array([u[0], u[1], a[0], a[1]]))
            continue
        lines.append(
            cv2.fitLine(pts[sel].astype(np.float32), cv2.DIST_HUBER, 0, 0.01, 0.01).ravel()
        )
    corners = []
    for i in range(4):
        p = _intersect(lines[i - 1], lines[i])
        if p is None or np.linalg.norm(p - poly[i]) > 4.0:
            p = poly[i].astype(float)
        corners.append(p)
    return np.asarray(corners) + np.array([x0, y0]) + 0.5


def _face_to_box(face_rotation: np.ndarray, face_centre: np.ndarray, size: float):
    """(R_cam_box, centre) of the box behind a face (z axis of ``face_rotation`` normal to it)."""
    n = face_rotation[:, 2]
    if n @ face_centre < 0:  # the box lies beyond its visible face
        face_rotation = face_rotation @ np.diag([1.0, -1.0, -1.0])
        n = -n
    return face_rotation, face_centre + 0.5 * size * n


def pnp_face_track(frames, intrinsics, size: float, fps: float, background) -> FrameTrack:
    """OpenCV baseline: :func:`face_quad` and ``solvePnP(IPPE_SQUARE)`` per frame; velocity by
    differences of consecutive valid centres.

    Both cyclic orders of the quad are tried (IPPE_SQUARE needs the square's own), the smaller
    reprojection error wins; a fit with an RMS reprojection error above 2 px is not valid.
    """
    k = np.asarray(intrinsics, np.float64)
    t_n = len(frames)
    pos, vel = np.zeros((t_n, 3)), np.full((t_n, 3), np.nan)
    rot, valid = np.tile(np.eye(3), (t_n, 1, 1)), np.zeros(t_n, bool)
    quads = np.full((t_n, 4, 2), np.nan)
    obj = _square_object_points(size)
    t0 = time.perf_counter()
    for i, frame in enumerate(frames):
        q = face_quad(frame, background)
        if q is None:
            continue
        quads[i] = q
        best = None
        for order in (q, q[::-1]):
            # the corners and K both in the intrinsics convention (pixel centres at k + 1/2);
            # shifting only the corners to OpenCV's integer centres would bias the pose by
            # half a pixel (about 1.2 mm/m at fovy 45 deg, 640x480)
            img = order.astype(np.float64)
            ok, rvec, tvec = cv2.solvePnP(obj, img, k, None, flags=cv2.SOLVEPNP_IPPE_SQUARE)
            if not ok:
                continue
            proj = cv2.projectPoints(obj, rvec, tvec, k, None)[0].reshape(4, 2)
            err = float(np.sqrt(np.mean(np.sum((proj - img) ** 2, -1))))
            if best is None or err < best[0]:
                best = (err, cv2.Rodrigues(rvec)[0], tvec.ravel())
        if best is None or best[0] > 2.0 or best[2][2] <= 0:
            continue
        rot[i], pos[i] = _face_to_box(best[1], best[2], size)
        valid[i] = True
        if i > 0 and valid[i - 1]:
            vel[i] = (pos[i] - pos[i - 1]) * fps
    ms = 1e3 * (time.perf_counter() - t0) / max(t_n, 1)
    return FrameTrack(pos, rot, vel, valid, quads, ms)


def match_quad(previous: np.ndarray, quad: np.ndarray) -> np.ndarray:
    """``quad`` (4, 2) re-ordered (cyclic shift, either sense) to best match ``previous``."""
    best, best_d = quad, np.inf
    for q in (quad, quad[::-1]):
        for s in range(4):
            r = np.roll(q, -s, axis=0)
            d = float(np.sum(np.linalg.norm(r - previous, axis=-1)))
            if d < best_d:
                best, best_d = r, d
    return best


def _face_pose_from_points(points: np.ndarray):
    """(R with z normal to the face, face centre) from its corners A, B, C, D (4, 3) (AB || CD)."""
    a, b, c, d = points
    u1 = (b - a) + (d - c)
    u1 /= np.linalg.norm(u1)
    w = (c - a) + (d - b)
    n = np.cross(u1, w)
    n /= np.linalg.norm(n)
    u2 = np.cross(n, u1)
    return np.stack([u1, u2, n], axis=1), points.mean(0)


def paper_two_frame_track(quads, intrinsics, size: float, fps: float) -> FrameTrack:
    """The paper's two-frame method (Eqs. 1-38, :func:`estimate_motion`, closed form, metric by
    |AB| = ``size``) on the visible face's opposite sides in consecutive frames.

    Frame t takes the quads of frames t-1 and t (matched corner to corner by :func:`match_quad`):
    l1 = AB, l2 = CD two opposite sides (3D-parallel). The estimate's 3D points after the motion
    give the face, hence the box's pose at t; its points before and after give the velocity
    (c_t - c_{t-1}) * fps. Valid where both quads exist, the corners moved less than a quarter
    of the quad's size (the same face) and the method reports a valid estimate.

    Returns:
        :class:`FrameTrack` (``time_ms``: the batched method's time per frame, quads excluded).
    """
    from hec_jax.geometry.parallel_motion import estimate_motion

    quads = np.asarray(quads, np.float64)
    k = np.asarray(intrinsics, np.float64)
    t_n = len(quads)
    kinv = np.linalg.inv(k)
    norm = lambda q: q @ kinv[:2, :2].T + kinv[:2, 2]  # noqa: E731
    pairs, idx = [], []
    for t in range(1, t_n):
        if not (np.all(np.isfinite(quads[t])) and np.all(np.isfinite(quads[t - 1]))):
            continue
        q = match_quad(quads[t - 1], quads[t])
        scale = np.max(np.ptp(quads[t - 1], axis=0))
        if np.max(np.linalg.norm(q - quads[t - 1], axis=-1)) > 0.25 * scale:
            continue
        order = [0, 1, 3, 2]  # A B (side 0-1), C D (side 3-2): parallel, same sense
        pairs.append((norm(quads[t - 1][order]), norm(q[order])))
        idx.append(t)
    pos, vel = np.zeros((t_n, 3)), np.full((t_n, 3), np.nan)
    rot, valid = np.tile(np.eye(3), (t_n, 1, 1)), np.zeros(t_n, bool)
    t0 = time.perf_counter()
    if pairs:
        # padded to t_n pairs (one compilation per sequence length; the padding is discarded)
        before = np.zeros((t_n, 4, 2))
        after = np.zeros((t_n, 4, 2))
        before[: len(pairs)] = np.stack([p[0] for p in pairs])
        after[: len(pairs)] = np.stack([p[1] for p in pairs])
        before[len(pairs) :], after[len(pairs) :] = before[0], after[0]
        est = estimate_motion(before, after, size)
        ok = np.asarray(est.valid)
        p_before, p_after = np.asarray(est.points_before), np.asarray(est.points_after)
        for j, t in enumerate(idx):
            if not ok[j] or not np.all(np.isfinite(p_after[j])):
                continue
            r, c = _face_to_box(*_face_pose_from_points(p_after[j]), size)
            _, c0 = _face_to_box(*_face_pose_from_points(p_before[j]), size)
            rot[t], pos[t], vel[t], valid[t] = r, c, (c - c0) * fps, True
    ms = 1e3 * (time.perf_counter() - t0) / max(t_n, 1)
    return FrameTrack(pos, rot, vel, valid, np.asarray(quads), ms)
