"""Synthetic ground truth: a cube of known edge seen by a pinhole camera before and after a motion.

NumPy only (a data generator at the boundary, seeded with ``numpy.random.Generator``); used by the
tests and by ``benchmarks/eye.py``. Camera frame: x right, y down, z forward.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

# Unit cube corners (index = 4 * bx + 2 * by + bz, coordinates in {-1/2, +1/2}).
CUBE_CORNERS_UNIT = np.array(
    [[bx - 0.5, by - 0.5, bz - 0.5] for bx in (0, 1) for by in (0, 1) for bz in (0, 1)]
)
# The 12 edges as corner index pairs, grouped into the 3 parallel families (along x, y, z).
CUBE_EDGE_FAMILIES = (
    ((0, 4), (1, 5), (2, 6), (3, 7)),  # along x
    ((0, 2), (1, 3), (4, 6), (5, 7)),  # along y
    ((0, 1), (2, 3), (4, 5), (6, 7)),  # along z
)
# Faces as corner index quadruples in cyclic order, with their outward normal (object frame).
CUBE_FACES = (
    ((0, 1, 3, 2), (-1, 0, 0)),
    ((4, 6, 7, 5), (1, 0, 0)),
    ((0, 4, 5, 1), (0, -1, 0)),
    ((2, 3, 7, 6), (0, 1, 0)),
    ((0, 2, 6, 4), (0, 0, -1)),
    ((1, 5, 7, 3), (0, 0, 1)),
)


def rotation_from_axis_angle(axis: np.ndarray, angle: float | np.ndarray) -> np.ndarray:
    """Rodrigues' formula; axis (..., 3) (normalised here), angle (...) [rad] -> (..., 3, 3)."""
    axis = np.asarray(axis, dtype=float)
    axis = axis / np.linalg.norm(axis, axis=-1, keepdims=True)
    angle = np.asarray(angle, dtype=float)[..., None, None]
    kx = np.zeros(axis.shape[:-1] + (3, 3))
    kx[..., 0, 1], kx[..., 0, 2] = -axis[..., 2], axis[..., 1]
    kx[..., 1, 0], kx[..., 1, 2] = axis[..., 2], -axis[..., 0]
    kx[..., 2, 0], kx[..., 2, 1] = -axis[..., 1], axis[..., 0]
    eye = np.broadcast_to(np.eye(3), kx.shape)
    return eye + np.sin(angle) * kx + (1.0 - np.cos(angle)) * (kx @ kx)


def random_rotation(rng: np.random.Generator, shape=()) -> np.ndarray:
    """Uniformly distributed rotations (..., 3, 3) (from normalised Gaussian quaternions)."""
    q = rng.normal(size=tuple(shape) + (4,))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def rotation_error_deg(estimated: np.ndarray, true: np.ndarray) -> np.ndarray:
    """Angle [deg] of estimated^T true (..., 3, 3) -> (...).

    atan2(|axis part|, cos part) keeps full precision near 0 (arccos of the trace does not: it
    cannot resolve angles below about 1e-6 deg in float64).
    """
    rel = np.einsum("...ji,...jk->...ik", np.asarray(estimated, float), np.asarray(true, float))
    cos = 0.5 * (np.trace(rel, axis1=-2, axis2=-1) - 1.0)
    skew = np.stack(
        [
            rel[..., 2, 1] - rel[..., 1, 2],
            rel[..., 0, 2] - rel[..., 2, 0],
            rel[..., 1, 0] - rel[..., 0, 1],
        ],
        axis=-1,
    )
    sin = 0.5 * np.linalg.norm(skew, axis=-1)
    return np.degrees(np.arctan2(sin, cos))


@dataclass(frozen=True)
class SceneConfig:
    """Static parameters of the synthetic scenes (defaults: the benchmark of the foundation issue)."""

    edge: float = 0.1  # cube edge [m]
    depth_range: tuple[float, float] = (0.5, 2.0)  # distance of the cube centre from the camera [m]
    focal_px: float = 600.0  # focal length [px]
    width: int = 640  # image size [px]
    height: int = 480
    small_rotation_deg: float = 5.0  # largest rotation of a "small" motion [deg]
    small_translation: float = 0.02  # largest translation of a "small" motion [m]
    large_rotation_deg: float = 60.0
    large_translation: float = 0.2

    @property
    def intrinsics(self) -> np.ndarray:
        """(3, 3) pinhole K [px] of this camera (principal point at the image centre)."""
        return np.array(
            [[self.focal_px, 0, self.width / 2], [0, self.focal_px, self.height / 2], [0, 0, 1.0]]
        )


class CubeMotionScenes(NamedTuple):
    """A batch of two-view cube scenes (leading axis = scene).

    Attributes:
        corners_before, corners_after: (n, 8, 3) cube corners in the camera frame [m].
        rotation: (n, 3, 3) true Phi (P' = Phi P + Gamma, camera frame).
        translation: (n, 3) true Gamma [m].
        pair: (n, 4) corner indices of A, B, C, D: AB and CD parallel cube edges.
        pixels_before, pixels_after: (n, 8, 2) noisy pixel coordinates of all corners [px].
        points_before, points_after: (n, 4, 2) noisy normalised coordinates of A, B, C, D.
        noise_px: the pixel noise standard deviation used.
    """

    corners_before: np.ndarray
    corners_after: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    pair: np.ndarray
    pixels_before: np.ndarray
    pixels_after: np.ndarray
    points_before: np.ndarray
    points_after: np.ndarray
    noise_px: float


def make_cube_scenes(
    rng: np.random.Generator,
    n: int,
    config: SceneConfig = SceneConfig(),
    motion: str = "mixed",
    noise_px: float = 0.0,
    in_view: bool = True,
) -> CubeMotionScenes:
    """Random two-view scenes of a cube with a random pair of parallel edges as (A, B, C, D).

    Cube pose: uniformly random orientation, centre at a random distance in ``depth_range`` inside
    the camera's field of view. Motion: random axis through the cube centre, angle uniform in
    (0, max] and a random translation of the centre up to the max ("small", "large" or "mixed":
    half of each). The pair (AB, CD) is a random pair of edges of one parallel family, with CD in the
    same or opposite direction as AB. Pixel noise: i.i.d. Gaussian, ``noise_px`` [px], added to
    every projected corner. With ``in_view`` the poses are redrawn until all corners before and
    after lie inside the image.
    """
    if motion not in ("small", "large", "mixed"):
        raise ValueError(f"motion must be 'small', 'large' or 'mixed', got {motion!r}")
    if n <= 0:
        raise ValueError(f"n must be positive, got {n}")
    k = config.intrinsics
    out = {key: [] for key in ("cb", "ca", "rot", "tr")}
    while len(out["cb"]) < n:
        depth = rng.uniform(*config.depth_range)
        half_w = 0.5 * config.width / config.focal_px
        half_h = 0.5 * config.height / config.focal_px
        direction = np.array(
            [rng.uniform(-0.7, 0.7) * half_w, rng.uniform(-0.7, 0.7) * half_h, 1.0]
        )
        centre = depth * direction / np.linalg.norm(direction)
        corners = centre + CUBE_CORNERS_UNIT @ random_rotation(rng).T * config.edge
        small = motion == "small" or (motion == "mixed" and rng.random() < 0.5)
        max_rot = config.small_rotation_deg if small else config.large_rotation_deg
        max_tr = config.small_translation if small else config.large_translation
        angle = np.radians(rng.uniform(0.05, 1.0) * max_rot)
        rot = rotation_from_axis_angle(rng.normal(size=3), angle)
        shift = rng.normal(size=3)
        shift *= rng.uniform(0.0, max_tr) / np.linalg.norm(shift)
        tr = centre + shift - rot @ centre  # centre moves by `shift`, rotates about itself
        corners_after = corners @ rot.T + tr
        if in_view:
            ok = True
            for c in (corners, corners_after):
                if np.any(c[:, 2] < 0.2):
                    ok = False
                    break
                pix = c[:, :2] / c[:, 2:] @ k[:2, :2].T + k[:2, 2]
                inside = (pix >= 0) & (pix <= [config.width, config.height])
                ok &= bool(np.all(inside))
            if not ok:
                continue
        out["cb"].append(corners)
        out["ca"].append(corners_after)
        out["rot"].append(rot)
        out["tr"].append(tr)
    corners_before, corners_after = np.stack(out["cb"]), np.stack(out["ca"])
    family = rng.integers(0, 3, size=n)
    edge_pick = np.array([rng.choice(4, size=2, replace=False) for _ in range(n)])
    flip = rng.random(n) < 0.5
    pair = np.empty((n, 4), dtype=int)
    for i in range(n):
        e1 = CUBE_EDGE_FAMILIES[family[i]][edge_pick[i, 0]]
        e2 = CUBE_EDGE_FAMILIES[family[i]][edge_pick[i, 1]]
        pair[i] = (e1[0], e1[1]) + ((e2[1], e2[0]) if flip[i] else (e2[0], e2[1]))

    def pixels(c):
        pix = c[..., :2] / c[..., 2:] * config.focal_px + k[:2, 2]
        return pix + rng.normal(scale=noise_px, size=pix.shape) if noise_px > 0 else pix

    pix_b, pix_a = pixels(corners_before), pixels(corners_after)
    to_norm = lambda p: (p - k[:2, 2]) / config.focal_px  # noqa: E731
    idx = (np.arange(n)[:, None], pair)
    return CubeMotionScenes(
        corners_before=corners_before,
        corners_after=corners_after,
        rotation=np.stack(out["rot"]),
        translation=np.stack(out["tr"]),
        pair=pair,
        pixels_before=pix_b,
        pixels_after=pix_a,
        points_before=to_norm(pix_b)[idx],
        points_after=to_norm(pix_a)[idx],
        noise_px=noise_px,
    )
