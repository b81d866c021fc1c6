"""The lab scene (issue 24, point 5): visual only, an oblique camera that sees three faces of the
cube, selectable with ``CameraConfig.scene``; and the industrial camera preset
(``CameraDefects.industrial``, ``--camera-model industrial``). Small renders, no loop compile."""

import dataclasses

import mujoco
import numpy as np
import pytest

from hec_jax import loop as tl
from hec_jax.cli import parse
from hec_jax.loop.cli import TaskRun, task_default
from hec_jax.mjx_scene import CUBE_EDGE, X_HOME, load_mj_model, scene_ids, solve_posture
from hec_jax.mjx_scene.camera import project
from hec_jax.mjx_scene.lab import lab_model, scene_model
from hec_jax.mjx_scene.render import SceneCamera, render_model_like, with_plane_grid

W, H = 160, 120
OBJ = mujoco.mjtObj


@pytest.fixture(scope="module")
def models():
    return load_mj_model(), lab_model()


def _names(m, kind, n):
    return [mujoco.mj_id2name(m, kind, i) for i in range(n)]


def _release(m, hinge_x=0.55, angle=-0.5):
    """qpos at the catching preset's release (hinge moved in the model ``m``, in place)."""
    m.body_pos[mujoco.mj_name2id(m, OBJ.mjOBJ_BODY, "ceiling"), 0] = hinge_x
    q = m.qpos0.copy()
    q[m.jnt_qposadr[mujoco.mj_name2id(m, OBJ.mjOBJ_JOINT, "hinge")]] = angle
    return q


def _controlled_swing(m) -> tuple[np.ndarray, int]:
    """((500, nq) qpos, steps with a contact) of 500 steps of the C model ``m`` (changed in
    place: the hinge moved) from the release, the hand waiting at X_HOME held by the constant
    torque that balances gravity there: the swinging cube strikes it (from step ~413)."""
    ids = scene_ids(m)
    q = _release(m)
    q[list(ids.arm_qpos)] = solve_posture(m, ids, X_HOME)
    d = mujoco.MjData(m)
    d.qpos[:] = q
    mujoco.mj_forward(m, d)
    d.ctrl[:] = d.qfrc_bias[list(ids.arm_dof)]  # [N m]
    out, contact_steps = [], 0
    for _ in range(500):
        mujoco.mj_step(m, d)
        out.append(d.qpos.copy())
        contact_steps += d.ncon > 0
    return np.array(out), contact_steps


def test_lab_is_scene_xml_first_then_visual_only_geoms(models):
    void, lab = models
    for kind, n in (
        (OBJ.mjOBJ_BODY, void.nbody),
        (OBJ.mjOBJ_GEOM, void.ngeom),
        (OBJ.mjOBJ_SITE, void.nsite),
        (OBJ.mjOBJ_JOINT, void.njnt),
        (OBJ.mjOBJ_ACTUATOR, void.nu),
        (OBJ.mjOBJ_CAMERA, void.ncam),
    ):
        assert _names(lab, kind, n) == _names(void, kind, n)
    assert (lab.nq, lab.nv, lab.nu, lab.njnt, lab.npair) == (
        void.nq,
        void.nv,
        void.nu,
        void.njnt,
        void.npair,
    )
    added = np.arange(void.ngeom, lab.ngeom)
    assert len(added) > 10
    assert not lab.geom_contype[added].any() and not lab.geom_conaffinity[added].any()
    np.testing.assert_array_equal(lab.body_mass[: void.nbody], void.body_mass)
    room = np.arange(void.nbody, lab.nbody)  # one static body, welded to the world
    assert len(room) == 1 and lab.body_weldid[room[0]] == 0 and lab.body_jntnum[room[0]] == 0


def test_lab_physics_is_bit_identical(models):
    """The same controlled swing (a few hundred 1 ms steps, hand-cube contact included) in the
    void and the lab C models: the same qpos, bit for bit."""
    (void_q, void_contacts), (lab_q, lab_contacts) = [
        _controlled_swing(m0.__copy__()) for m0 in models
    ]
    np.testing.assert_array_equal(void_q, lab_q)
    assert void_contacts == lab_contacts > 10  # the cube struck the hand
    assert np.ptp(void_q, axis=0).min() > 1e-3  # everything moved


def test_render_model_like_fills_the_simulated_prefix(models):
    void, lab = models
    mx = void.__copy__()
    mx.body_pos[mujoco.mj_name2id(mx, OBJ.mjOBJ_BODY, "ceiling"), 0] = 0.55
    out = render_model_like(lab, mx)
    np.testing.assert_array_equal(out.body_pos[: void.nbody], mx.body_pos)
    np.testing.assert_array_equal(out.body_pos[void.nbody :], lab.body_pos[void.nbody :])
    np.testing.assert_array_equal(out.geom_size[void.ngeom :], lab.geom_size[void.ngeom :])
    with pytest.raises(ValueError, match="body_pos"):
        render_model_like(void, lab)


def test_lab_render_differs_from_void_where_expected(models):
    """The void frame is mostly black backdrop; the lab's has (almost) none, the cube is where the
    lab camera's calibration puts it, and its shadow and image are absent from the background
    shot."""
    void, lab = models
    m_void, m_lab = void.__copy__(), lab.__copy__()
    q = _release(m_void)
    _release(m_lab)
    with SceneCamera(m_void, "eye", W, H) as cam:
        f_void = cam.render(q)
    with SceneCamera(m_lab, "eye", W, H, shadows=True) as cam:
        f_lab = cam.render(q)
        cube = mujoco.mj_name2id(m_lab, OBJ.mjOBJ_BODY, "cube")
        uv, depth = project(cam.intrinsics, *cam.world_from_camera, cam.data.xpos[cube])
    with SceneCamera(m_lab, "eye", W, H, True, ("cube", "rod"), shadows=True) as cam:
        bg_lab = cam.render(q)
    dark = lambda f: (f.max(axis=2) < 10).mean()  # noqa: E731
    assert dark(f_void) > 0.5 and dark(f_lab) < 0.01
    u, v = np.round(uv[0]).astype(int)
    assert 0 < u < W and 0 < v < H and 1.0 < depth[0] < 3.0
    r, g, b = f_lab[v, u].astype(int)
    assert r > g > b and r - b > 60  # the cube's orange, not the room
    changed = np.abs(f_lab.astype(int) - bg_lab.astype(int)).max(axis=2) > 20
    assert changed[v, u]
    # the pendulum, its shadow: all change near the cube or along the rod, above the floor
    assert changed.mean() < 0.1


@pytest.mark.parametrize("hinge_x, angle", [(0.55, -0.5), (0.55, 0.0), (0.35, -0.5), (0.35, 0.4)])
def test_lab_camera_sees_three_faces_of_the_cube(models, hinge_x, angle):
    """Over the swing, for both presets' hinge positions, the cube's outward face normals point
    toward the lab camera for three faces (-x, front, top), at least two of them at less than
    78 deg from the line of sight (cosine > 0.2; issue 24 asks for 2-3 faces), and the cube is
    in the image.
    """
    m = models[1].__copy__()
    q = _release(m, hinge_x, angle)
    with SceneCamera(m, "eye", W, H) as cam:
        cam.pose(q)
        cube = mujoco.mj_name2id(m, OBJ.mjOBJ_BODY, "cube")
        c, r_cube = cam.data.xpos[cube], cam.data.xmat[cube].reshape(3, 3)
        p_cam = cam.world_from_camera[1]
        normals = np.concatenate([r_cube.T, -r_cube.T])  # rows: +x, +y, +z, -x, -y, -z (world)
        ray = p_cam - (c + 0.5 * CUBE_EDGE * normals)  # face centre -> camera
        cos = (normals * ray).sum(axis=1) / np.linalg.norm(ray, axis=1)
        assert (cos > 0).sum() == 3 and (cos > 0.2).sum() >= 2
        uv, _ = project(cam.intrinsics, *cam.world_from_camera, c)
        assert 0.05 * W < uv[0, 0] < 0.95 * W and 0.05 * H < uv[0, 1] < 0.95 * H


def test_scene_model_and_config():
    # the lab is the loop's default scene (issue 24, point 5); real time keeps the void
    assert tl.CameraConfig().scene == "lab" and tl.catching().camera.scene == "lab"
    assert tl.CameraConfig.void_perfect().scene == "void"
    assert (
        parse(TaskRun(experiment=tl.catching()), ["--scene", "void"]).experiment.camera.scene
        == "void"
    )
    assert scene_model("void").ngeom == load_mj_model().ngeom
    with pytest.raises(ValueError, match="scene"):
        scene_model("moon")
    run = parse(TaskRun(experiment=tl.catching()), ["--scene", "lab"])
    assert run.experiment.camera.scene == "lab"
    with pytest.raises(SystemExit):  # the default camera's defects are simulated-time only
        parse(TaskRun(experiment=tl.catching()), ["--scene", "lab", "--realtime"])
    # with --realtime the task scripts' default camera is the real-time one; the lab is allowed
    argv = ["--realtime", "--eye", "camera"]
    run = parse(task_default("catching", argv), argv)
    assert run.experiment.camera == tl.CameraConfig.void_perfect()
    run = parse(task_default("catching", argv + ["--scene", "lab"]), argv + ["--scene", "lab"])
    assert run.experiment.camera == tl.CameraConfig.void_perfect(scene="lab")
    assert task_default("hitting", []).experiment.camera == tl.CameraConfig()


def test_industrial_camera_is_the_default_and_perfect_one_flag():
    ind = tl.CameraDefects.industrial()
    assert tl.CameraConfig().camera_model == "industrial"
    assert tl.CameraConfig().applied_defects == ind
    assert tl.catching().camera.applied_defects == ind == tl.hitting().camera.applied_defects
    perfect = parse(TaskRun(experiment=tl.catching()), ["--camera-model", "perfect"])
    assert perfect.experiment.camera.applied_defects == tl.CameraDefects()
    assert tl.CameraConfig.void_perfect().applied_defects == tl.CameraDefects()
    # what a run folder records is what runs, and recording it again changes nothing
    cam = tl.CameraConfig()
    assert cam.resolved().defects == ind and cam.resolved().tracker == cam.tracker
    assert cam.resolved().resolved() == cam.resolved()
    # the ranges argued in its docstring (issue 24: a plausible machine-vision camera)
    assert 1 <= ind.noise_grey <= 3 and ind.blur_renders > 1 and 0 < ind.defocus_px <= 1
    assert 0.005 <= ind.focal_error <= 0.02 and 1 <= ind.centre_error_px <= 2
    assert 0 < ind.jitter_s <= 0.002
    run = parse(TaskRun(experiment=tl.catching()), ["--camera-model", "industrial"])
    assert run.experiment.camera.applied_defects == ind
    # a defect flag given keeps its value, the seed too; the rest are the preset's
    run = parse(
        TaskRun(experiment=tl.catching()),
        ["--camera-model", "industrial", "--jitter-s", "0.002", "--defect-seed", "4"],
    )
    want = dataclasses.replace(ind, jitter_s=0.002, defect_seed=4)
    assert run.experiment.camera.applied_defects == want
    with pytest.raises(SystemExit):  # the real-time loop has no defects
        parse(TaskRun(experiment=tl.catching()), ["--camera-model", "industrial", "--realtime"])


def test_plane_grid_is_rendering_only(models):
    """``with_plane_grid``: a copy whose planes alone get the new grid spacing; the physics is
    the scene's (the controlled swing of ``test_lab_physics_is_bit_identical``, bit for bit);
    None gives the model itself; a spacing that is not finite and > 0 is refused."""
    void, lab = models
    for m0 in models:
        before = m0.geom_size.copy()
        out = with_plane_grid(m0, 0.05)
        assert out is not m0 and with_plane_grid(m0, None) is m0
        planes = m0.geom_type == int(mujoco.mjtGeom.mjGEOM_PLANE)
        assert planes.any()
        np.testing.assert_array_equal(out.geom_size[planes, 2], 0.05)
        np.testing.assert_array_equal(out.geom_size[planes, :2], m0.geom_size[planes, :2])
        np.testing.assert_array_equal(out.geom_size[~planes], m0.geom_size[~planes])
        np.testing.assert_array_equal(m0.geom_size, before)  # the original is untouched
    trajs = [_controlled_swing(m)[0] for m in (void.__copy__(), with_plane_grid(void, 0.5))]
    np.testing.assert_array_equal(trajs[0], trajs[1])  # the grid is visual: a check of that
    for bad in (0.0, -0.1, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="plane grid spacing"):
            with_plane_grid(void, bad)


def test_plane_grid_changes_only_the_floors_shading(models):
    """At 640x480 without multisampling (the real-time camera's frames), scene.xml's floor
    drawn at a 0.05 m grid instead of 0.01: every pixel that changes is one of the floor's
    (the pixels the floor changes against a render without it), the cube, the rod and the arm
    are bit for bit the same, and the floor's pixels change by at most a grey level at the
    median."""
    void = models[0].__copy__()
    void.vis.quality.offsamples = 0
    q = _release(void)
    frames = {}
    for name, m, hidden in (
        ("scene", void, ()),
        ("coarse", with_plane_grid(void, 0.05), ()),
        ("no floor", void, ("floor",)),
    ):
        with SceneCamera(m, "eye", 640, 480, True, hidden) as cam:
            frames[name] = cam.render(q).astype(int)
    floor = np.abs(frames["scene"] - frames["no floor"]).max(axis=2) > 0
    change = np.abs(frames["coarse"] - frames["scene"]).max(axis=2)
    assert floor.mean() > 0.1 and change.any()  # the floor is in view, and the grid shows
    # a changed pixel outside the floor's image would be an object drawn differently
    outside = (change > 0) & ~floor
    assert not outside.any(), f"{int(outside.sum())} pixels off the floor changed"
    assert np.median(change[change > 0]) <= 1
