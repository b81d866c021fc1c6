"""Camera frames of the scene at given joint positions (NumPy boundary, MuJoCo C renderer).

The closed hand-eye loop simulates in MJX and renders with MuJoCo C: :func:`render_model_like`
copies the kinematic geometry of an MJX model (pendulum conditions, moved hinge) into a C model,
and :class:`SceneCamera` renders the fixed camera at any ``qpos``. Headless rendering needs
``MUJOCO_GL=egl`` (or osmesa).
"""

from __future__ import annotations

import copy

import mujoco
import numpy as np

from hec_jax.mjx_scene.camera import IMAGE_HEIGHT, IMAGE_WIDTH, camera_intrinsics, camera_pose_world

# what decides where things are and how big they look (everything ``apply_conditions`` and a moved
# hinge change, and the rest of the kinematic tree for good measure)
_GEOMETRY_FIELDS = ("body_pos", "body_quat", "geom_pos", "geom_quat", "geom_size", "site_pos")

# software (Mesa) rendering is 3x faster without these, and the eye does not need them
_SLOW_FLAGS = ("mjRND_SHADOW", "mjRND_REFLECTION", "mjRND_SKYBOX", "mjRND_FOG", "mjRND_HAZE")


def render_model_like(m_c: mujoco.MjModel, mx) -> mujoco.MjModel:
    """A copy of the C model ``m_c`` with the kinematic geometry of the MJX model ``mx`` (unbatched).

    Raises:
        ValueError: ``mx`` is batched or does not match ``m_c``'s sizes.
    """
    out = copy.copy(m_c)
    for name in _GEOMETRY_FIELDS:
        src = np.asarray(getattr(mx, name))
        dst = getattr(out, name)
        if src.shape != dst.shape:
            raise ValueError(f"{name}: MJX model has shape {src.shape}, C model {dst.shape}")
        dst[...] = src
    return out


class SceneCamera:
    """Renders one camera of a model at given joint positions.

    Frames are (height, width, 3) uint8 RGB; ``intrinsics`` is K of the MJCF camera at that
    resolution and ``world_from_camera`` the camera pose in the pinhole convention (x right,
    y down, z forward), so that a camera-frame point p is ``R @ p + t`` in the world.

    Args:
        m_c: the C model to render (e.g. from :func:`render_model_like`).
        camera: camera name.
        width, height: [px].
        fast: drop shadows, reflections, skybox, fog and haze (3x faster in software rendering).
        hidden_geoms: names of geoms drawn fully transparent (e.g. to render a background).
    """

    def __init__(
        self,
        m_c: mujoco.MjModel,
        camera: str = "eye",
        width: int = IMAGE_WIDTH,
        height: int = IMAGE_HEIGHT,
        fast: bool = True,
        hidden_geoms: tuple[str, ...] = (),
    ):
        self.camera_id = mujoco.mj_name2id(m_c, mujoco.mjtObj.mjOBJ_CAMERA, camera)
        if self.camera_id < 0:
            raise ValueError(f"model has no camera {camera!r}")
        self.model = copy.copy(m_c)
        for name in hidden_geoms:
            gid = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_GEOM, name)
            if gid < 0:
                raise ValueError(f"model has no geom {name!r}")
            self.model.geom_rgba[gid, 3] = 0.0
        self.data = mujoco.MjData(self.model)
        self.intrinsics = camera_intrinsics(self.model, self.camera_id, width, height)
        mujoco.mj_kinematics(self.model, self.data)
        mujoco.mj_camlight(self.model, self.data)
        self.world_from_camera = camera_pose_world(self.model, self.data, self.camera_id)
        self._renderer = mujoco.Renderer(self.model, height, width)
        if fast:
            for flag in _SLOW_FLAGS:
                self._renderer.scene.flags[getattr(mujoco.mjtRndFlag, flag)] = False

    def render(self, qpos) -> np.ndarray:
        """The frame (H, W, 3) uint8 at joint positions ``qpos`` (nq,)."""
        qpos = np.asarray(qpos, dtype=np.float64)
        if qpos.shape != (self.model.nq,):
            raise ValueError(f"qpos must have shape ({self.model.nq},), got {qpos.shape}")
        self.data.qpos[:] = qpos
        mujoco.mj_kinematics(self.model, self.data)
        mujoco.mj_camlight(self.model, self.data)
        self._renderer.update_scene(self.data, camera=self.camera_id)
        return self._renderer.render()

    def to_world(self, p_cam, v_cam=None, a_cam=None):
        """Camera-frame position [m] (and velocity, acceleration) of a point -> world frame."""
        r, t = self.world_from_camera
        out = [r @ np.asarray(p_cam) + t]
        out += [r @ np.asarray(x) for x in (v_cam, a_cam) if x is not None]
        return out[0] if len(out) == 1 else tuple(out)

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
