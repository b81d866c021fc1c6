"""The closed loop of Secs. 5-6: MJX world + impedance hand + online learning of the virtual impedance.

Wires ``hec_jax.mjx_scene`` (world), ``hec_jax.control`` (hand) and ``hec_jax.nets`` (learning)
together through plain arrays and pure functions. One swing is one ``lax.scan`` over 1 ms steps
(``hec_jax.mjx_scene.rollout``); successive swings are a ``lax.scan`` over swings that restarts the
world at the same release and carries the learner's state (weights) over; conditions and seeds are
``vmap``-ed. The three conditions of the experiments share one compiled function: they differ only
in two pytree leaves, ``use_virtual`` (0: plain impedance, F_o = 0) and ``learn`` (0: frozen nets).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from hec_jax.control import (
    ControllerConfig,
    ImpedanceParams,
    Target,
    VirtualParams,
    make_impedance_controller,
    observe,
    sphere_kinematics,
)
from hec_jax.mjx_scene import (
    PendulumConditions,
    SimStep,
    apply_conditions,
    load_mj_model,
    load_mjx_model,
    make_data,
    rollout,
    scene_ids,
    set_solver_options,
    solve_posture,
)
from hec_jax.mjx_scene.model import CUBE_EDGE, HAND_RADIUS
from hec_jax.nets import LearnerConfig, LearnerInputs, SphereGeometry, make_online_learner

CONDITIONS = ("plain", "frozen", "learned")
# [m] hand centre to object centre while they touch: the hand sphere's radius plus half the cube's
# edge (a face on the hand; a corner would be 0.037 m further out)
TOUCH_DISTANCE = HAND_RADIUS + CUBE_EDGE / 2

# Why the task scripts leave the VIN (M_o) untrained by default (``--eta-m 0``; it keeps its
# initial output, about -0.05 kg): M_o multiplies dX_o'' (Eq. 47), which the controller forms as a
# 1 ms backward difference of the measured velocities. In contact that signal is the contact
# impulse itself (hundreds of m/s^2 over a few ms), so the VIN's gradient (Eq. 53) and its force
# M_o dX_o'' are driven by the impacts rather than by the relative motion the network is meant to
# shape (the paper's accelerations come from a 30 Hz camera, far smoother). Measured with
# ``--eta-m 0.3``: catching chatters on the hand for one seed of two (48 contact episodes);
# hitting is unaffected (9 periodic hits).
VIN_NOTE = "eta_m = 0: dX_o'' is a 1 kHz backward difference, impact-dominated in contact"


@dataclass(frozen=True)
class TaskConfig:
    """Static configuration of one experiment (catching or hitting)."""

    learner: LearnerConfig
    x_home: tuple[float, float] = (0.65, 0.60)  # X_d: hand equilibrium (x, z) [m]
    swing_steps: int = 1500  # samples per swing [1 ms]
    swings: int = 10
    final_steps: int = 0  # a continuous run after the swings (weights carried over), 0: none
    hinge_x: float | None = None  # pendulum hinge x [m] in the world (None: scene.xml's 0.35)
    contact_threshold: float = 1e-3  # |F_int| above this counts as contact [N]
    controller: ControllerConfig = field(default_factory=ControllerConfig)
    # Hand-cube contact (the scene's ``hand_cube`` pair) per task, written into the MJX model's
    # ``pair_solref`` (timeconst [s], dampratio) / ``pair_solimp``; None keeps scene.xml's values
    # (0.005 s, 1: critically damped, restitution ~0). scene.xml itself is never changed.
    contact_solref: tuple[float, float] | None = None
    contact_solimp: tuple[float, float, float, float, float] | None = None
    # Constraint solver caps (MuJoCo's ``opt.iterations`` / ``opt.ls_iterations``); None keeps
    # scene.xml's (100 / 50: MuJoCo's defaults, a loop that stops at ``opt.tolerance``). A vmapped
    # batch iterates until its slowest member converges; sweeps cap it (see experiments/sweep.py).
    solver_iterations: int | None = None
    ls_iterations: int | None = None
    # Solver algorithm and inertia layout (``opt.solver`` "newton" / "cg", ``opt.jacobian``
    # "dense" / "sparse"); None keeps scene.xml's (Newton, dense). "cg" + "sparse" has no batched
    # Cholesky factorisation, the fastest on a GPU, and reaches Newton's solution with at least 8
    # iterations (with 4, learned runs diverged from Newton's; ``set_solver_options`` warns).
    solver: str | None = None
    jacobian: str | None = None


def with_contact(mx, config: TaskConfig):
    """The MJX model with the task's hand-cube contact parameters (all pairs of the scene: there is
    one, ``hand_cube``); unchanged where the config leaves them at None."""
    if config.contact_solref is not None:
        ref = jnp.broadcast_to(jnp.asarray(config.contact_solref), mx.pair_solref.shape)
        mx = mx.replace(pair_solref=ref.astype(mx.pair_solref.dtype))
    if config.contact_solimp is not None:
        imp = jnp.broadcast_to(jnp.asarray(config.contact_solimp), mx.pair_solimp.shape)
        mx = mx.replace(pair_solimp=imp.astype(mx.pair_solimp.dtype))
    return mx


def hold_point(f_cd: float, hinge_x: float | None, k_e: float = 400.0) -> np.ndarray:
    """X_d (x, z) [m] where a caught cube at rest presses on the hand with ``f_cd`` [N].

    Default pendulum (0.6 m steel rod of radius 3 mm, 0.7 kg cube of edge 0.1 m) on the ceiling
    hinge at (``hinge_x``, scene height). Static balance about the hinge with the contact force
    along the cube's face normal (lever L_c): f_cd L_c = (m_c L_c + m_rod L / 2) g sin(theta); the
    pendulum is held at -theta (on the side the cube comes from), the hand centre is half a cube
    plus the hand radius out along the face normal, and X_d is f_cd / K_e behind it (Eq. 40 at rest:
    K_e (X_e - X_d) = F_int).
    """
    from hec_jax.mjx_scene import default_conditions
    from hec_jax.mjx_scene.model import ROD_DENSITY, ROD_RADIUS

    c = default_conditions()
    m = load_mj_model()
    ceiling = m.body_pos[int(m.body_parentid[scene_ids(m).rod_body])]
    hinge = np.array([ceiling[0] if hinge_x is None else hinge_x, ceiling[2]])
    rod, m_c = float(c.rod_length), float(c.cube_mass)
    l_c = rod + CUBE_EDGE / 2
    m_rod = ROD_DENSITY * np.pi * ROD_RADIUS**2 * rod
    theta = -np.arcsin(f_cd * l_c / ((m_c * l_c + m_rod * rod / 2) * 9.81))
    cube = hinge + l_c * np.array([np.sin(theta), -np.cos(theta)])
    normal = np.array([np.cos(theta), np.sin(theta)])  # cube face toward the hand
    return cube + (CUBE_EDGE / 2 + HAND_RADIUS - f_cd / k_e) * normal


def sphere_fn(x_r, xd_r, xdd_r, radius) -> SphereGeometry:
    """Eqs. 45-46 from the hand's ``sphere_kinematics`` in the form the learner wants."""
    sk = sphere_kinematics(x_r, xd_r, xdd_r, radius)
    return SphereGeometry(sk.dx_o, sk.dxd_o, sk.dxdd_o)


class EyeInput(NamedTuple):
    """The object's state as the eye reports it (task plane (x, z), world frame), for camera runs.

    Two estimates: ``old`` (index 0) is used until ``t_switch``, ``new`` (index 1) from then on (the
    camera's latency decides when a frame's estimate arrives). Between frames the state is
    predicted from the estimate with the filter's constant-acceleration model:
    X_o(t) = x + xd tau + xdd tau^2 / 2, tau = t - t_stamp.

    Attributes:
        use: () 1.0: take X_o, X_o', X_o'' from here; 0.0: from the simulator (ground truth).
        seen: () 1.0 once the eye has an estimate; before that F_o = 0 and no learning.
        t_stamp: [s] (2,) time of each estimate's state (mid-exposure of its frame).
        t_switch: [s] () from this time on the new estimate is used.
        x: [m] (2, 2), xd: [m/s] (2, 2), xdd: [m/s^2] (2, 2): (estimate, axis).
        touch_guard: [s] () an estimate whose frame was exposed less than this after the hand last
            felt the object is not used (see :class:`TouchMemory`); 0: no guard.
        touch_memory: [s] () how long after the last touch its extrapolation may stand in for
            the eye (an old or lost estimate); later the object counts as unseen.
    """

    use: jax.Array
    seen: jax.Array
    t_stamp: jax.Array
    t_switch: jax.Array
    x: jax.Array
    xd: jax.Array
    xdd: jax.Array
    touch_guard: jax.Array = 0.0
    touch_memory: jax.Array = 0.0


def truth_eye() -> EyeInput:
    """The object state comes from the simulator (``--eye truth``)."""
    z = jnp.zeros((2, 2))
    one, zero = jnp.asarray(1.0), jnp.asarray(0.0)
    return EyeInput(zero, one, jnp.zeros(2), jnp.asarray(jnp.inf), z, z, z, zero, zero)


class TouchMemory(NamedTuple):
    """What the hand's force sensor last said about the object (camera runs; part of the policy
    state, carried across steps and frames).

    While the sensor feels the object (|F_int| above the contact threshold) the object's centre is
    taken to be ``TOUCH_DISTANCE`` from the hand's centre against the measured force (F_int acts ON
    the hand, so the object lies along -F_int), moving with the hand along that normal (the eye
    gives the motion across it: :func:`touch_object_state`). After the contact ends, the
    object is extrapolated from that last touch at constant velocity until the eye delivers an
    estimate from a frame exposed at least ``EyeInput.touch_guard`` after it: a 30 fps eye with
    33 ms latency still reports the pre-impact motion (into the hand) for several frames after an
    impact, and its filter needs a few post-impact frames for the new velocity.

    Attributes:
        t: [s] () time of the last sample in contact (-inf: never).
        x: [m] (2,) object centre at that sample (world task plane).
        xd: [m/s] (2,) object velocity at that sample (the hand's).
    """

    t: jax.Array
    x: jax.Array
    xd: jax.Array


def no_touch(dtype=None) -> TouchMemory:
    """The memory before any contact."""
    z = jnp.zeros(2, dtype)
    return TouchMemory(jnp.asarray(-jnp.inf, dtype), z, z)


def touch_object_state(
    eye: EyeInput, touch: TouchMemory, t, x_e, xd_e, xdd_e, f_int, in_contact, distance: float
):
    """(X_o, X_o', X_o'', known, memory) of a camera run at time ``t``: touch in contact, the last
    touch extrapolated while the eye's estimate predates it (+ guard) or is lost, the eye
    otherwise; out of contact the estimate is kept out of the hand. Pure.

    ``known`` (bool): the object is in contact, or within ``eye.touch_memory`` of the last touch
    while the eye has nothing newer, or the eye sees it (``eye.seen``); otherwise it counts as
    unseen (the caller then drops the virtual force and learning).

    * In contact: the force on the (spherical, frictionless) hand is along the contact normal n,
      so touch fixes the centre along n only: at ``distance`` from the hand's centre; across n
      (where on its face the cube is held) the position is the eye's prediction (measured, main
      catching run: taking the centre on the hand's normal line instead gave 44-50 mm errors
      while a cube was held off-centre, and the hand pushed it out). Velocity and acceleration
      are the hand's (the eye's across n made the hold chatter, measured: 8-18 contacts a swing).
    * Out of contact the force sensor says the object does not touch the hand, so an estimate
      closer than ``distance`` contradicts it: the position is moved out to ``distance`` along the
      same direction (projected onto what the sensor allows). Near X_r = 0 the sphere geometry of
      Eqs. 45-47 is singular (its n' and n'' grow as 1 / |X_r|), so an estimate inside the hand
      would otherwise turn eye errors into arbitrarily large virtual forces. The velocity is
      kept: an estimate just ahead of a real impact is still approaching (removing the approach
      velocity there was tried: learned camera peaks 10-23% above ground truth on the short test
      run, against 4-9% below with the velocity kept).

    Args: ``x_e``, ``xd_e``, ``xdd_e`` [m, m/s, m/s^2] (2,) the hand; ``f_int`` [N] (2,) force on
    the hand; ``in_contact`` () bool; ``distance`` [m] hand centre to object centre in contact.
    """
    f_sq = jnp.sum(f_int**2)
    pos = f_sq > 0.0
    inv = jnp.where(pos, 1.0 / jnp.sqrt(jnp.where(pos, f_sq, 1.0)), 0.0)
    n = -f_int * inv  # unit contact normal, hand -> object (F_int acts ON the hand)
    x_eye, xd_eye, xdd_eye = eye_object_state(eye, t)
    # touch along n, the eye's position across it (where on the face the hand holds the cube)
    x_touch = x_eye + n * jnp.dot(n, x_e + distance * n - x_eye)
    touch = jax.tree_util.tree_map(
        lambda new, old: jnp.where(in_contact, new, old),
        TouchMemory(jnp.asarray(t, touch.t.dtype), x_touch, xd_e),
        touch,
    )
    i = (t >= eye.t_switch).astype(jnp.int32)
    stale = eye.t_stamp[i] < touch.t + eye.touch_guard  # the frame predates the last touch
    since = t - jnp.where(jnp.isfinite(touch.t), touch.t, t)
    stale = stale | ((eye.seen <= 0) & jnp.isfinite(touch.t))  # the eye lost it: touch if recent
    known = in_contact | jnp.where(stale, since <= eye.touch_memory, eye.seen > 0)
    x_free = jnp.where(stale, touch.x + touch.xd * since, x_eye)
    xd_free = jnp.where(stale, touch.xd, xd_eye)
    xdd_free = jnp.where(stale, jnp.zeros(2), xdd_eye)
    # out of contact: not inside the hand (the position projected onto what the sensor allows)
    r = x_free - x_e
    rho_sq = jnp.sum(r**2)
    inside = (rho_sq < distance**2) & (rho_sq > 0.0)
    rho = jnp.sqrt(jnp.where(inside, rho_sq, 1.0))
    u = jnp.where(inside, r / rho, jnp.zeros(2))  # unit, hand -> estimate (0: nothing to do)
    x_free = jnp.where(inside, x_e + distance * u, x_free)
    x = jnp.where(in_contact, x_touch, x_free)
    xd = jnp.where(in_contact, xd_e, xd_free)
    xdd = jnp.where(in_contact, xdd_e, xdd_free)
    return x, xd, xdd, known, touch


def eye_object_state(eye: EyeInput, t: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """(X_o, X_o', X_o'') at time ``t`` predicted from the estimate in force at ``t``."""
    i = (t >= eye.t_switch).astype(jnp.int32)
    tau = t - eye.t_stamp[i]
    x, xd, xdd = eye.x[i], eye.xd[i], eye.xdd[i]
    return x + xd * tau + 0.5 * xdd * tau**2, xd + xdd * tau, xdd


class Switches(NamedTuple):
    """Pytree leaves selecting the condition (so one compile serves all three) and the source of
    the object's state (simulator or eye)."""

    use_virtual: jax.Array  # () 0.0 or 1.0
    learn: jax.Array  # () 0.0 or 1.0
    eye: EyeInput = None  # None: ground truth (see ``switches``)


def switches(condition: str, eye: EyeInput | None = None) -> Switches:
    if condition not in CONDITIONS:
        raise ValueError(f"condition must be one of {CONDITIONS}, got {condition!r}")
    return Switches(
        use_virtual=jnp.asarray(0.0 if condition == "plain" else 1.0),
        learn=jnp.asarray(1.0 if condition == "learned" else 0.0),
        eye=truth_eye() if eye is None else eye,
    )


class PolicyState(NamedTuple):
    """State the closed loop's policy carries from step to step."""

    controller: object  # the impedance controller's state
    learner: object  # LearnerState (weights, latched t_c, ...)
    switches: Switches
    touch: TouchMemory  # used by camera runs only


class Loop(NamedTuple):
    """The pieces of the closed loop (all pure; ``policy`` plugs into ``mjx_scene.rollout``)."""

    mx: object  # MJX model with the default pendulum conditions applied
    ids: object  # static scene ids
    policy: object  # (policy_state, m, SimStep) -> (tau, policy_state, aux)
    initial_data: object  # () -> MJX data at the release (default conditions)
    initial_policy_state: object  # (data, learner_state, switches) -> PolicyState
    learner_init: object  # (key, dtype) -> LearnerState
    model_for: object  # (PendulumConditions) -> MJX model (pure, vmappable)
    data_for: object  # (mjx model, PendulumConditions) -> MJX data at the release


def build_loop(config: TaskConfig, pendulum: PendulumConditions) -> Loop:
    """World, hand and learner wired together for one pendulum condition."""
    lc = config.learner
    m_c = load_mj_model()
    ids = scene_ids(m_c)
    set_solver_options(
        m_c, config.solver_iterations, config.ls_iterations, config.solver, config.jacobian
    )
    mx_base = load_mjx_model(m_c)
    if config.hinge_x is not None:  # move the ceiling hinge (the rod's parent body) along x
        ceiling = int(m_c.body_parentid[ids.rod_body])
        mx_base = mx_base.replace(body_pos=mx_base.body_pos.at[ceiling, 0].set(config.hinge_x))
    mx_base = with_contact(mx_base, config)
    mx = apply_conditions(mx_base, ids, pendulum)
    q_home = jnp.asarray(solve_posture(m_c, ids, config.x_home))
    c_init, c_apply = make_impedance_controller(config.controller)
    l_init, l_update = make_online_learner(lc, sphere_fn)
    params = ImpedanceParams(
        m_e=jnp.asarray(lc.m_e), b_e=jnp.asarray(lc.b_e), k_e=jnp.asarray(lc.k_e)
    )
    target = Target(x_d=jnp.asarray(config.x_home), xd_d=jnp.zeros(2), xdd_d=jnp.zeros(2))
    dt = config.controller.dt

    def policy(ps, m, step: SimStep):
        cs, ls, sw, touch = ps
        obs = observe(m, ids, step)
        x_o_true, xd_o_true = obs.x_o, obs.xd_o
        xdd_e = (obs.xd_e - cs.xd_e_prev) / dt  # one sample old, as the controller's
        xdd_o = (obs.xd_o - cs.xd_o_prev) / dt
        in_contact = jnp.sqrt(jnp.sum(obs.f_int**2)) > config.contact_threshold
        # the object as the eye sees it (camera runs) or as simulated (sw.eye.use == 0), with
        # touch over vision (``TouchMemory``): a 30 fps eye with a constant-acceleration filter
        # learns of an impact only some frames after it.
        use_eye = sw.eye.use > 0
        x_eye, xd_eye, xdd_eye, known, touch_new = touch_object_state(
            sw.eye, touch, step.t, obs.x_e, obs.xd_e, xdd_e, obs.f_int, in_contact, TOUCH_DISTANCE
        )
        touch = jax.tree_util.tree_map(
            lambda new, old: jnp.where(use_eye, new, old), touch_new, touch
        )
        obs = obs._replace(
            x_o=jnp.where(use_eye, x_eye, obs.x_o),
            xd_o=jnp.where(use_eye, xd_eye, obs.xd_o),
            xdd_o=jnp.where(use_eye, xdd_eye, xdd_o),
        )
        xdd_o = obs.xdd_o
        # nothing seen or touched (recently): no virtual force and no learning
        seen = jnp.where(use_eye, known, sw.eye.seen > 0)
        inputs = LearnerInputs(
            obs.x_e, obs.xd_e, xdd_e, obs.x_o, obs.xd_o, xdd_o, obs.f_int, in_contact
        )
        keep = (sw.learn > 0) & seen
        ls_new, out = l_update(ls, inputs, keep)
        o = out.impedance * (sw.use_virtual * seen)  # (2, 3): K_o, B_o, M_o per axis
        vp = VirtualParams(m_o=o[:, 2], b_o=o[:, 1], k_o=o[:, 0], r=jnp.asarray(lc.radius))
        tau, cs, info = c_apply(params, vp, target, cs, obs)
        aux = dict(
            x_e=obs.x_e,
            xd_e=obs.xd_e,
            x_o=obs.x_o,
            xd_o=obs.xd_o,
            x_o_true=x_o_true,
            xd_o_true=xd_o_true,
            object_seen=seen,
            f_int=obs.f_int,
            f_o=info.f_o,
            k_o=o[:, 0],
            b_o=o[:, 1],
            m_o=o[:, 2],
            margins=out.margins,
            energy=out.energy,
            inside=out.inside,
            learning=out.learning,
            in_contact=in_contact,
            saturated=info.saturated,
        )
        return tau, PolicyState(cs, ls_new, sw, touch), aux

    def initial_data():
        return make_data(mx, ids, pendulum, q_home)

    def model_for(conditions):
        return apply_conditions(mx_base, ids, conditions)

    def data_for(m, conditions):
        return make_data(m, ids, conditions, q_home)

    def initial_policy_state(d0, ls, sw):
        cs0 = c_init(observe(mx, ids, SimStep(d=d0, f_int=jnp.zeros(3), t=d0.time)))
        return PolicyState(cs0, ls, sw, no_touch(d0.qpos.dtype))

    return Loop(mx, ids, policy, initial_data, initial_policy_state, l_init, model_for, data_for)


def _make_seed_run(config: TaskConfig, loop: Loop):
    """(key, switches, conditions) -> logs of one seed: ``config.swings`` swings (world restarted
    at the release each swing, learner state carried over), then the optional continuous run."""

    def one_swing(ls, sw, conditions, m, steps):
        d0 = loop.data_for(m, conditions)
        ps0 = loop.initial_policy_state(d0, ls, sw)
        f_ext = jnp.zeros((steps, 3))
        (_, ps), traj = rollout(m, loop.ids, d0, loop.policy, ps0, f_ext, conditions)
        ls = ps.learner
        ls = ls._replace(was_inside=jnp.asarray(False))
        log = dict(traj.aux, f_contact=traj.f_contact, t=traj.t, qpos=traj.qpos, qvel=traj.qvel)
        return ls, log

    def run_one_seed(key, sw, conditions):
        m = loop.model_for(conditions)
        ls0 = loop.learner_init(key, jnp.float64 if jax.config.jax_enable_x64 else jnp.float32)
        ls, logs = jax.lax.scan(
            lambda ls, _: one_swing(ls, sw, conditions, m, config.swing_steps),
            ls0,
            None,
            length=config.swings,
        )
        if config.final_steps > 0:
            _, final = one_swing(ls, sw, conditions, m, config.final_steps)
            logs = dict(logs, final=jax.tree_util.tree_map(lambda x: x[None], final))
        return logs

    return run_one_seed


def make_experiment(config: TaskConfig, pendulum: PendulumConditions):
    """Builds ``run(keys, switches) -> logs``: swings x steps logs for a batch of seeds.

    ``keys``: (n_seeds, 2) PRNG keys (network initialisation); ``switches``: a :class:`Switches`.
    Returns a dict of arrays with leading axes (n_seeds, swings, swing_steps); with
    ``config.final_steps > 0`` also ``final``: the logs (n_seeds, 1, final_steps) of one continuous
    run from the same release after the swings, with the learner's state carried over.
    """
    run_one_seed = _make_seed_run(config, build_loop(config, pendulum))
    return jax.jit(jax.vmap(lambda key, sw: run_one_seed(key, sw, pendulum), in_axes=(0, None)))


def make_sweep(config: TaskConfig, per_run_switches: bool = False):
    """``run(keys, switches, conditions) -> logs`` over a batch of runs: ``keys`` (B, 2) and every
    leaf of ``conditions`` (B,), one pendulum condition and network seed per run (``vmap``).
    With ``per_run_switches`` the ``use_virtual``/``learn`` leaves of ``switches`` are (B,) too, so
    plain and learned runs share one batch (and one compile). Not jitted here, so the caller can
    choose devices (``experiments/devices.py``)."""
    from hec_jax.mjx_scene import default_conditions

    run_one_seed = _make_seed_run(config, build_loop(config, default_conditions()))
    return jax.vmap(run_one_seed, in_axes=sweep_in_axes(per_run_switches))


def sweep_in_axes(per_run_switches: bool = False) -> tuple:
    """``make_sweep``'s ``vmap`` axes of (keys, switches, conditions) (``experiments.devices``)."""
    sw_axes = Switches(use_virtual=0, learn=0, eye=None) if per_run_switches else None
    return (0, sw_axes, 0)


def run_conditions(config: TaskConfig, pendulum: PendulumConditions, seed: int, n_seeds: int):
    """All three conditions for ``n_seeds`` seeds; returns {condition: logs as NumPy}, timings."""
    import time

    run = make_experiment(config, pendulum)
    keys = jax.random.split(jax.random.PRNGKey(seed), n_seeds)
    out, timing = {}, {}
    for condition in CONDITIONS:
        t0 = time.perf_counter()
        logs = run(keys, switches(condition))
        logs = jax.tree_util.tree_map(np.asarray, jax.block_until_ready(logs))
        timing[condition] = time.perf_counter() - t0
        out[condition] = logs
    return out, timing


# ---------------------------------------------------------------------------------------------
# Command line, metrics and files shared by catching.py and hitting.py (NumPy boundary).


def add_common_args(parser, out_default: str) -> None:
    """Flags every task script takes (the task-specific ones are added by the script)."""
    from pathlib import Path

    parser.add_argument("--out", type=Path, default=Path(out_default))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--seeds", type=int, default=5, help="network initialisations (vmapped)")
    parser.add_argument("--release-angle", type=float, default=-0.5, help="[rad]")
    parser.add_argument("--eta", type=float, default=0.3, help="learning rate of all three nets")
    parser.add_argument("--radius", type=float, default=0.25, help="virtual sphere r [m]")
    parser.add_argument("--r-b", type=float, default=0.085, help="R_b of Eqs. 62/66 [m]")
    parser.add_argument("--contact-stiffness", type=float, default=1e5, help="nominal k_c [N/m]")
    parser.add_argument(
        "--x-home", type=float, nargs=2, default=(0.65, 0.60), help="X_d (x, z) [m]"
    )
    parser.add_argument("--hinge-x", type=float, default=None, help="pendulum hinge x [m]")
    parser.add_argument(
        "--contact-solref",
        type=float,
        nargs=2,
        default=None,
        help="hand-cube contact (timeconst [s], dampratio); default: scene.xml's (0.005, 1)",
    )
    parser.add_argument("--eta-b", type=float, default=None, help="VVN learning rate")
    parser.add_argument("--eta-m", type=float, default=None, help="VIN learning rate")
    parser.add_argument("--contact-damping", type=float, default=0.0, help="nominal b_c [N s/m]")
    parser.add_argument(
        "--vel-after-contact", action="store_true", help="keep E_cv after contact (Eq. 59)"
    )
    parser.add_argument(
        "--kernel",
        choices=("xla", "triton"),
        default="xla",
        help="learner's network step: XLA reference, or one Pallas Triton kernel per sample "
        "(CUDA GPUs; the reference elsewhere; same results to rounding)",
    )
    parser.add_argument(
        "--nets-inside-only",
        action="store_true",
        help="evaluate the networks only inside the virtual sphere, where F_o uses them (the same "
        "forces and learning; K_o, B_o, M_o logged as 0 outside, so the Eq. 49 margins there are "
        "the target impedance's; with --kernel triton the kernel then skips those runs' weights)",
    )


def learner_from_args(args, task: str, f_desired: float) -> LearnerConfig:
    return LearnerConfig(
        task=task,
        radius=args.radius,
        r_b=args.r_b,
        eta=(
            args.eta,
            args.eta if args.eta_b is None else args.eta_b,
            args.eta if args.eta_m is None else args.eta_m,
        ),
        mu=args.mu,
        f_desired=f_desired,
        contact_stiffness=args.contact_stiffness,
        contact_damping=args.contact_damping,
        velocity_after_contact=args.vel_after_contact,
        kernel=args.kernel,
        nets_outside=not args.nets_inside_only,
    )


def config_from_args(
    args, learner: LearnerConfig, swing_s: float, swings: int, final_s: float = 0.0
) -> TaskConfig:
    """The TaskConfig of a task script: world set-up from the common flags, durations in [s]."""
    dt = ControllerConfig().dt
    return TaskConfig(
        learner=learner,
        x_home=tuple(args.x_home),
        hinge_x=args.hinge_x,
        contact_solref=None if args.contact_solref is None else tuple(args.contact_solref),
        swing_steps=int(round(swing_s / dt)),
        swings=swings,
        final_steps=int(round(final_s / dt)),
    )


def run_settings(args, task: str, pendulum, learner, config) -> dict:
    """What ``config.json`` records beside seed, versions and device."""
    return dict(
        {k: v for k, v in vars(args).items() if k != "seed"},
        out=str(args.out),
        pendulum=pendulum._asdict(),
        learner=repr(learner),
        task_config=repr(config),
        task=task,
    )


def contact_events(f_norm: np.ndarray, threshold: float, min_gap: int) -> list[tuple[int, int]]:
    """(start, end) sample indices of contact episodes in a force-magnitude series; contacts closer
    than ``min_gap`` samples are merged into one event (one hit may chatter)."""
    on = np.flatnonzero(f_norm > threshold)
    if on.size == 0:
        return []
    events, start, prev = [], on[0], on[0]
    for i in on[1:]:
        if i - prev > min_gap:
            events.append((int(start), int(prev) + 1))
            start = i
        prev = i
    events.append((int(start), int(prev) + 1))
    return events


def settle_metrics(f_norm: np.ndarray, f_desired: float, threshold: float, tail: int) -> dict:
    """How the contact force of one swing ends, (steps,) force magnitudes [N].

    ``settle_force``: mean |F_int| over the last ``tail`` samples; ``settle_rel_error``:
    |settle_force - f_desired| / f_desired; ``contacts``: contact episodes (gaps of 20 samples merged,
    as for ``contact_events``); ``held``: one episode that lasts to the end of the swing (the object
    never leaves the hand after the first contact: no second impact); ``overshoot_after_settle``:
    the largest |F_int| in the last ``tail`` samples over ``settle_force`` (1: flat).
    """
    events = contact_events(f_norm, threshold, min_gap=20)
    settle = float(np.mean(f_norm[-tail:]))
    return {
        "settle_force": settle,
        "settle_rel_error": abs(settle - f_desired) / f_desired,
        "contacts": len(events),
        "held": bool(len(events) == 1 and events[0][1] == f_norm.shape[-1]),
        "overshoot_after_settle": float(np.max(f_norm[-tail:]) / max(settle, 1e-12)),
    }


def hit_series(f_norm: np.ndarray, dt: float, threshold: float, tolerance: float = 0.2) -> dict:
    """Hits, their force pulses and the longest periodic series in one force series (steps,) [N].

    A hit is a contact episode (episodes less than 50 ms apart merged: one strike may chatter). The
    periodic series is the longest run of consecutive hits whose start-to-start intervals all lie
    within ``tolerance`` of the median interval of that run's hits (``periodic_hits`` counts hits,
    i.e. intervals + 1). Its force pulses are *bounded* when (i) no pulse exceeds the first pulse of
    the series (``pulse_growth`` = max pulse / first pulse <= 1: the strikes do not build up) and
    (ii) every pulse is a short impact (``max_pulse_duration_s`` under 50 ms), not a sustained push.
    """
    events = contact_events(f_norm, threshold, min_gap=int(round(0.05 / dt)))
    starts = np.array([e[0] for e in events], dtype=float) * dt
    peaks = np.array([float(f_norm[a:b].max()) for a, b in events])
    durations = np.array([(b - a) * dt for a, b in events])
    best = (0, min(len(events), 1))  # (first hit, number of hits) of the longest periodic run
    if len(events) >= 2:
        intervals = np.diff(starts)
        for i in range(len(intervals)):
            for j in range(len(intervals), i, -1):  # longest run starting at i first
                if j - i + 1 <= best[1]:
                    break
                seg = intervals[i:j]
                if np.all(np.abs(seg - np.median(seg)) <= tolerance * np.median(seg)):
                    best = (i, j - i + 1)
                    break
    i0, n = best
    series = slice(i0, i0 + n)
    sp, sd = peaks[series], durations[series]
    return {
        "hits": len(events),
        "periodic_hits": int(n),
        "hit_times_s": starts.tolist(),
        "peak_forces": peaks.tolist(),
        "pulse_durations_s": durations.tolist(),
        "max_peak_force": float(peaks.max()) if len(peaks) else 0.0,
        "series_first_hit": int(i0),
        "series_pulse_max": float(sp.max()) if n else 0.0,
        "series_pulse_last": float(sp[-1]) if n else 0.0,
        "pulse_growth": float(sp.max() / sp[0]) if n else 0.0,
        "max_pulse_duration_s": float(sd.max()) if n else 0.0,
        "pulses_bounded": bool(n > 0 and sp.max() <= sp[0] and sd.max() < 0.05),
        "median_interval_s": float(np.median(np.diff(starts[series]))) if n > 1 else None,
    }


def force_norm(logs: dict) -> np.ndarray:
    """|F_int| [N] of the contact solved at each step, (..., steps)."""
    return np.linalg.norm(logs["f_contact"][..., [0, 2]], axis=-1)


def mean_std(x) -> dict:
    x = np.asarray(x, dtype=float)
    return {"mean": float(np.mean(x)), "std": float(np.std(x))}


def save_trajectories(folder, logs_by_condition: dict, dt: float) -> None:
    """One ``trajectory_<condition>.npz`` per condition: t, x_e, x_o (as the controller used it),
    x_o_true (simulator), f_int, k_o, b_o, m_o (+ more),
    arrays with a leading seed axis (then swing and sample axes for swing-structured runs)."""
    from hec_jax.runs import write_npz

    for condition, logs in logs_by_condition.items():
        steps = logs["x_e"].shape[-2]
        write_npz(
            folder / f"trajectory_{condition}.npz",
            t=np.arange(steps) * dt,
            x_e=logs["x_e"],
            xd_e=logs["xd_e"],
            x_o=logs["x_o"],
            xd_o=logs["xd_o"],
            x_o_true=logs["x_o_true"],
            xd_o_true=logs["xd_o_true"],
            f_int=logs["f_contact"][..., [0, 2]],
            f_o=logs["f_o"],
            k_o=logs["k_o"],
            b_o=logs["b_o"],
            m_o=logs["m_o"],
            margins=logs["margins"],
            inside=logs["inside"],
            learning=logs["learning"],
            in_contact=logs["in_contact"],
            object_seen=logs["object_seen"],
        )


def stability_summary(logs: dict) -> dict:
    """Smallest strict Eq. 49 margins (K_o + K_e, B_o + B_e, M_o + M_e) over every sample."""
    m = logs["margins"].reshape(-1, logs["margins"].shape[-2], 3)
    return {
        "min_k_margin": float(m[..., 0].min()),
        "min_b_margin": float(m[..., 1].min()),
        "min_m_margin": float(m[..., 2].min()),
        "all_strictly_stable": bool(np.all(m > 0)),
    }
