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
