"""The known box: corners, edges, faces, projection and visibility (pure JAX).

Object frame: origin at the box centre, axes along the edges; a pose maps object points to the
camera frame, ``X_cam = R X_obj + t`` (camera frame x right, y down, z forward). Corner, edge and
face numbering follow ``synthetic.CUBE_CORNERS_UNIT``, ``CUBE_EDGE_FAMILIES`` and ``CUBE_FACES``.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
from jax import Array

from hec_jax.geometry.camera import project_to_pixels
from hec_jax.geometry.synthetic import CUBE_CORNERS_UNIT, CUBE_EDGE_FAMILIES, CUBE_FACES

# (12, 2) corner indices of the 12 edges, family by family (x, y, z), and their family (12,).
EDGES = np.array([e for fam in CUBE_EDGE_FAMILIES for e in fam], dtype=np.int32)
EDGE_FAMILY = np.repeat(np.arange(3, dtype=np.int32), 4)
# (6, 4) corner indices of the faces (cyclic), (6, 3) outward normals in the object frame.
FACES = np.array([f for f, _ in CUBE_FACES], dtype=np.int32)
FACE_NORMALS = np.array([n for _, n in CUBE_FACES], dtype=float)


def _face_orientation() -> np.ndarray:
    """+1 where the cyclic corner order of a face turns counter-clockwise about its outward normal."""
    c = CUBE_CORNERS_UNIT[FACES]
    turn = np.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 1])
    return np.sign(np.sum(turn * FACE_NORMALS, axis=-1))


FACE_ORIENTATION = _face_orientation()
# (12, 2) the two faces adjacent to each edge.
EDGE_FACES = np.array(
    [[f for f in range(6) if a in FACES[f] and b in FACES[f]] for a, b in EDGES], dtype=np.int32
)


def cube_symmetries() -> np.ndarray:
    """(24, 3, 3) proper rotations mapping the cube onto itself (signed permutation matrices)."""
    out = []
    for perm in ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)):
        for signs in np.ndindex(2, 2, 2):
            m = np.zeros((3, 3))
            m[np.arange(3), perm] = 1.0 - 2.0 * np.asarray(signs)
            if np.linalg.det(m) > 0:
                out.append(m)
    return np.stack(out)


_SYMMETRIES = cube_symmetries()


def snap_to_symmetry(rotation: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """The labelling ``rotation @ S`` (S a cube symmetry) closest to ``reference``."""
    cands = rotation[None] @ _SYMMETRIES
    traces = np.einsum("nij,ij->n", cands, reference)
    return cands[int(np.argmax(traces))]


def nearest_labellings(rotations: Array, references: Array) -> Array:
    """(T, 3, 3) each ``rotations[t] @ S`` (S one of the cube's 24 symmetries) nearest
    ``references[t]`` (largest trace of ``references[t]^T rotations[t] S``, i.e. least angle);
    pure JAX, the batched form of :func:`snap_to_symmetry`.

    A cube's orientation is known only up to these labellings of its axes: the same box, its
    faces named otherwise. Ties (a rotation 45 deg from two labellings) go to the first in
    :func:`cube_symmetries`' order.
    """
    sym = jnp.asarray(_SYMMETRIES, rotations.dtype)
    cands = jnp.einsum("tij,njk->tnik", rotations, sym)  # (T, 24, 3, 3)
    traces = jnp.einsum("tnij,tij->tn", cands, references)
    best = jnp.argmax(traces, axis=1)
    return jnp.take_along_axis(cands, best[:, None, None, None], axis=1)[:, 0]


class Pose(NamedTuple):
    """Rigid pose of the box in the camera frame (a pytree).

    Attributes:
        rotation: (..., 3, 3) R, object axes in the camera frame.
        translation: (..., 3) t, box centre in the camera frame [m].
    """

    rotation: Array
    translation: Array


def box_corners(size) -> Array:
    """(8, 3) corners of a cube of edge ``size`` [m] in the object frame."""
    return jnp.asarray(CUBE_CORNERS_UNIT) * size


def corners_camera(pose: Pose, size) -> Array:
    """(..., 8, 3) corners in the camera frame [m]."""
    c = box_corners(size)
    return jnp.einsum("...ij,nj->...ni", pose.rotation, c) + pose.translation[..., None, :]


def project_corners(pose: Pose, size, intrinsics: Array) -> Array:
    """(..., 8, 2) pixel coordinates [px] of the corners (pinhole convention of ``intrinsics``)."""
    return project_to_pixels(corners_camera(pose, size), intrinsics)


def face_visibility(pose: Pose, size) -> Array:
    """(..., 6) bool: face turned towards the camera (outward normal . face centre < 0)."""
    corners = corners_camera(pose, size)
    centres = jnp.mean(corners[..., FACES, :], axis=-2)  # (..., 6, 3)
    normals = jnp.einsum("...ij,fj->...fi", pose.rotation, jnp.asarray(FACE_NORMALS))
    return jnp.sum(normals * centres, axis=-1) < 0


def image_face_visibility(pixels: Array) -> tuple[Array, Array]:
    """Visibility of the faces from the image alone: (..., 6) bool and (..., 6) image areas [px^2].

    A face is turned towards the camera iff its projected corner polygon keeps the turning sense
    it has about its outward normal (x right, y down: a face seen from the front with its corners
    counter-clockwise about the normal is clockwise in the image, i.e. of negative shoelace area).
    Needs only the labelled corner pixels (..., 8, 2), no pose.
    """
    p = pixels[..., FACES, :]  # (..., 6, 4, 2)
    q = jnp.roll(p, -1, axis=-2)
    shoelace = 0.5 * jnp.sum(p[..., 0] * q[..., 1] - p[..., 1] * q[..., 0], axis=-1)
    orient = jnp.asarray(FACE_ORIENTATION).reshape((1,) * (shoelace.ndim - 1) + (6,))
    signed = -shoelace * orient
    return signed > 0, jnp.maximum(signed, 0.0)


def edge_visibility(face_visible: Array) -> Array:
    """(..., 12) bool: an edge of a convex box is visible iff one of its two faces is."""
    return jnp.any(face_visible[..., EDGE_FACES], axis=-1)


def project_edges(pose: Pose, size, intrinsics: Array) -> Array:
    """(..., 12, 2, 2) pixel end points [px] of the 12 edges."""
    return project_corners(pose, size, intrinsics)[..., EDGES, :]


# ---------------------------------------------------------------------------------------------
# NumPy twins for the per-frame host code of the tracker (no JAX dispatch; same conventions).


def project_corners_np(
    rotation: np.ndarray, translation: np.ndarray, size, intrinsics
) -> np.ndarray:
    """NumPy :func:`project_corners` for one pose: (8, 2) [px]."""
    c = (CUBE_CORNERS_UNIT * size) @ np.asarray(rotation).T + np.asarray(translation)
    k = np.asarray(intrinsics)
    return (c[:, :2] / c[:, 2:3]) @ k[:2, :2].T + k[:2, 2]


def face_visibility_np(rotation: np.ndarray, translation: np.ndarray, size) -> np.ndarray:
    """NumPy :func:`face_visibility` for one pose: (6,) bool."""
    c = (CUBE_CORNERS_UNIT * size) @ np.asarray(rotation).T + np.asarray(translation)
    centres = c[FACES].mean(1)
    normals = FACE_NORMALS @ np.asarray(rotation).T
    return np.sum(normals * centres, -1) < 0


def image_face_area_np(pixels: np.ndarray) -> np.ndarray:
    """NumPy twin of the areas of :func:`image_face_visibility`: (6,) [px^2] (0 if turned away)."""
    p = pixels[FACES]
    q = np.roll(p, -1, axis=-2)
    shoelace = 0.5 * np.sum(p[..., 0] * q[..., 1] - p[..., 1] * q[..., 0], axis=-1)
    return np.maximum(-shoelace * FACE_ORIENTATION, 0.0)
