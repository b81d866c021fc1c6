"""What the benchmark scripts (``benchmarks/``) run and time, shared so that each script is a thin
command line: timing loops, plain-text tables, the MuJoCo C baselines, the closed loops reduced to
what a benchmark times, and the gradient cases.

Timing rules (as :mod:`hec_jax.report`'s): every timed call blocks until its outputs are ready; a
jitted function's first call (compilation) is timed apart; a rate in steps/s is simulated control
steps of one environment per wall-clock second, summed over the batch. Nothing here is jitted
itself; the functions returned are, where their docstrings say so.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable, Sequence
from typing import Literal, NamedTuple, get_args

# first: mujoco.mjx without its warp-not-installed lines (hec_jax.mjx_scene._quiet_import)
from hec_jax.mjx_scene import _quiet_import  # noqa: F401

# isort: split
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx
from mujoco import rollout as mj_rollout

from hec_jax.control import (
    ControllerConfig,
    ImpedanceParams,
    Target,
    VirtualParams,
    make_impedance_controller,
    sphere_kinematics,
)
from hec_jax.loop import (
    Loop,
    OnDevices,
    Sharded,
    TaskConfig,
    build_loop,
    make_c_policy,
    make_mjx_policy,
    make_sweep,
    switches,
)
from hec_jax.loop.observation import observe, observe_c
from hec_jax.mjx_scene import (
    TASK_AXES,
    PendulumConditions,
    SceneIds,
    SimStep,
    c_quantities,
    differentiable,
    load_mj_model,
    make_data,
    make_data_c,
    rollout,
    rollout_c,
    scene_ids,
)
from hec_jax.mjx_scene.contact_probe import make_probe, probe_conditions
from hec_jax.nets import LearnerConfig, LearnerInputs, SphereGeometry, make_online_learner
from hec_jax.report import call_times, timed

# ---------------------------------------------------------------------------------------------
# Timing and tables


def best_of(fn: Callable[[], object], repeat: int = 3) -> float:
    """The shortest wall time [s] of ``repeat`` calls of ``fn`` (which must block until done)."""
    return float(call_times(fn, repeat).min())


def first_call(fn, *args) -> tuple[object, float]:
    """(outputs, wall time [s]) of ``fn(*args)`` waited for: a jitted function's compile + run."""
    return timed(lambda: jax.block_until_ready(fn(*args)))


def mean_call(fn, args: tuple, repeats: int) -> float:
    """Mean wall time [s] per call of ``fn(*args)``: one call to compile, then ``repeats`` calls
    dispatched back to back and the last one waited for (latency of a pipelined control loop).
    """
    jax.block_until_ready(fn(*args))

    def calls():
        for _ in range(repeats - 1):
            fn(*args)
        jax.block_until_ready(fn(*args))

    return timed(calls)[1] / repeats


def interleaved_best(fns: dict[str, Callable], args: tuple, repeat: int) -> dict[str, float]:
    """{name: shortest wall time [s] of ``fn(*args)``} over ``repeat`` rounds, each round calling
    every function once in turn, so that a change of load hits every row alike.
    """
    times = {name: np.inf for name in fns}
    for _ in range(repeat):
        for name, fn in fns.items():
            _, t = timed(lambda fn=fn: jax.block_until_ready(fn(*args)))
            times[name] = min(times[name], t)
    return times


def text_table(header: Sequence[str], widths: Sequence[int], rows: Sequence[Sequence]) -> list[str]:
    """Lines of a plain-text table: the first column left-aligned in ``widths[0]`` characters,
    the next ones right-aligned in theirs, the last (notes) after two spaces, unpadded.
    """

    def line(cells):
        cells = [str(c) for c in cells]
        first = cells[0].ljust(widths[0])
        middle = [c.rjust(w) for c, w in zip(cells[1:-1], widths[1:], strict=True)]
        return " ".join([first, *middle]) + "  " + cells[-1]

    return [line(header)] + [line(r) for r in rows]


def device_name() -> str:
    """The first JAX device's kind and the backend, e.g. ``"cpu (cpu)"``."""
    return f"{jax.devices()[0].device_kind} ({jax.default_backend()})"


def float_dtype(float32: bool):
    """Switches JAX's 64-bit mode to match and returns the float dtype (call before any array)."""
    jax.config.update("jax_enable_x64", not float32)
    return jnp.float32 if float32 else jnp.float64


# ---------------------------------------------------------------------------------------------
# MuJoCo C baselines


def full_state(m: mujoco.MjModel, d: mujoco.MjData) -> np.ndarray:
    """``mjSTATE_FULLPHYSICS`` of ``d`` (what ``mujoco.rollout`` starts from)."""
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    state = np.zeros(mujoco.mj_stateSize(m, spec))
    mujoco.mj_getState(m, d, state, spec)
    return state


def release_states(m: mujoco.MjModel, ids: SceneIds, release: np.ndarray) -> np.ndarray:
    """(B, nstate) full states of the scene at rest with the hinge at each ``release`` [rad]."""
    d = mujoco.MjData(m)
    states = []
    for angle in np.asarray(release):
        mujoco.mj_resetData(m, d)
        d.qpos[ids.pend_qpos] = angle
        states.append(full_state(m, d))
    return np.stack(states)


def c_rollout_seconds(
    m: mujoco.MjModel, states: np.ndarray, ctrl: np.ndarray, threads: int, repeat: int = 3
) -> float:
    """Shortest wall time [s] of MuJoCo C's ``mujoco.rollout`` of ``states`` (B, nstate) under
    the open-loop controls ``ctrl`` (B, T, nu) on ``threads`` threads, after one untimed call.
    """
    batch = len(states)
    datas = [mujoco.MjData(m) for _ in range(threads)]
    with mj_rollout.Rollout(nthread=threads) as r:
        r.rollout([m] * batch, datas, states, ctrl)
        return best_of(lambda: r.rollout([m] * batch, datas, states, ctrl), repeat)


def solver_name(m: mujoco.MjModel) -> str:
    """``opt.solver`` and ``opt.jacobian`` by name, e.g. ``"mjSOL_NEWTON, mjJAC_DENSE"``."""
    return f"{mujoco.mjtSolver(m.opt.solver).name}, {mujoco.mjtJacobian(m.opt.jacobian).name}"


def effective_settings(m: mujoco.MjModel) -> tuple:
    """(solver, jacobian) as MuJoCo runs them: ``auto`` is dense below 60 dofs."""
    jacobian = m.opt.jacobian
    if jacobian == mujoco.mjtJacobian.mjJAC_AUTO:
        sparse = m.nv >= 60
        jacobian = mujoco.mjtJacobian.mjJAC_SPARSE if sparse else mujoco.mjtJacobian.mjJAC_DENSE
    return m.opt.solver, jacobian


def physics_only(m: mujoco.MjModel, batch: int, steps: int, impl: str = "jax"):
    """Jitted ``run(release) -> (largest hinge angle (B,), final qpos (B, nq))``: ``mjx.step`` in
    a ``lax.scan`` of ``steps`` steps, zero torques, from rest with the hinge at each ``release``
    [rad] (B,) (``vmap``), on MJX's ``impl`` ("jax" or "warp": MuJoCo Warp, whose contact buffers
    are sized for ``batch`` worlds).
    """
    mx = mjx.put_model(m, impl=impl)
    if impl == "warp":  # contact buffers are shared by all worlds: one hand-cube contact each
        d0 = mjx.make_data(m, impl="warp", naconmax=max(batch, 8), njmax=16)
    else:
        d0 = mjx.make_data(mx)
    hinge = int(m.jnt_qposadr[m.joint("hinge").id])

    def one(angle):
        def step(d, _):
            d = mjx.step(mx, d)
            return d, d.qpos[hinge]

        d = d0.replace(qpos=d0.qpos.at[hinge].set(angle))
        d, angles = jax.lax.scan(step, d, None, length=steps)
        return jnp.max(angles), d.qpos

    return jax.jit(jax.vmap(one))


# ---------------------------------------------------------------------------------------------
# Impedance control alone (benchmarks/control.py)


def control_step(mm, ids: SceneIds, conditions, q_home, cfg: ControllerConfig | None = None):
    """(jitted ``apply``, its arguments but the parameters) of one control step on the TaskObs of
    MuJoCo C data at the release: ``apply(params, vparams, target, state, obs)``.
    """
    d = make_data_c(mm, ids, conditions, q_home)
    obs = observe_c(ids, d.qpos, d.qvel, c_quantities(mm, d, ids), np.zeros(3))
    init, apply = make_impedance_controller(ids.timestep, ids.torque_limit, cfg)
    target = Target(obs.x_e, jnp.zeros(2), jnp.zeros(2))
    return jax.jit(apply), (target, init(obs), obs)


def control_rollout(mx, ids, q_home, conditions, params, vparams, steps: int, cfg=None):
    """``run(release) -> Trajectory``: ``steps`` steps of MJX physics + observe + impedance
    controller in one ``lax.scan`` (``mjx_scene.rollout``) from ``release`` [rad] (pure,
    vmappable); the target is the hand's position at the release.
    """
    policy_init, policy = make_mjx_policy(ids, cfg)

    def run(release):
        c = conditions._replace(release_angle=release)
        d0 = make_data(mx, ids, c, jnp.asarray(q_home))
        x_d = d0.site_xpos[ids.hand_site][jnp.array(TASK_AXES)]
        ps0 = policy_init(mx, d0, params, vparams, Target(x_d, jnp.zeros(2), jnp.zeros(2)))
        return rollout(mx, ids, d0, policy, ps0, jnp.zeros((steps, 3)), c)[1]

    return run


def c_control_rollout(mm, ids, q_home, conditions, params, vparams, steps: int, cfg=None):
    """``() -> None``: the same closed loop on MuJoCo C (``rollout_c``, a Python loop calling the
    same jitted controller on MuJoCo C quantities).
    """
    policy_init, policy = make_c_policy(ids, cfg)

    def run():
        d = make_data_c(mm, ids, conditions, q_home)
        cq = c_quantities(mm, d, ids)
        x_d = jnp.asarray(cq.x_hand[list(TASK_AXES)])
        ps0 = policy_init(d, cq, params, vparams, Target(x_d, jnp.zeros(2), jnp.zeros(2)))
        rollout_c(mm, ids, d, policy, ps0, np.zeros((steps, 3)), conditions)

    return run


# ---------------------------------------------------------------------------------------------
# Control + learning (benchmarks/learning.py)


def plain_impedance(loop: Loop) -> tuple[ImpedanceParams, Target, VirtualParams]:
    """The task's target impedance (Eq. 40), its resting target at ``loop.x_home`` and a zero
    virtual impedance: the controller's arguments for plain impedance control.
    """
    imp, radius = loop.config.impedance, loop.config.learner.radius
    params = ImpedanceParams(jnp.asarray(imp.m_e), jnp.asarray(imp.b_e), jnp.asarray(imp.k_e))
    target = Target(jnp.asarray(loop.x_home), jnp.zeros(2), jnp.zeros(2))
    zero = jnp.zeros(2)
    return params, target, VirtualParams(zero, zero, zero, jnp.asarray(radius))


def learning_steps(loop: Loop, conditions: PendulumConditions, key, dtype) -> dict:
    """{name: (jitted fn, args)} of one step at the release: control + learning and control only
    on a given TaskObs, and the loop's policy and the plain impedance policy on the MJX data
    (observation included). The learner's inputs take zero accelerations, as a first sample.
    """
    task, ids = loop.config, loop.ids
    lc = task.learner
    params, target, zero_vp = plain_impedance(loop)
    c_init, c_apply = make_impedance_controller(ids.timestep, ids.torque_limit, task.controller)
    imp = task.impedance
    _, l_update = make_online_learner(lc, ids.timestep, imp.m_e, imp.b_e, imp.k_e)
    m = loop.model_for(conditions)
    d0 = loop.data_for(m, conditions)
    step = SimStep(d=d0, f_int=jnp.zeros(3), t=d0.time)
    obs = jax.jit(observe, static_argnums=1)(m, ids, step)
    cs, ls = c_init(obs), loop.learner_init(key, dtype)

    def control_and_learning(cs, ls, obs):
        zero = jnp.zeros(2)
        sk = sphere_kinematics(obs.x_o - obs.x_e, obs.xd_o - obs.xd_e, zero, lc.radius)
        sphere = SphereGeometry(sk.dx_o, sk.dxd_o, sk.dxdd_o)
        inputs = LearnerInputs(
            obs.x_e, obs.xd_e, zero, obs.x_o, obs.xd_o, zero, obs.f_int, jnp.asarray(False), sphere
        )
        ls, out = l_update(ls, inputs)
        o = out.impedance
        vp = VirtualParams(o[:, 2], o[:, 1], o[:, 0], jnp.asarray(lc.radius))
        tau, cs, _ = c_apply(params, vp, target, cs, obs)
        return tau, cs, ls

    def control_only(cs, obs):
        tau, cs, _ = c_apply(params, zero_vp, target, cs, obs)
        return tau, cs

    plain_init, plain_policy = make_mjx_policy(ids, task.controller)
    ps_learn = loop.initial_policy_state(m, d0, ls, switches("learned"))
    ps_plain = plain_init(m, d0, params, zero_vp, target)
    return {
        "control_and_learning": (jax.jit(control_and_learning), (cs, ls, obs)),
        "control_only": (jax.jit(control_only), (cs, obs)),
        "control_and_learning_with_observe": (jax.jit(loop.policy), (ps_learn, m, step)),
        "control_only_with_observe": (jax.jit(plain_policy), (ps_plain, m, step)),
    }


def learning_rollouts(loop: Loop, conditions: PendulumConditions, steps: int, dtype) -> dict:
    """{"learning", "forward_only"}: ``run(key) -> x_hand (steps, 3)`` (pure, vmappable):
    ``steps`` steps of MJX physics + controller with the online learner (learned condition) or
    plain impedance; the release angle is moved by 1e-3 rad N(0, 1) drawn from ``key``, so that
    ``vmap`` cannot hoist the work out of a batch.
    """
    task, ids = loop.config, loop.ids
    params, target, zero_vp = plain_impedance(loop)
    plain_init, plain_policy = make_mjx_policy(ids, task.controller)
    f_ext = jnp.zeros((steps, 3))
    m = loop.model_for(conditions)

    def start(key):
        d = loop.data_for(m, conditions)
        angle = d.qpos[ids.pend_qpos] + 1e-3 * jax.random.normal(key, ())
        return d.replace(qpos=d.qpos.at[ids.pend_qpos].set(angle))

    def learning(key):
        d = start(key)
        ps = loop.initial_policy_state(m, d, loop.learner_init(key, dtype), switches("learned"))
        return rollout(m, ids, d, loop.policy, ps, f_ext, None)[1].x_hand

    def forward_only(key):
        d = start(key)
        ps = plain_init(m, d, params, zero_vp, target)
        return rollout(m, ids, d, plain_policy, ps, f_ext, None)[1].x_hand

    return {"learning": learning, "forward_only": forward_only}


# ---------------------------------------------------------------------------------------------
# Exact gradients through closed-loop rollouts (benchmarks/gradients.py, benchmarks/sweep.py)


def _batched(fn):
    return jax.jit(jax.vmap(fn, in_axes=(None, 0)))


def probe_gradients(task: TaskConfig, steps: int, batch: int, dtype):
    """(forward, {name: value_and_grad}, args) of the contact probe (PD-held hand struck by the
    pendulum, ``mjx_scene.contact_probe``) w.r.t. its 3 gains, over ``batch`` conditions.
    ``task`` is not used (the probe has no learner).
    """
    conds = probe_conditions(batch, 0, dtype)
    gains = jnp.zeros(3, dtype)
    base, one = make_probe(), make_probe(iterations=1)

    def implicit(ck, jacfwd=False):
        return lambda m, ids, d, pol, ps, f, c: differentiable.rollout(
            m, ids, d, pol, ps, f, c, checkpoint=ck, observe_jacfwd=jacfwd
        )

    def vg(probe, rollout_fn):
        return _batched(jax.value_and_grad(lambda g, c: probe.loss(g, c, steps, rollout_fn)[0]))

    def forward_mode(g, c):
        loss = lambda gg: (base.loss(gg, c, steps, implicit(False))[0],) * 2  # noqa: E731
        return jax.jacfwd(loss, has_aux=True)(g)[::-1]

    grads = {
        "implicit": vg(base, implicit(False)),
        "implicit+remat": vg(base, implicit(True)),
        "implicit, jacfwd through the stages": vg(base, implicit(False, True)),
        "implicit, forward mode (jacfwd, 3 tangents)": _batched(forward_mode),
        "unrolled (iterations=1)": vg(one, rollout),
    }
    forward = _batched(lambda g, c: base.loss(g, c, steps, rollout)[0])
    return forward, grads, (gains, conds)


def catching_gradients(task: TaskConfig, steps: int, batch: int, dtype):
    """(forward, {name: value_and_grad}, args) of the catching loop with the initial (frozen)
    networks: sum |F_contact|^2 1e-5 + sum x_hand over ``steps`` steps from the release, w.r.t.
    all network weights (Eqs. 50-51), over ``batch`` probe conditions.
    """
    loop = build_loop(task)
    ls0 = loop.learner_init(jax.random.PRNGKey(0), dtype)
    conds = probe_conditions(batch, 0, dtype)

    def loss(params, c, fn):
        m = loop.model_for(c)
        d0 = loop.data_for(m, c)
        ps0 = loop.initial_policy_state(m, d0, ls0._replace(params=params), switches("frozen"))
        _, traj = fn(m, loop.ids, d0, loop.policy, ps0, jnp.zeros((steps, 3), dtype), c)
        return jnp.sum(traj.f_contact**2) * 1e-5 + jnp.sum(traj.x_hand[:, 0])

    def implicit(ck):
        return lambda *a: differentiable.rollout(*a, checkpoint=ck)

    grads = {
        "implicit": _batched(jax.value_and_grad(lambda p, c: loss(p, c, implicit(False)))),
        "implicit+remat": _batched(jax.value_and_grad(lambda p, c: loss(p, c, implicit(True)))),
    }
    return _batched(lambda p, c: loss(p, c, rollout)), grads, (ls0.params, conds)


GRADIENT_CASES = {"probe": probe_gradients, "catching": catching_gradients}


def all_finite(tree) -> bool:
    """Every leaf of ``tree`` finite."""
    return all(bool(np.all(np.isfinite(x))) for x in jax.tree_util.tree_leaves(tree))


# ---------------------------------------------------------------------------------------------
# The sweep's learning loop (benchmarks/sweep.py)

# network-step variants: kernel, and "-inside" for LearnerConfig(nets_outside=False)
Variant = Literal["xla", "triton", "xla-inside", "triton-inside"]
VARIANTS = get_args(Variant)


def learner_variant(learner: LearnerConfig, variant: str) -> LearnerConfig:
    """``learner`` with the network step of ``variant`` (one of ``VARIANTS``)."""
    kernel, _, where = variant.partition("-")
    return dataclasses.replace(learner, kernel=kernel, nets_outside=where != "inside")


def variant_of(learner: LearnerConfig) -> str:
    """The variant name of ``learner``'s network step (inverse of :func:`learner_variant`)."""
    return learner.kernel + ("" if learner.nets_outside else "-inside")


def one_swing(task: TaskConfig, steps: int) -> TaskConfig:
    """``task`` with one swing of ``steps`` control steps (the model's time step) and no
    continuous run (the settle window cut to the swing where longer).
    """
    swing_s = steps * float(load_mj_model().opt.timestep)
    return dataclasses.replace(
        task, swings=1, swing_s=swing_s, final_s=0.0, settle_s=min(task.settle_s, swing_s)
    )


def scene_solver(task: TaskConfig) -> TaskConfig:
    """``task`` with scene.xml's constraint solver settings."""
    return dataclasses.replace(
        task, solver_iterations=None, ls_iterations=None, solver=None, jacobian=None
    )


def release_batch(conditions: PendulumConditions, size: int, lo=-0.55, hi=-0.45):
    """(keys (size, 2), conditions (size,) each, release angles [rad] (size,)): ``conditions``
    with the release angle spread over [lo, hi] (distinct runs: ``vmap`` cannot hoist the work),
    one network seed per run (``PRNGKey(0)`` split).
    """
    release = jnp.linspace(lo, hi, size)
    batched = PendulumConditions(
        **{k: jnp.broadcast_to(v, (size,)) for k, v in conditions._asdict().items()}
    )._replace(release_angle=release)
    return jax.random.split(jax.random.PRNGKey(0), size), batched, release


def peaks_and_shares(loop: Loop):
    """``run(keys, conditions) -> (peak, learning, inside)`` (not jitted; for
    :class:`~hec_jax.loop.OnDevices`): each run's peak contact force [N] under the learned
    condition, and the shares of its steps in which the learner updated its weights and in which
    the cube was inside the virtual sphere.
    """
    sweep = make_sweep(loop)
    sw = switches("learned")

    def run(keys, conditions):
        logs = sweep(keys, sw, conditions)
        f = jnp.abs(logs["f_contact"])
        peak = jnp.max(f, axis=tuple(range(1, f.ndim)))
        flat = lambda x: x.reshape(x.shape[0], -1).astype(peak.dtype)  # noqa: E731
        return peak, flat(logs["learning"]).mean(1), flat(logs["inside"]).mean(1)

    return run


def time_on_devices(runner, *args, repeat: int = 3):
    """(outputs, first call [s] (compile included), shortest of ``repeat`` calls [s]) of an
    :class:`~hec_jax.loop.OnDevices` / :class:`~hec_jax.loop.Sharded` ``runner`` on ``args``,
    placed on its devices once, outside the timed calls.
    """
    placed = runner.place(*args)
    out, compile_s = timed(lambda: runner.run(placed))
    return out, compile_s, best_of(lambda: runner.run(placed), repeat)


def host_threads() -> int:
    """The host's CPU cores (MuJoCo C's threads)."""
    return os.cpu_count() or 1


class LoopRates(NamedTuple):
    """What :func:`loop_rows` measured.

    Attributes:
        rates: {(variant, devices): steps/s} of the learning loop (one executable per device).
        counts: the device counts timed (the first is one device).
        peaks: {variant: each run's peak contact force [N] (B,)} on one device.
        learning_share: share of run-steps in which the learner updated its weights (last variant).
        inside_share: share of run-steps with the cube inside the virtual sphere (last variant).
    """

    rates: dict
    counts: list
    peaks: dict
    learning_share: float
    inside_share: float


def loop_rows(task, variants, batch, steps, per_device, spmd, add_row) -> LoopRates:
    """Times the learning loop of ``task`` (one swing of ``steps``) with each network-step
    variant on the first n devices, n = 1, 2, 4, ... (one executable per device, called from its
    own thread; with ``spmd`` also one GSPMD program for n > 1, not for the Triton kernel on
    GPUs); ``batch`` runs in all (``per_device``: on every device). Rows go to
    ``add_row(what, steps/s, notes)`` as they are measured.
    """
    n_dev = jax.device_count()
    counts = [n for n in (1, 2, 4, 8, 16) if n <= n_dev and (per_device or batch % n == 0)]
    rates, peaks, shares = {}, {}, (np.nan, np.nan)
    for variant in variants:
        learner = learner_variant(task.learner, variant)
        per_run = peaks_and_shares(build_loop(dataclasses.replace(task, learner=learner)))
        ways = [(n, OnDevices) for n in counts]
        if spmd and not (variant.startswith("triton") and jax.default_backend() == "gpu"):
            ways += [(n, Sharded) for n in counts if n > 1]  # GSPMD cannot split Triton
        for n, strategy in ways:
            size = batch * n if per_device else batch
            keys, conditions, _ = release_batch(task.pendulum.conditions(), size)
            runner = strategy(per_run, jax.devices()[:n], (0, 0))
            (peak, learning, inside), compile_s, wall = time_on_devices(runner, keys, conditions)
            if n == counts[0]:
                peaks[variant] = peak
                shares = float(learning.mean()), float(inside.mean())
            note, same = f"compile {compile_s:.0f} s, best of 3: {wall:.2f} s", ""
            if n > counts[0] and not per_device:  # the same runs as on one device
                diff = float(np.max(np.abs(peak - peaks[variant])))
                same = f"; peaks differ from 1 device's by at most {diff:.2g} N"
            rate = size * steps / wall
            if strategy is Sharded:
                what = f"  the same as one GSPMD program (--spmd), {n} device(s), batch {size}"
                speedup = f"{rate / rates[variant, counts[0]]:.2f}x 1 device"
                add_row(what, f"{rate:.3g}", f"{note}, {speedup}{same}")
                continue
            rates[variant, n] = rate
            what = f"MJX learning loop ({variant} network step), {n} device(s), batch {size}"
            add_row(what, f"{rate:.3g}", note + same)
    return LoopRates(rates, counts, peaks, *shares)


def physics_rows(m: mujoco.MjModel, release, steps: int, warp: bool, add_row) -> dict:
    """Times :func:`physics_only` on MJX (and with ``warp`` on MuJoCo Warp, with the largest
    differences of its results from MJX's); returns {"jax": steps/s, "warp": steps/s}.
    """
    batch, rates, results = len(release), {}, {}
    for impl in ("jax", "warp") if warp else ("jax",):
        fn = physics_only(m, batch, steps, impl)
        out, compile_s = first_call(fn, release)
        results[impl] = [np.asarray(x) for x in out]
        wall = best_of(lambda fn=fn: jax.block_until_ready(fn(release)))
        rates[impl] = batch * steps / wall
        what = "MJX physics only (mjx.step scan)" if impl == "jax" else "MuJoCo Warp physics only"
        note = f"compile {compile_s:.0f} s, best of 3: {wall:.2f} s"
        if impl == "warp":
            hinge, qpos = (np.max(np.abs(w - j)) for w, j in zip(*results.values(), strict=True))
            note += f"; vs MJX: largest hinge angle {hinge:.1e} rad, final qpos {qpos:.1e} rad"
        add_row(f"{what}, 1 device, batch {batch}", f"{rates[impl]:.3g}", note)
    return rates


def c_rows(m: mujoco.MjModel, m_scene: mujoco.MjModel, release, steps, repeats, add_row) -> float:
    """Times MuJoCo C's ``mujoco.rollout`` (zero torques, all host cores) from each ``release``
    on ``m``, and on ``m_scene`` (scene.xml's solver) where MuJoCo runs that differently; returns
    the faster rate [steps/s], the baseline (a setting that suits MJX cannot make C look slow).
    """
    batch, threads = len(release), host_threads()
    models = [(m, f"same settings ({solver_name(m)})")]
    if effective_settings(m_scene) != effective_settings(m):
        models.append((m_scene, f"scene.xml's {solver_name(m_scene)}"))
    rates = []
    for m_c, what in models:
        states = release_states(m_c, scene_ids(m_c), release)
        ctrl = np.zeros((batch, steps, m_c.nu))
        wall = c_rollout_seconds(m_c, states, ctrl, threads, repeats)
        rates.append(batch * steps / wall)
        add_row(
            f"MuJoCo C mujoco.rollout, physics only, {threads} threads, batch {batch}",
            f"{rates[-1]:.3g}",
            f"{what}, best of {repeats}: {wall:.2f} s",
        )
    return max(rates)


def gradient_rows(task: TaskConfig, batch: int, steps: int, dtype, add_row) -> float:
    """Times the catching case's exact gradient (implicit + remat) against its forward rollout
    with scene.xml's solver, interleaved, best of 3; returns gradient / forward.

    Raises:
        FloatingPointError: a non-finite output.
    """
    forward, grads, args = catching_gradients(scene_solver(task), steps, batch, dtype)
    fns = {"forward": forward, "gradient": grads["implicit+remat"]}
    compile_s = {}
    for name, fn in fns.items():
        out, compile_s[name] = first_call(fn, *args)
        if not all_finite(out):
            raise FloatingPointError(f"non-finite {name} in the gradient-cost row")
    times = interleaved_best(fns, args, 3)
    for name, what in (
        ("forward", "catching loop forward (rollout), scene.xml's solver"),
        ("gradient", "value_and_grad, all weights (implicit+remat), scene.xml's"),
    ):
        add_row(
            f"{what}, batch {batch} x {steps} steps",
            f"{batch * steps / times[name]:.3g}",
            f"compile {compile_s[name]:.0f} s, best of 3: {times[name]:.2f} s",
        )
    return times["gradient"] / times["forward"]
