"""Loading the set-up of Sec. 6.1 and putting the pendulum conditions into the model pytree.

The MJCF is ``scene.xml`` next to this file. Names and indices that code needs are collected once in
the frozen :class:`SceneIds` (static, hashable). The pendulum conditions are a pytree
(:class:`PendulumConditions`) so that a sweep is ``jax.vmap`` over them; rod length and cube mass
reach the physics through :func:`apply_conditions`, which rewrites the MJX model fields that the
compiler would have produced for those values.
"""

from __future__ import annotations

import dataclasses
import functools
import warnings
from pathlib import Path
from typing import NamedTuple

import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

SCENE_XML = Path(__file__).resolve().parent / "scene.xml"

# Fixed physical constants of the pendulum (not swept).
ROD_RADIUS = 0.003  # [m] steel rod radius (matches scene.xml)
ROD_DENSITY = 7850.0  # [kg/m^3] steel
CUBE_EDGE = 0.1  # [m] wooden cube edge (box half-size 0.05 in scene.xml)
HAND_RADIUS = 0.04  # [m] hand sphere radius (scene.xml)

ARM_JOINTS = ("shoulder", "elbow", "wrist")
# Task space: the vertical plane x-z of the world (Eq. 39 with l = 2). TASK_AXES picks (x, z).
TASK_AXES = (0, 2)


@dataclasses.dataclass(frozen=True)
class SceneIds:
    """Static indices into the model (hashable, safe as a jit static argument).

    Attributes:
        arm_qpos: qpos addresses of the 3 active pitch joints (shoulder, elbow, wrist).
        arm_dof: dof addresses of the same joints.
        pend_qpos: qpos address of the pendulum hinge.
        pend_dof: dof address of the pendulum hinge.
        hand_body: body id of the hand (sphere centre = body origin = COM = site ``hand``).
        hand_site: site id of the end-effector point X_e.
        hand_geom: geom id of the hand sphere.
        cube_body, cube_site, cube_geom: ids of the cube (object point X_o = cube centre).
        rod_body, rod_geom: ids of the rod.
        ft_site: site of the force/torque sensor between wrist flange and hand.
        camera: camera id of the fixed camera ``eye``.
        force_sensor_adr: sensordata address of the 3-axis force sensor.
        timestep: [s] the model's time step (``opt.timestep``), the control period.
        torque_limit: [N m] (3,) symmetric limits of the arm's motors (their ``ctrlrange``).
    """

    arm_qpos: tuple[int, ...]
    arm_dof: tuple[int, ...]
    pend_qpos: int
    pend_dof: int
    hand_body: int
    hand_site: int
    hand_geom: int
    cube_body: int
    cube_site: int
    cube_geom: int
    rod_body: int
    rod_geom: int
    ft_site: int
    camera: int
    force_sensor_adr: int
    timestep: float
    torque_limit: tuple[float, float, float]


def scene_ids(m: mujoco.MjModel) -> SceneIds:
    """Collects the ids used by the simulation and control code from a compiled MjModel."""

    def jid(name: str) -> int:
        return mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, name)

    def oid(obj: mujoco.mjtObj, name: str) -> int:
        i = mujoco.mj_name2id(m, obj, name)
        if i < 0:
            raise ValueError(f"scene has no {obj.name} named {name!r}")
        return i

    arm = [jid(n) for n in ARM_JOINTS]
    hinge = jid("hinge")
    return SceneIds(
        arm_qpos=tuple(int(m.jnt_qposadr[j]) for j in arm),
        arm_dof=tuple(int(m.jnt_dofadr[j]) for j in arm),
        pend_qpos=int(m.jnt_qposadr[hinge]),
        pend_dof=int(m.jnt_dofadr[hinge]),
        hand_body=oid(mujoco.mjtObj.mjOBJ_BODY, "hand"),
        hand_site=oid(mujoco.mjtObj.mjOBJ_SITE, "hand"),
        hand_geom=oid(mujoco.mjtObj.mjOBJ_GEOM, "hand"),
        cube_body=oid(mujoco.mjtObj.mjOBJ_BODY, "cube"),
        cube_site=oid(mujoco.mjtObj.mjOBJ_SITE, "cube"),
        cube_geom=oid(mujoco.mjtObj.mjOBJ_GEOM, "cube"),
        rod_body=oid(mujoco.mjtObj.mjOBJ_BODY, "rod"),
        rod_geom=oid(mujoco.mjtObj.mjOBJ_GEOM, "rod"),
        ft_site=oid(mujoco.mjtObj.mjOBJ_SITE, "ft_sensor"),
        camera=oid(mujoco.mjtObj.mjOBJ_CAMERA, "eye"),
        force_sensor_adr=int(m.sensor_adr[oid(mujoco.mjtObj.mjOBJ_SENSOR, "hand_force")]),
        timestep=float(m.opt.timestep),
        torque_limit=tuple(
            float(m.actuator_ctrlrange[oid(mujoco.mjtObj.mjOBJ_ACTUATOR, n), 1]) for n in ARM_JOINTS
        ),
    )


class PendulumConditions(NamedTuple):
    """Conditions of one pendulum swing; every field is a pytree leaf (vmap a sweep over them).

    Attributes:
        rod_length: [m] length of the steel rod from the hinge to the top face of the cube.
        cube_mass: [kg] mass of the wooden cube (edge 0.1 m, uniform density).
        release_angle: [rad] hinge angle at release (0 = hanging, > 0 swings the cube toward +x).
        release_speed: [rad/s] hinge angular velocity at release.
        hinge_damping: [N m s/rad] viscous damping of the ceiling hinge.
        arrival_phase: [s] delay of the release after t = 0: the pendulum is held in its release
            state for this long, which shifts when the cube arrives at the hand.
        hinge_x: [m] world x of the ceiling hinge (the rod's parent body); scene.xml: 0.35.
    """

    rod_length: jnp.ndarray
    cube_mass: jnp.ndarray
    release_angle: jnp.ndarray
    release_speed: jnp.ndarray
    hinge_damping: jnp.ndarray
    arrival_phase: jnp.ndarray
    hinge_x: jnp.ndarray


@functools.cache
def scene_hinge_x(path: str | Path = SCENE_XML) -> float:
    """[m] world x of the pendulum's ceiling hinge in the MJCF (read from the model)."""
    m = load_mj_model(path)
    rod = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "rod")
    return float(m.body_pos[int(m.body_parentid[rod])][0])


@dataclasses.dataclass(frozen=True)
class PendulumConfig:
    """One pendulum condition as static settings (a preset's or a command line's); the defaults
    are the set-up's nominal values (docs/paper_readings.md, parameter values). ``conditions()``
    turns it into the :class:`PendulumConditions` pytree that the simulation takes.

    Attributes: as :class:`PendulumConditions`; ``hinge_x`` None is scene.xml's hinge.
    """

    rod_length: float = 0.6  # [m] hinge to the cube's top face
    cube_mass: float = 0.7  # [kg]
    release_angle: float = -0.5  # [rad] hinge angle at release (0: hanging)
    release_speed: float = 0.0  # [rad/s] hinge angular velocity at release
    hinge_damping: float = 0.002  # [N m s/rad]
    arrival_phase: float = 0.0  # [s] the pendulum is held at its release state this long
    hinge_x: float | None = None  # [m] world x of the ceiling hinge; None: scene.xml's

    def __post_init__(self):
        values = {k: np.asarray(np.nan if v is None else v, float) for k, v in self._items()}
        if self.hinge_x is None:
            values["hinge_x"] = np.asarray(0.0)
        validate_conditions(PendulumConditions(**values))

    def _items(self):
        return dataclasses.asdict(self).items()

    def conditions(self, dtype=float) -> PendulumConditions:
        """The pytree of these conditions (scalar leaves of ``dtype``)."""
        values = dataclasses.asdict(self)
        if values["hinge_x"] is None:
            values["hinge_x"] = scene_hinge_x()
        return PendulumConditions(**{k: jnp.asarray(v, dtype=dtype) for k, v in values.items()})


def default_conditions(**overrides: float) -> PendulumConditions:
    """The nominal conditions (:class:`PendulumConfig`'s defaults) with ``overrides`` applied.

    Raises:
        ValueError: an unknown field name, or a meaningless value (``validate_conditions``).
    """
    unknown = set(overrides) - set(PendulumConditions._fields)
    if unknown:
        raise ValueError(f"unknown pendulum condition(s): {sorted(unknown)}")
    return PendulumConfig(**overrides).conditions()


def validate_conditions(c: PendulumConditions) -> None:
    """Raises ValueError for physically meaningless conditions (host-side check, not traced)."""
    for name in ("rod_length", "cube_mass"):
        v = np.asarray(getattr(c, name))
        if np.any(~np.isfinite(v)) or np.any(v <= 0):
            raise ValueError(f"{name} must be finite and > 0, got {v}")
    for name in ("hinge_damping", "arrival_phase"):
        v = np.asarray(getattr(c, name))
        if np.any(~np.isfinite(v)) or np.any(v < 0):
            raise ValueError(f"{name} must be finite and >= 0, got {v}")
    for name in ("release_angle", "release_speed", "hinge_x"):
        v = np.asarray(getattr(c, name))
        if np.any(~np.isfinite(v)):
            raise ValueError(f"{name} must be finite, got {v}")


def load_mj_model(path: str | Path = SCENE_XML) -> mujoco.MjModel:
    """Compiles the MJCF of the set-up with MuJoCo C."""
    return mujoco.MjModel.from_xml_path(str(path))


SOLVERS = {"newton": mujoco.mjtSolver.mjSOL_NEWTON, "cg": mujoco.mjtSolver.mjSOL_CG}
JACOBIANS = {
    "dense": mujoco.mjtJacobian.mjJAC_DENSE,
    "sparse": mujoco.mjtJacobian.mjJAC_SPARSE,
    "auto": mujoco.mjtJacobian.mjJAC_AUTO,
}


CG_MIN_ITERATIONS = 8  # CG below this cap changed learned runs of this scene (see below)


def set_solver_options(
    m: mujoco.MjModel,
    iterations: int | None = None,
    ls_iterations: int | None = None,
    solver: str | None = None,
    jacobian: str | None = None,
) -> mujoco.MjModel:
    """Sets MuJoCo's constraint-solver options on ``m`` in place (and returns it); None keeps
    scene.xml's value (100 / 50 iterations, Newton, ``auto``).

    Args:
        m: the MuJoCo model (changed in place).
        iterations: cap of ``opt.iterations`` (>= 1).
        ls_iterations: cap of ``opt.ls_iterations`` (>= 1).
        solver: ``opt.solver``, "newton" or "cg". Both minimise the same convex problem; CG
            preconditions with M^-1 instead of factoring the Newton Hessian.
        jacobian: ``opt.jacobian``, "dense", "sparse" or "auto" (dense for this scene's nv = 4).
            In MJX it picks the layout of the joint-space inertia: "sparse" factors M as L D L^T
            along the kinematic tree (elementwise arithmetic for this scene) instead of a batched
            dense Cholesky. With "cg" + "sparse" an MJX step of this scene has no Cholesky or
            triangular solve left, the cheapest form on a GPU (``benchmarks/sweep.py``).

    CG needs more iterations than Newton to reach the same solution: on this scene's learning
    runs (float64, docs/benchmarks_gpu.md) CG capped at 4 iterations moved learned peak forces by
    up to 22 N from Newton's, while 8 or more agreed to 6e-7 N; a CG cap below 8 warns.

    The same model then serves MuJoCo C and MJX (``load_mjx_model(m)``), so both sides of a
    comparison run the same settings.
    """
    for name, v in (("iterations", iterations), ("ls_iterations", ls_iterations)):
        if v is not None and (isinstance(v, (bool, np.bool_)) or int(v) != v or v < 1):
            raise ValueError(f"{name} must be an integer >= 1, got {v}")
    if solver is not None and solver not in SOLVERS:
        raise ValueError(f"solver must be one of {sorted(SOLVERS)}, got {solver!r}")
    if jacobian is not None and jacobian not in JACOBIANS:
        raise ValueError(f"jacobian must be one of {sorted(JACOBIANS)}, got {jacobian!r}")
    if iterations is not None:
        m.opt.iterations = int(iterations)
    if ls_iterations is not None:
        m.opt.ls_iterations = int(ls_iterations)
    if solver is not None:
        m.opt.solver = SOLVERS[solver]
    if jacobian is not None:
        m.opt.jacobian = JACOBIANS[jacobian]
    if m.opt.solver == mujoco.mjtSolver.mjSOL_CG and m.opt.iterations < CG_MIN_ITERATIONS:
        warnings.warn(
            f"opt.solver CG with opt.iterations {m.opt.iterations} < {CG_MIN_ITERATIONS}: on this "
            "scene CG stops short of Newton's solution in some contact states and learned runs "
            "diverge from Newton's (docs/benchmarks_gpu.md)",
            stacklevel=2,
        )
    return m


def load_mjx_model(m: mujoco.MjModel | None = None) -> mjx.Model:
    """Puts the model on the default device with the pure-JAX MJX implementation."""
    if m is None:
        m = load_mj_model()
    return mjx.put_model(m, impl="jax")


def mj_model_with_conditions(c: PendulumConditions, path: str | Path = SCENE_XML) -> mujoco.MjModel:
    """MuJoCo C model with rod length, cube mass and hinge damping set in the MJCF spec,
    recompiled.

    The compiler computes masses and inertias from the geoms itself, so this is an independent
    reference for :func:`apply_conditions`. Only scalar (unbatched) conditions are accepted.
    """
    validate_conditions(c)
    L = float(c.rod_length)
    spec = mujoco.MjSpec.from_file(str(path))
    rod = spec.geom("rod")
    rod.size = np.array([ROD_RADIUS, L / 2, 0.0])
    rod.pos = np.array([0.0, 0.0, -L / 2])
    spec.body("cube").pos = np.array([0.0, 0.0, -(L + CUBE_EDGE / 2)])
    spec.geom("cube").mass = float(c.cube_mass)
    spec.joint("hinge").damping = np.array([float(c.hinge_damping), 0.0, 0.0])
    ceiling = spec.body("rod").parent
    ceiling.pos = np.array([float(c.hinge_x), ceiling.pos[1], ceiling.pos[2]])
    return spec.compile()


def apply_conditions(m: mjx.Model, ids: SceneIds, c: PendulumConditions) -> mjx.Model:
    """Writes rod length, cube mass and hinge damping into the MJX model (pure, vmappable).

    Rod (cylinder of radius ROD_RADIUS, steel, from the hinge down to the cube, axis along body z):
        mass m_r = rho pi a^2 L, COM at (0, 0, -L/2),
        principal inertia (m_r (3a^2 + L^2)/12, same, m_r a^2 / 2).
    Cube (edge e, uniform): body origin at (0, 0, -(L + e/2)), mass m_c,
        inertia m_c e^2 / 6 per axis.
    Hinge: dof_damping of the pendulum dof; its position: x of the ceiling body. Release angle/speed and arrival phase enter through the
    state (see ``make_data``) and the hold in ``rollout``, not the model.
    Constraint softness: the rod's and cube's ``body_invweight0`` and the hinge's
    ``dof_invweight0`` as the compiler computes them at qpos0 (the hand-cube contact's
    impedance depends on them; before 2026-12-04 they kept the nominal cube's values).
    """
    L = c.rod_length
    a = ROD_RADIUS
    m_rod = ROD_DENSITY * jnp.pi * a**2 * L
    rod_inertia = jnp.stack(
        [m_rod * (3 * a**2 + L**2) / 12, m_rod * (3 * a**2 + L**2) / 12, m_rod * a**2 / 2]
    )
    zero = jnp.zeros_like(L)
    rod_com = jnp.stack([zero, zero, -L / 2])
    m_cube = c.cube_mass
    cube_inertia = jnp.full((3,), 1.0) * (m_cube * CUBE_EDGE**2 / 6)
    cube_pos = jnp.stack([zero, zero, -(L + CUBE_EDGE / 2)])

    body_mass = m.body_mass.at[ids.rod_body].set(m_rod).at[ids.cube_body].set(m_cube)
    # subtree masses: the rod's subtree is rod + cube; ancestors are fixed bodies (ceiling, world).
    old_sub = m.body_subtreemass[ids.rod_body]
    new_sub = m_rod + m_cube
    body_subtreemass = (
        m.body_subtreemass.at[ids.rod_body]
        .set(new_sub)
        .at[ids.cube_body]
        .set(m_cube)
        .at[0]
        .add(new_sub - old_sub)
    )
    ceiling = int(np.asarray(m.body_parentid)[ids.rod_body])
    if ceiling != 0:
        body_subtreemass = body_subtreemass.at[ceiling].add(new_sub - old_sub)
    body_pos = m.body_pos.at[ids.cube_body].set(cube_pos)
    if ceiling != 0:
        body_pos = body_pos.at[ceiling, 0].set(c.hinge_x)
    geom_size = m.geom_size.at[ids.rod_geom, 1].set(L / 2)
    geom_pos = m.geom_pos.at[ids.rod_geom].set(rod_com)
    # The compiler's mean inverse inertias at qpos0 (mj_setConst), which set the constraints'
    # softness (MJX's contact rows take body_invweight0; limit rows dof_invweight0). The hinge
    # (axis y) carries the rod and the cube alone, so M is block diagonal and its pendulum entry
    # is the inertia about the hinge: I_h = I_rod + m_r (L/2)^2 + I_cube + m_c (L + e/2)^2 +
    # armature. A body of COM distance r from the axis: J M^-1 J^T has translational trace
    # r^2 / I_h and rotational trace 1 / I_h; MuJoCo keeps their means over three axes.
    r_cube = L + CUBE_EDGE / 2
    i_hinge = (
        rod_inertia[1]
        + m_rod * (L / 2) ** 2
        + cube_inertia[1]
        + m_cube * r_cube**2
        + m.dof_armature[ids.pend_dof]
    )
    body_invweight0 = (
        m.body_invweight0.at[ids.rod_body]
        .set(jnp.stack([(L / 2) ** 2, jnp.ones_like(L)]) / (3 * i_hinge))
        .at[ids.cube_body]
        .set(jnp.stack([r_cube**2, jnp.ones_like(L)]) / (3 * i_hinge))
    )
    dof_invweight0 = m.dof_invweight0.at[ids.pend_dof].set(1.0 / i_hinge)
    return m.replace(
        body_invweight0=body_invweight0,
        dof_invweight0=dof_invweight0,
        body_mass=body_mass,
        body_subtreemass=body_subtreemass,
        body_inertia=m.body_inertia.at[ids.rod_body]
        .set(rod_inertia)
        .at[ids.cube_body]
        .set(cube_inertia),
        body_ipos=m.body_ipos.at[ids.rod_body].set(rod_com),
        body_pos=body_pos,
        geom_size=geom_size,
        geom_pos=geom_pos,
        dof_damping=m.dof_damping.at[ids.pend_dof].set(c.hinge_damping),
    )


# Nominal set-up: the hand waits at X_HOME (task coordinates x, z [m]), hand link horizontal,
# pointing at the pendulum (0.3 m from the resting cube centre, outside the 0.25 m virtual sphere).
X_HOME = (0.65, 0.60)
Q_HOME_GUESS = (-0.6, 1.9, -1.3)  # [rad] elbow-up branch


def solve_posture(
    m: mujoco.MjModel,
    ids: SceneIds,
    x_task,
    hand_pitch: float = 0.0,
    q_guess=Q_HOME_GUESS,
    tol: float = 1e-12,
) -> np.ndarray:
    """Arm joint angles [rad] (3,) putting the hand centre at ``x_task`` = (x, z) [m] with the hand
    link at pitch ``hand_pitch`` = q1 + q2 + q3 [rad] (Newton iterations on MuJoCo C kinematics).
    """
    d = mujoco.MjData(m)
    q = np.asarray(q_guess, dtype=float).copy()
    target = np.array([x_task[0], x_task[1], hand_pitch])
    jac = np.zeros((3, m.nv))
    for _ in range(100):
        d.qpos[list(ids.arm_qpos)] = q
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)
        x = d.site_xpos[ids.hand_site]
        err = target - np.array([x[TASK_AXES[0]], x[TASK_AXES[1]], q.sum()])
        if np.max(np.abs(err)) < tol:
            return q
        mujoco.mj_jacSite(m, d, jac, None, ids.hand_site)
        A = np.vstack([jac[list(TASK_AXES)][:, list(ids.arm_dof)], np.ones((1, 3))])
        q = q + np.linalg.solve(A, err)
    raise ValueError(f"posture for {x_task} did not converge (residual {err})")
