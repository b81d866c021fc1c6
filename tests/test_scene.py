"""The MJX scene against MuJoCo C: model conditions, dynamics quantities, contact force, camera."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx

from hec_jax import control as C
from hec_jax import loop as L
from hec_jax import mjx_scene as S
from hec_jax.loop import observation as observe_mod
from hec_jax.mjx_scene._mjx_internal import inertia_storage
from hec_jax.mjx_scene.sim import _mjx_ctx

N_BATCH = 4  # every call of the shared compiled function uses this batch size (one compile)
PLANE = [0, 2]  # task-plane components (x, z) of world vectors

CONDS = [
    dict(rod_length=0.6, cube_mass=0.7, hinge_damping=0.002),
    dict(rod_length=0.45, cube_mass=1.1, hinge_damping=0.05),
]


@pytest.fixture(scope="module")
def scene():
    mm = S.load_mj_model()
    ids = S.scene_ids(mm)
    return mm, ids, S.load_mjx_model(mm)


@pytest.fixture(scope="module")
def quantities(scene):
    """One compiled, vmapped function: apply_conditions + full forward (with contact solve)."""
    mm, ids, mx = scene

    def one(c, qpos, qvel, ctrl):
        m = S.apply_conditions(mx, ids, c)
        d = mjx.make_data(m).replace(qpos=qpos, qvel=qvel, ctrl=ctrl)
        with _mjx_ctx():
            d = mjx.forward(m, d)
        obs = L.observe(m, ids, S.SimStep(d=d, f_int=jnp.zeros(3), t=d.time))
        J_fd = jax.jacfwd(lambda q: observe_mod.hand_position(m, d, ids, q))(
            qpos[np.array(ids.arm_qpos)]
        )
        return dict(
            M=S.full_mass_matrix(m, d),
            h=S.bias_force(d),
            qacc=d.qacc,
            site_xpos=d.site_xpos,
            J=obs.J,
            J_autodiff=J_fd,
            jdot_qdot=obs.jdot_qdot,
            x_o=obs.x_o,
            xd_o=obs.xd_o,
            f_contact=S.hand_contact_force(m, d, ids),
            sensor=d.sensordata[:3],
            site_xmat=d.site_xmat,
        )

    return jax.jit(jax.vmap(one))


def _random_states(rng, n, ids, contact=False):
    qpos = np.zeros((n, 4))
    qpos[:, :3] = rng.uniform(-2.0, 2.0, size=(n, 3))
    qpos[:, 3] = rng.uniform(-0.8, 0.8, size=n)
    qvel = rng.normal(size=(n, 4))
    ctrl = rng.uniform(-10, 10, size=(n, 3))
    return qpos, qvel, ctrl


def _stack(conds):
    return jax.tree.map(lambda *x: jnp.stack(x), *conds)


def test_apply_conditions_matches_compiler(scene):
    """apply_conditions writes the same masses/inertias/positions the MuJoCo compiler computes."""
    mm, ids, mx = scene
    for kw in CONDS:
        c = S.default_conditions(**kw)
        m2 = S.apply_conditions(mx, ids, c)
        mc = S.mj_model_with_conditions(c)
        for f in (
            "body_mass",
            "body_subtreemass",
            "body_inertia",
            "body_ipos",
            "body_iquat",
            "body_pos",
            "geom_size",
            "geom_pos",
            "dof_damping",
            "body_invweight0",
            "dof_invweight0",
        ):
            np.testing.assert_allclose(np.asarray(getattr(m2, f)), getattr(mc, f), atol=1e-12)


def test_dynamics_match_mujoco_c(scene, quantities):
    """M, h, J, J' theta', site positions and qacc (with conditions applied) equal MuJoCo C's."""
    mm, ids, _ = scene
    rng = np.random.default_rng(0)
    n = N_BATCH
    worst = {}
    for kw in CONDS:
        c = S.default_conditions(**kw)
        qpos, qvel, ctrl = _random_states(rng, n, ids)
        out = jax.tree.map(np.asarray, quantities(_stack([c] * n), qpos, qvel, ctrl))
        mc = S.mj_model_with_conditions(c)
        for i in range(n):
            d = mujoco.MjData(mc)
            d.qpos[:], d.qvel[:], d.ctrl[:] = qpos[i], qvel[i], ctrl[i]
            mujoco.mj_forward(mc, d)
            cq = S.c_quantities(mc, d, ids)
            obs_c = L.observe_c(ids, d.qpos, d.qvel, cq, np.zeros(3))
            pairs = dict(
                M=(out["M"][i], cq.M),
                h=(out["h"][i], cq.h),
                qacc=(out["qacc"][i], d.qacc),
                site_xpos=(out["site_xpos"][i], d.site_xpos),
                J=(out["J"][i], np.asarray(obs_c.J)),
                J_autodiff=(out["J_autodiff"][i], np.asarray(obs_c.J)),
                jdot_qdot=(out["jdot_qdot"][i], np.asarray(obs_c.jdot_qdot)),
                x_o=(out["x_o"][i], np.asarray(obs_c.x_o)),
                xd_o=(out["xd_o"][i], np.asarray(obs_c.xd_o)),
            )
            for k, (a, b) in pairs.items():
                err = np.max(np.abs(a - b)) / max(1.0, np.max(np.abs(b)))
                worst[k] = max(worst.get(k, 0.0), err)
    print("max relative error vs MuJoCo C:", {k: f"{v:.1e}" for k, v in worst.items()})
    for k, v in worst.items():
        assert v < 1e-9, (k, v)


def test_operational_inertia_matches_c(scene, quantities):
    """M_x (Eq. 44) from MJX quantities equals inv(J M^-1 J^T) from MuJoCo C's mj_fullM/mj_jacSite."""
    mm, ids, _ = scene
    c = S.default_conditions()
    q_home = S.solve_posture(mm, ids, S.X_HOME)
    qpos = np.zeros((N_BATCH, 4))
    qpos[:, :3] = q_home
    qpos[1, :3] = q_home + np.array([0.3, -0.4, 0.2])
    out = jax.tree.map(
        np.asarray,
        quantities(_stack([c] * N_BATCH), qpos, np.zeros((N_BATCH, 4)), np.zeros((N_BATCH, 3))),
    )
    for i in range(2):
        d = mujoco.MjData(mm)
        d.qpos[:] = qpos[i]
        mujoco.mj_forward(mm, d)
        cq = S.c_quantities(mm, d, ids)
        Jc = cq.J_hand[[0, 2]][:, :3]
        Mx_c = np.linalg.inv(Jc @ np.linalg.solve(cq.M[:3, :3], Jc.T))
        Mx, cond = C.operational_inertia(out["M"][i][:3, :3], out["J"][i], 1e-3)
        np.testing.assert_allclose(np.asarray(Mx), Mx_c, rtol=1e-5)
        assert 1.0 <= float(cond) < 10.0


def test_contact_force_sign_magnitude(scene, quantities):
    """Force ON the hand: equals mj_contactForce (C) and the wrist force-sensor balance, and pushes
    the hand away from the cube."""
    mm, ids, _ = scene
    c = S.default_conditions()
    q_home = S.solve_posture(mm, ids, S.X_HOME)
    qpos = np.zeros((N_BATCH, 4))
    qpos[:, :3] = q_home
    # cube centre 0.08 m and 0.085 m left of the hand centre: 1-2 cm penetration
    qpos[:2, 3] = np.arcsin((np.array([0.65 - 0.08, 0.65 - 0.085]) - 0.35) / 0.65)
    qvel = np.zeros((N_BATCH, 4))
    qvel[:2] = [[0.3, -0.2, 0.5, 1.0], [0.0, 0.0, 0.0, 0.5]]
    ctrl = np.zeros((N_BATCH, 3))
    ctrl[0] = [5.0, -3.0, 1.0]
    out = jax.tree.map(np.asarray, quantities(_stack([c] * N_BATCH), qpos, qvel, ctrl))
    m_h = mm.body_mass[ids.hand_body]
    for i in range(2):
        d = mujoco.MjData(mm)
        d.qpos[:], d.qvel[:], d.ctrl[:] = qpos[i], qvel[i], ctrl[i]
        mujoco.mj_forward(mm, d)
        assert d.ncon == 1
        f_c = S.hand_contact_force_c(mm, d, ids)
        f_mjx = out["f_contact"][i]
        assert np.linalg.norm(f_c) > 50.0  # a real, large contact force
        # In-plane components agree. MJX's sphere-box normal has a spurious out-of-plane component
        # (~3e-4 of |F|); no joint moves out of the plane, so it does no work and F_int uses (x, z).
        np.testing.assert_allclose(f_mjx[PLANE], f_c[PLANE], rtol=1e-6)
        assert abs(f_mjx[1]) < 1e-3 * np.linalg.norm(f_mjx)
        # sign: the force on the hand points from the cube towards the hand
        away = d.site_xpos[ids.hand_site] - d.site_xpos[ids.cube_site]
        assert np.dot(f_mjx, away) > 0.9 * np.linalg.norm(f_mjx) * np.linalg.norm(away)
        # wrist force sensor (force of the wrist on the hand, site frame): Newton on the hand body,
        # m_h (a_h - g) = F_contact + F_wrist, with a_h from qacc (MuJoCo C)
        cq = S.c_quantities(mm, d, ids)
        a_h = cq.J_hand @ d.qacc + cq.Jdot_hand @ d.qvel
        f_wrist = out["site_xmat"][i][ids.ft_site].reshape(3, 3) @ out["sensor"][i]
        f_from_sensor = m_h * (a_h - mm.opt.gravity) - f_wrist
        np.testing.assert_allclose(f_from_sensor[PLANE], f_mjx[PLANE], rtol=1e-6)


@pytest.mark.parametrize("kw", [CONDS[1], dict(rod_length=0.6, cube_mass=2.0)])
def test_contact_under_swept_conditions_matches_mujoco_c(scene, quantities, kw):
    """Hand pressed into a cube of another rod length / mass: MJX's contact force and qacc
    equal the recompiled C model's (the contact's softness follows the compiler's invweights)."""
    mm, ids, _ = scene
    c = S.default_conditions(**kw)
    mc = S.mj_model_with_conditions(c)
    d = mujoco.MjData(mc)
    for angle in (0.3, -0.3):  # the cube swung towards the arm (+x)
        d.qpos[ids.pend_qpos] = angle
        mujoco.mj_kinematics(mc, d)
        cube = d.xpos[ids.cube_body].copy()
        if cube[0] > 0.4:
            break
    assert cube[0] > 0.4
    q_arm = S.solve_posture(mc, ids, (cube[0] + 0.085, cube[2]))  # 1.5 cm penetration
    qpos = np.zeros((N_BATCH, 4))
    qpos[:, :3], qpos[:, 3] = q_arm, d.qpos[ids.pend_qpos]
    qvel = np.zeros((N_BATCH, 4))
    qvel[0] = [0.3, -0.2, 0.5, 1.0]
    ctrl = np.zeros((N_BATCH, 3))
    out = jax.tree.map(np.asarray, quantities(_stack([c] * N_BATCH), qpos, qvel, ctrl))
    for i in range(2):
        d = mujoco.MjData(mc)
        d.qpos[:], d.qvel[:], d.ctrl[:] = qpos[i], qvel[i], ctrl[i]
        mujoco.mj_forward(mc, d)
        assert d.ncon == 1
        f_c = S.hand_contact_force_c(mc, d, ids)
        assert np.linalg.norm(f_c) > 50.0
        np.testing.assert_allclose(out["f_contact"][i][PLANE], f_c[PLANE], rtol=1e-6)
        np.testing.assert_allclose(out["qacc"][i], d.qacc, rtol=1e-6, atol=1e-6)


def test_contact_only_hand_cube(scene):
    """Only the explicit hand-cube pair can collide."""
    mm, ids, _ = scene
    assert np.all(mm.geom_contype == 0) and np.all(mm.geom_conaffinity == 0)
    assert mm.npair == 1
    assert {mm.pair_geom1[0], mm.pair_geom2[0]} == {ids.hand_geom, ids.cube_geom}


def test_camera_intrinsics_and_pose(scene):
    """K from fovy (pinhole, x right, y down) and pose: geometric truths of the frustum."""
    mm, ids, _ = scene
    d = mujoco.MjData(mm)
    mujoco.mj_forward(mm, d)
    K = S.camera_intrinsics(mm, ids.camera)
    R, p = S.camera_pose_world(mm, d, ids.camera)
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.isclose(np.linalg.det(R), 1.0)
    # MuJoCo's own camera frame as the reference: it looks along its -z axis, y up
    np.testing.assert_allclose(p, d.cam_xpos[ids.camera], atol=1e-12)
    mj = d.cam_xmat[ids.camera].reshape(3, 3)
    # a point on MuJoCo's optical axis projects to the image centre
    uv, z = S.project(K, R, p, p - 2.0 * mj[:, 2])
    np.testing.assert_allclose(uv[0], [320.0, 240.0], atol=1e-9)
    np.testing.assert_allclose(z[0], 2.0, atol=1e-12)
    # a point at half the vertical field of view above the axis: the top edge of the image
    half = np.radians(mm.cam_fovy[ids.camera]) / 2
    up = p - np.cos(half) * mj[:, 2] + np.sin(half) * mj[:, 1]
    uv, _ = S.project(K, R, p, up)
    np.testing.assert_allclose(uv[0], [320.0, 0.0], atol=1e-9)
    # world +x appears to the right, world +z upwards (smaller v)
    uv, _ = S.project(
        K, R, p, np.stack([p + R[:, 2], p + R[:, 2] + [0.1, 0, 0], p + R[:, 2] + [0, 0, 0.1]])
    )
    assert uv[1, 0] > uv[0, 0] and uv[2, 1] < uv[0, 1]
    # hand and cube (at rest and at release) in view, in front of the camera
    c = S.default_conditions()
    dc = S.make_data_c(mm, ids, c, S.solve_posture(mm, ids, S.X_HOME))
    pts = np.stack(
        [dc.site_xpos[ids.hand_site], dc.site_xpos[ids.cube_site], d.site_xpos[ids.cube_site]]
    )
    uv, z = S.project(K, R, p, pts)
    assert np.all(z > 0.5)
    assert np.all((uv >= 0) & (uv <= [640, 480]))
    from hec_jax.geometry import intrinsics_from_fovy

    with pytest.raises(ValueError, match="fovy"):
        intrinsics_from_fovy(0.0, 640, 480)
    with pytest.raises(ValueError, match="image size"):
        intrinsics_from_fovy(45.0, 0, 480)


def test_conditions_validation():
    with pytest.raises(ValueError):
        S.mj_model_with_conditions(S.default_conditions(rod_length=-0.1))
    with pytest.raises(ValueError):
        S.validate_conditions(S.default_conditions(cube_mass=0.0))
    with pytest.raises(ValueError):
        S.default_conditions(rod_lenght=0.5)


# slow (2026-12-03): the CG solver with the sparse Jacobian is an option (``--solver cg`` of the
# sweep, for GPUs without a batched Cholesky); the default suite keeps the default (Newton) solve
# against MuJoCo C (test_dynamics_match_mujoco_c). 23 s of the CI's time.
@pytest.mark.slow
def test_cg_sparse_solver_matches_c_and_newton():
    """``set_solver_options(..., "cg", "sparse")`` (no batched Cholesky in an MJX step): MJX's
    constraint solve equals MuJoCo C's with the same settings, and both equal scene.xml's Newton
    solve, at states with the hand pressing into the cube (one active contact) and without."""
    mm_newton = S.load_mj_model()
    mm_cg = S.set_solver_options(S.load_mj_model(), 8, 8, "cg", "sparse")
    assert mm_cg.opt.solver == mujoco.mjtSolver.mjSOL_CG
    assert mm_cg.opt.jacobian == mujoco.mjtJacobian.mjJAC_SPARSE
    ids = S.scene_ids(mm_cg)
    mx = S.load_mjx_model(mm_cg)
    q_home = S.solve_posture(mm_cg, ids, S.X_HOME)
    qpos = np.zeros((N_BATCH, 4))
    qpos[:, :3] = q_home
    qpos[:, 3] = np.arcsin((np.array([0.57, 0.565, 0.56, 0.2]) - 0.35) / 0.65)  # 3 in contact
    qvel = np.array([[0.3, -0.2, 0.5, 1.0], [0.0, 0.0, 0.0, 0.5], [1.0, 0.5, -0.5, 2.0], [0.0] * 4])
    ctrl = np.array([[5.0, -3.0, 1.0], [0.0, 0.0, 0.0], [-8.0, 4.0, 2.0], [1.0, 1.0, 1.0]])

    def one(qpos, qvel, ctrl):
        d = mjx.make_data(mx).replace(qpos=qpos, qvel=qvel, ctrl=ctrl)
        with _mjx_ctx():
            d = mjx.forward(mx, d)
        # the sparse inertia path was taken: MJX keeps M as the nC entries of the tree (a private
        # field of MJX 3.17's JAX implementation; the dense path keeps it as (nv, nv))
        assert inertia_storage(d).shape == (mx.nC,)
        return d.qacc, S.hand_contact_force(mx, d, ids), S.full_mass_matrix(mx, d)

    qacc_mjx, f_mjx, m_mjx = jax.tree.map(np.asarray, jax.jit(jax.vmap(one))(qpos, qvel, ctrl))
    for i in range(N_BATCH):
        qacc = {}
        for name, mm in (("cg", mm_cg), ("newton", mm_newton)):
            d = mujoco.MjData(mm)
            d.qpos[:], d.qvel[:], d.ctrl[:] = qpos[i], qvel[i], ctrl[i]
            mujoco.mj_forward(mm, d)
            assert d.ncon == (1 if i < 3 else 0)
            qacc[name] = d.qacc.copy()
            if name == "cg":  # the controller's inputs read from sparse-inertia data
                m_full = np.zeros((mm.nv, mm.nv))
                mujoco.mj_fullM(mm, d, m_full)
                np.testing.assert_allclose(m_mjx[i], m_full, rtol=1e-10, atol=1e-12)
                # in-plane components (MJX's sphere-box normal: see the test above)
                f_c = S.hand_contact_force_c(mm, d, ids)
                np.testing.assert_allclose(f_mjx[i][PLANE], f_c[PLANE], rtol=1e-6, atol=1e-9)
                assert abs(f_mjx[i][1]) <= 1e-3 * np.linalg.norm(f_mjx[i])
        # iterative solves that stop at opt.tolerance (1e-8): agreement to 10x that, scaled by
        # the largest acceleration (a rule of thumb: MuJoCo's own stopping test scales the
        # improvement by trace(M) and the number of dofs, not by |qacc|)
        tol = 10 * mm_cg.opt.tolerance * np.abs(qacc["newton"]).max()
        np.testing.assert_allclose(qacc_mjx[i], qacc["cg"], rtol=0, atol=tol)
        np.testing.assert_allclose(qacc["cg"], qacc["newton"], rtol=0, atol=tol)
    assert np.all(np.linalg.norm(f_mjx[:3], axis=-1) > 1.0) and np.all(f_mjx[3] == 0)
    with pytest.raises(ValueError, match="solver"):
        S.set_solver_options(S.load_mj_model(), solver="pgs")
    with pytest.raises(ValueError, match="jacobian"):
        S.set_solver_options(S.load_mj_model(), jacobian="banded")
    with pytest.raises(ValueError, match="iterations"):
        S.set_solver_options(S.load_mj_model(), iterations=0)
    with pytest.raises(ValueError, match="iterations"):
        S.set_solver_options(S.load_mj_model(), iterations=True)
    with pytest.raises(ValueError, match="ls_iterations"):
        S.set_solver_options(S.load_mj_model(), ls_iterations=np.True_)
    with pytest.warns(UserWarning, match="CG with opt.iterations 4"):
        S.set_solver_options(S.load_mj_model(), 4, 8, "cg")


@pytest.mark.slow  # 70 s on the 2-core CI; the forward oracle above is slow too (2026-12-03)
def test_implicit_solve_derivatives_do_not_depend_on_cg_sparse():
    """``differentiable.solve`` under CG with the sparse inertia: the same qacc and the same
    forward- and reverse-mode derivatives (float64) as under scene.xml's Newton/dense, at a
    contact state (its derivative is one Newton step at the solution, whatever found it)."""
    from hec_jax.mjx_scene import differentiable as D

    results = {}
    for name, settings in (("newton", (100, 50)), ("cg", (100, 50, "cg", "sparse"))):
        mm = S.set_solver_options(S.load_mj_model(), *settings)
        ids = S.scene_ids(mm)
        mx = S.load_mjx_model(mm)
        qpos = np.zeros(4)
        qpos[:3] = S.solve_posture(mm, ids, S.X_HOME)
        qpos[3] = np.arcsin((0.57 - 0.35) / 0.65)  # the hand presses into the cube
        d_c = mujoco.MjData(mm)
        d_c.qpos[:] = qpos
        mujoco.mj_forward(mm, d_c)
        assert d_c.ncon == 1  # a contact state (MuJoCo C)

        def qacc(qvel, mx=mx, qpos=qpos):
            d = mjx.make_data(mx).replace(
                qpos=jnp.asarray(qpos), qvel=qvel, ctrl=jnp.array([5.0, -3.0, 1.0])
            )
            with _mjx_ctx():
                for stage in (
                    mjx.fwd_position,
                    mjx.fwd_velocity,
                    mjx.fwd_actuation,
                    mjx.fwd_acceleration,
                ):
                    d = stage(mx, d)
                return D.solve(mx, d).qacc

        qvel = jnp.array([0.3, -0.2, 0.5, 1.0])
        results[name] = [
            np.asarray(jax.jit(f)(qvel)) for f in (qacc, jax.jacfwd(qacc), jax.jacrev(qacc))
        ]
    for what, newton, cg in zip(("qacc", "jacfwd", "jacrev"), *results.values(), strict=True):
        assert np.abs(newton).max() > 1.0, what  # contact: large, non-trivial values
        np.testing.assert_allclose(
            cg, newton, rtol=0, atol=1e-9 * np.abs(newton).max(), err_msg=what
        )


def test_merged_welded_links_have_the_dynamics_of_one_body_per_link():
    """scene.xml puts each welded link's geom in the body it is welded to (9 bodies, depth 5); the
    same arm with one body per link (tests/data, 12 bodies) has the same inertia matrix, bias
    forces, accelerations, site positions and force/torque sensor readings (MuJoCo C, float64)."""
    from pathlib import Path

    merged = S.load_mj_model()
    per_link = S.load_mj_model(Path(__file__).parent / "data" / "scene_body_per_link.xml")
    assert (merged.nbody, per_link.nbody) == (9, 12)
    assert merged.nv == per_link.nv and merged.nsensordata == per_link.nsensordata
    rng = np.random.default_rng(0)
    for _ in range(20):
        qpos, qvel = rng.uniform(-1.5, 1.5, merged.nq), rng.normal(0.0, 2.0, merged.nv)
        ctrl = rng.normal(0.0, 10.0, merged.nu)
        got = []
        for m in (merged, per_link):
            d = mujoco.MjData(m)
            d.qpos[:], d.qvel[:], d.ctrl[:] = qpos, qvel, ctrl
            mujoco.mj_forward(m, d)
            full_m = np.zeros((m.nv, m.nv))
            mujoco.mj_fullM(m, d, full_m)
            sites = [d.site(n).xpos.copy() for n in ("hand", "ft_sensor", "cube")]
            got.append([full_m, d.qfrc_bias.copy(), d.qacc.copy(), *sites, d.sensordata.copy()])
        for a, b in zip(*got, strict=True):
            np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * max(1.0, np.abs(b).max()))


@pytest.mark.parametrize("phase", [0.0, 0.05, 0.3, 0.1234])
def test_the_hold_counts_the_same_steps_in_float32_and_float64(phase):
    """The pendulum is held at the steps k with k dt < arrival_phase: ceil(phase / dt) of them,
    whether the step times are accumulated in float32 or float64, in NumPy or JAX (before,
    float32's accumulated time held one step more for phases on the 1 ms grid)."""
    from hec_jax.mjx_scene.sim import held_at

    dt = 1e-3
    expected = int(np.ceil(round(phase / dt, 6)))
    for dtype in (np.float32, np.float64):
        t, held = dtype(0.0), []
        for _ in range(400):
            held.append(bool(held_at(t, dtype(phase), dt)))
            t = dtype(t + dtype(dt))
        assert held == [k < expected for k in range(400)], (dtype, phase)
    times = jnp.asarray(np.arange(400) * dt, jnp.float32)
    assert int(jnp.sum(held_at(times, jnp.float32(phase), dt))) == expected


def test_render_rollout_times_are_its_frames_states_times():
    """``render.render_rollout``'s ``times`` against an independent replay of the same simulation
    from a state whose clock does not start at 0: each frame's true centre is the replay's
    state at the frame's time, to round-off (before session 90 ``times`` was i / fps, a step
    early)."""
    from hec_jax.mjx_scene.render import body_in_camera, render_rollout

    m = S.load_mj_model()
    d = mujoco.MjData(m)
    hinge = m.jnt_qposadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, "hinge")]
    d.qpos[hinge], d.time = 0.5, 0.25
    start_qpos = d.qpos.copy()
    seq = render_rollout(m, d, 4, 30.0, "eye", "cube", 64, 48)  # (the time step shrunk in m)
    replay = mujoco.MjData(m)
    replay.qpos[:], replay.time = start_qpos, 0.25
    mujoco.mj_forward(m, replay)
    at_time = {}
    while replay.time < seq.times[-1] + 0.5 * m.opt.timestep:
        at_time[round(replay.time / m.opt.timestep)] = body_in_camera(m, replay, "cube", "eye")[0]
        mujoco.mj_step(m, replay)
        mujoco.mj_forward(m, replay)
    assert seq.times[0] > 0.25 and np.allclose(np.diff(seq.times), 1 / 30.0)
    for t, centre in zip(seq.times, seq.position, strict=True):
        np.testing.assert_allclose(centre, at_time[round(t / m.opt.timestep)], atol=1e-12)
