"""The eye's one camera convention and its layering: geometry imports nothing else of hec_jax."""

import ast
from pathlib import Path

import mujoco
import numpy as np
import pytest

import hec_jax.geometry as G
from hec_jax.mjx_scene import camera as scene_camera
from hec_jax.mjx_scene import load_mj_model
from hec_jax.mjx_scene.render import body_in_camera


def test_geometry_imports_no_world():
    """hec_jax.geometry imports no other part of hec_jax and no MuJoCo (read from the source)."""
    for path in Path(G.__file__).parent.glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                names = [node.module or ""] if node.level == 0 else ["hec_jax.geometry"]
            else:
                continue
            for name in names:
                assert not name.startswith("mujoco"), (path.name, name)
                assert not name.startswith("hec_jax") or name.startswith("hec_jax.geometry"), (
                    path.name,
                    name,
                )


def test_intrinsics_from_fovy():
    k = G.intrinsics_from_fovy(90.0, 640, 480)
    np.testing.assert_allclose(k, [[240.0, 0, 320.0], [0, 240.0, 240.0], [0, 0, 1]], atol=1e-12)
    G.check_intrinsics(k)
    for bad in ((0.0, 640, 480), (180.0, 640, 480), (45.0, 0, 480), (45.0, 640, -1)):
        with pytest.raises(ValueError):
            G.intrinsics_from_fovy(*bad)


def test_mujoco_camera_to_pinhole():
    """The scene camera read through mjx_scene uses the geometry conversion: a body straight ahead
    of the camera projects to the image centre, world up is image up (smaller v)."""
    m = load_mj_model()
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    cam = scene_camera.camera_id(m, "eye")
    assert scene_camera.camera_id(m, cam) == cam
    with pytest.raises(ValueError):
        scene_camera.camera_id(m, "nope")
    with pytest.raises(ValueError):
        scene_camera.camera_id(m, m.ncam)
    k = scene_camera.camera_intrinsics(m, "eye", 320, 240)
    np.testing.assert_array_equal(k, G.intrinsics_from_fovy(float(m.cam_fovy[cam]), 320, 240))
    r, p = scene_camera.camera_pose_world(m, d, "eye")
    np.testing.assert_array_equal(r, G.pinhole_rotation_from_mujoco(d.cam_xmat[cam]))
    np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(p, d.cam_xpos[cam], atol=1e-12)
    # a point 2 m along MuJoCo's viewing direction (its camera's -z axis): the image centre
    ahead = d.cam_xpos[cam] - 2.0 * d.cam_xmat[cam].reshape(3, 3)[:, 2]
    centre = G.project_to_pixels(np.asarray(r.T @ (ahead - p)), k)
    np.testing.assert_allclose(np.asarray(centre), [160.0, 120.0], atol=1e-9)
    up = G.project_to_pixels(np.asarray(r.T @ (ahead + [0.0, 0.0, 0.1] - p)), k)
    assert float(up[1]) < 120.0
    # a body: its camera-frame pose is the world pose seen through the same rotation
    pos, rot = body_in_camera(m, d, "cube", "eye")
    bid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "cube")
    np.testing.assert_allclose(r @ pos + p, d.xpos[bid], atol=1e-12)
    np.testing.assert_allclose(r @ rot, d.xmat[bid].reshape(3, 3), atol=1e-12)
    assert pos[2] > 0  # in front of the camera
