"""The hand-eye loop on the wall clock: controller + learner every 1 ms, the eye at 30 fps.

Per tick j (plant time j dt, :class:`~hec_jax.realtime.clock.WallClock`):

1. wait for the tick (sleep, then spin the last ``spin_us``);
2. read the plant's sample j (:class:`~hec_jax.realtime.plant.Plant`: joint state, end-point
   force, time); if the eye has published a newer estimate, it becomes the object's state source
   (latest-estimate policy: the eye itself takes the newest frame, :mod:`.workers`);
3. the observation of Eqs. 39-44 from the joint state by MuJoCo C
   (:class:`~hec_jax.realtime.plant.ArmModel`), packed into one vector;
4. one jitted call: :attr:`hec_jax.loop.policy.Loop.policy_obs`, the very function the simulated
   loops run after their MJX observation (object state from eye and touch, online learning of
   Eqs. 50-66, impedance law of Eqs. 41-49), on flat vectors (policy state, switches,
   observation in; policy state, torques and the logged signals out), so each call passes
   three arrays and the steps since the previous call;
5. write the torques; the plant applies them to step j if they came before its deadline
   ((j + 1) dt), else holds the previous ones (:class:`~hec_jax.realtime.plant.MujocoPlant`).

Each tick records its clock times and the control thread's CPU time per stage
(:data:`TICK_TIMES`, :data:`TICK_CPU`). :func:`run_realtime` runs the loop with every thread of
the control process (XLA's pool threads, which run parts of each jitted step, included) on one
CPU and, at real-time priority, XLA's threads one priority below the loop
(:class:`~hec_jax.realtime.clock.pinned`, :class:`~hec_jax.realtime.clock.realtime_priority`),
with ``RealtimeConfig.cpu_latency_us`` set, idle CPUs polling rather than halting
(:class:`~hec_jax.realtime.clock.cpu_latency_request`); ``experiments/realtime.py`` also makes
JAX's CPU dispatch inline (docs/realtime.md).

Episodes (swings) are as in :mod:`hec_jax.loop.episodes`: the world restarts at the release,
the controller state restarts, the learner's weights carry over. Un-timed mode
(:class:`~hec_jax.realtime.clock.FreeClock`) runs the same code with no clock: every torque is on
time and the run is the simulated loop's step sequence in MuJoCo C (tests compare it with
:func:`hec_jax.mjx_scene.rollout_c` and with the MJX episodes).
"""

from __future__ import annotations

import contextlib
import dataclasses
import gc
import math
import os
import queue
import resource
import time
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from hec_jax.control import TaskObs
from hec_jax.loop.camera_loop import mid_exposure_steps, run_camera, steps_per_frame
from hec_jax.loop.config import (
    PRESETS,
    CameraConfig,
    ExperimentConfig,
)
from hec_jax.loop.episodes import make_episodes
from hec_jax.loop.experiment import condition_metrics
from hec_jax.loop.object_state import EyeInput
from hec_jax.loop.policy import Loop, build_loop, switches
from hec_jax.realtime import workers
from hec_jax.realtime.clock import (
    Clock,
    FreeClock,
    WallClock,
    cpu_latency_request,
    host_steal_ms,
    idle_filler,
    monotonic_s,
    pin_process,
    pinned,
    pool_idle_refused,
    pool_rescue,
    realtime_priority,
    rt_budget_rest_s,
)
from hec_jax.realtime.config import RealtimeConfig
from hec_jax.realtime.plant import (
    ArmModel,
    ArmObs,
    MujocoPlant,
    Plant,
    PlantSample,
    plant_model,
)
from hec_jax.realtime.report import compare_metrics, deadline_report
from hec_jax.realtime.shared import _CTX, Board, wait_for

# Per-tick records of :func:`run_loop` (``LoopRun.ticks``): clock times [s] of the tick's phases,
# and the control thread's CPU time [ns] per stage (load-insensitive: time the thread ran, not
# time it waited), the CPU time of the process's other threads (XLA's pool running parts of the
# jitted step), the control thread's context switches during the tick's work and its page
# faults since the previous tick's torques (the wait for this tick included).
TICK_TIMES = ("t_due", "t_wake", "t_obs", "t_step", "t_write", "t_stamp")
TICK_CPU = (
    "cpu_read",
    "cpu_observe",
    "cpu_step",
    "cpu_write",
    "cpu_other_threads",
    "switches_voluntary",
    "switches_involuntary",
    "faults_major",
    "faults_minor",
)
_thread_ns, _process_ns = time.thread_time_ns, time.process_time_ns
# [s] before tick 0 at which the dry ticks of an episode's lead stop (one takes about 0.3 ms)
WARM_UNTIL_S = 1.5e-3
_rusage = resource.getrusage
_THREAD = getattr(resource, "RUSAGE_THREAD", resource.RUSAGE_SELF)


def float_dtype():
    """The loop's float type: float64 with ``jax_enable_x64``, else float32."""
    return jnp.float64 if jax.config.jax_enable_x64 else jnp.float32


# ---------------------------------------------------------------------------------------------
# Flat vectors at the jit boundary


class Flat:
    """A pytree <-> one flat vector, for a fixed structure (``template``'s).

    Leaves of any dtype are stored as floats (bools and counters exactly) and cast back.
    ``pack``/``unpack`` are jittable; ``pack_np``/``unpack_np`` are their NumPy forms
    (``unpack_np`` of a stack of vectors, leading axis kept).
    """

    def __init__(self, template):
        leaves, self.treedef = jax.tree_util.tree_flatten(template)
        self.shapes = tuple(tuple(np.shape(x)) for x in leaves)
        self.dtypes = tuple(np.dtype(x.dtype if hasattr(x, "dtype") else type(x)) for x in leaves)
        self.sizes = tuple(int(np.prod(s, dtype=int)) for s in self.shapes)
        self.offsets = tuple(int(o) for o in np.cumsum((0, *self.sizes))[:-1])
        self.size = int(sum(self.sizes))

    def pack(self, tree, dtype) -> jax.Array:
        """(size,) vector of ``tree``'s leaves (jittable)."""
        leaves = self.treedef.flatten_up_to(tree)
        return jnp.concatenate([jnp.ravel(jnp.asarray(x)).astype(dtype) for x in leaves])

    def pack_np(self, tree, dtype=np.float64) -> np.ndarray:
        """NumPy form of :meth:`pack`."""
        leaves = self.treedef.flatten_up_to(tree)
        return np.concatenate([np.ravel(np.asarray(x)).astype(dtype) for x in leaves])

    def unpack(self, vec):
        """The pytree from a (size,) vector (jittable)."""
        parts = zip(self.offsets, self.sizes, self.shapes, self.dtypes, strict=True)
        return self.treedef.unflatten(
            [vec[o : o + n].reshape(s).astype(dt) for o, n, s, dt in parts]
        )

    def unpack_np(self, rows: np.ndarray):
        """The pytree of stacked leaves from (T, size) rows (NumPy)."""
        parts = zip(self.offsets, self.sizes, self.shapes, self.dtypes, strict=True)
        return self.treedef.unflatten(
            [rows[:, o : o + n].reshape((-1, *s)).astype(dt) for o, n, s, dt in parts]
        )


# The observation vector: TaskObs's fields (task axes x, z) and the time [s].
OBS_FIELDS = (
    ("q", (3,)),
    ("qd", (3,)),
    ("M", (3, 3)),
    ("h", (3,)),
    ("x_e", (2,)),
    ("xd_e", (2,)),
    ("J", (2, 3)),
    ("jdot_qdot", (2,)),
    ("f_int", (2,)),
    ("x_o", (2,)),
    ("xd_o", (2,)),
    ("t", ()),
)
_OBS_SLICES = {}
_start = 0
for _name, _shape in OBS_FIELDS:
    _n = int(np.prod(_shape, dtype=int))
    _OBS_SLICES[_name] = slice(_start, _start + _n)
    _start += _n
OBS_SIZE = _start
del _start, _name, _shape, _n
_XZ = np.array([0, 2])


def fill_observation(vec: np.ndarray, sample: PlantSample, arm) -> None:
    """Writes the observation of ``sample`` (with ``arm``, an
    :class:`~hec_jax.realtime.plant.ArmObs`) into ``vec`` (OBS_SIZE,) in place. The object's
    state is the plant's truth where it has it, else zeros (then only the eye's is used).
    """
    sl = _OBS_SLICES
    vec[sl["q"]] = sample.q
    vec[sl["qd"]] = sample.qd
    vec[sl["M"]] = arm.M.ravel()
    vec[sl["h"]] = arm.h
    vec[sl["x_e"]] = arm.x_e
    vec[sl["xd_e"]] = arm.xd_e
    vec[sl["J"]] = arm.J.ravel()
    vec[sl["jdot_qdot"]] = arm.jdot_qdot
    vec[sl["f_int"]] = sample.f_int[_XZ]
    vec[sl["x_o"]] = 0.0 if sample.x_o is None else sample.x_o
    vec[sl["xd_o"]] = 0.0 if sample.xd_o is None else sample.xd_o
    vec[sl["t"]] = sample.t


def fill_sample(vec: np.ndarray, sample: PlantSample) -> None:
    """Writes the plant sample's part of the observation (joint state, force, object truth, time)
    into ``vec`` in place; the arm's part comes from
    :meth:`~hec_jax.realtime.plant.ArmModel.observe` into :func:`arm_views` of ``vec``.
    """
    sl = _OBS_SLICES
    vec[sl["q"]] = sample.q
    vec[sl["qd"]] = sample.qd
    vec[sl["f_int"]] = sample.f_int[_XZ]
    vec[sl["x_o"]] = 0.0 if sample.x_o is None else sample.x_o
    vec[sl["xd_o"]] = 0.0 if sample.xd_o is None else sample.xd_o
    vec[sl["t"]] = sample.t


def arm_views(vec: np.ndarray) -> ArmObs:
    """:class:`~hec_jax.realtime.plant.ArmObs` of views into the observation vector ``vec``
    (``ArmModel.observe(q, qd, out=arm_views(vec))`` writes the arm's part in place).
    """
    sl = _OBS_SLICES
    return ArmObs(
        M=vec[sl["M"]].reshape(3, 3),
        h=vec[sl["h"]],
        J=vec[sl["J"]].reshape(2, 3),
        jdot_qdot=vec[sl["jdot_qdot"]],
        x_e=vec[sl["x_e"]],
        xd_e=vec[sl["xd_e"]],
    )


def unpack_observation(vec: jax.Array) -> tuple[TaskObs, jax.Array]:
    """(TaskObs, t [s]) from an observation vector (jittable)."""
    parts = {name: vec[_OBS_SLICES[name]].reshape(shape) for name, shape in OBS_FIELDS}
    t = parts.pop("t")
    return TaskObs(**parts), t


class StepFns(NamedTuple):
    """The jitted functions of the control path and the layouts of their flat vectors.

    Attributes:
        step: ``(ps_vec, sw_vec, obs_vec, steps_elapsed) -> (ps_vec, out_vec)``; ``out_vec``
            is the torques [N m] (3,) followed by the policy's logged signals (``aux``).
            ``ps_vec`` is donated (invalid after the call: use the returned one).
            ``steps_elapsed`` (a scalar of ``dtype``): physics steps since the previous call, 1
            but after skipped steps (``policy_obs``).
        init: ``(obs_vec, learner_state, switches) -> PolicyState`` at a release.
        ps: layout of the policy state without its switches.
        sw: layout of the :class:`~hec_jax.loop.policy.Switches`.
        aux: layout of the logged signals.
        dtype: the float type of the vectors.
    """

    step: Any
    init: Any
    ps: Flat
    sw: Flat
    aux: Flat
    dtype: Any


def make_step_fns(loop: Loop, learner_state, sw) -> StepFns:
    """Jitted ``step`` and ``init`` of ``loop`` for policy states like the one built from
    ``learner_state`` and switches ``sw`` (compiled on first call).
    """
    dtype = float_dtype()

    def init(obs_vec, ls, sw):
        obs, _ = unpack_observation(obs_vec.astype(dtype))
        return loop.initial_policy_state_obs(obs, ls, sw)

    obs0 = jnp.zeros(OBS_SIZE, dtype).at[_OBS_SLICES["M"]].set(jnp.eye(3, dtype=dtype).ravel())
    ps0 = jax.eval_shape(init, obs0, learner_state, sw)
    flat_ps = Flat(ps0._replace(switches=None))
    flat_sw = Flat(sw)

    def policy(ps_vec, sw_vec, obs_vec, steps_elapsed):
        obs, t = unpack_observation(obs_vec.astype(dtype))
        ps = flat_ps.unpack(ps_vec)._replace(switches=flat_sw.unpack(sw_vec))
        return loop.policy_obs(ps, obs, t, steps_elapsed.astype(dtype))

    _, _, aux0 = jax.eval_shape(
        policy,
        jnp.zeros(flat_ps.size, dtype),
        jnp.zeros(flat_sw.size, dtype),
        obs0,
        jnp.ones((), dtype),
    )
    flat_aux = Flat(aux0)

    def step(ps_vec, sw_vec, obs_vec, steps_elapsed):
        tau, ps, aux = policy(ps_vec, sw_vec, obs_vec, steps_elapsed)
        ps_vec = flat_ps.pack(ps._replace(switches=None), dtype)
        return ps_vec, jnp.concatenate([tau.astype(dtype), flat_aux.pack(aux, dtype)])

    # the policy state's buffer is donated: its successor is written into it (no allocation of
    # the 26 kB state per tick; the caller keeps only the returned one)
    return StepFns(
        jax.jit(step, donate_argnums=0), jax.jit(init), flat_ps, flat_sw, flat_aux, dtype
    )


# ---------------------------------------------------------------------------------------------
# The eye's estimates -> the policy's switches


def loop_switches(condition: str, with_eye: bool):
    """The policy's switches at the start of each of :func:`run_loop`'s episodes.

    ``condition``'s (:func:`hec_jax.loop.policy.switches`), with an empty eye input where the eye
    drives (``with_eye``; its estimates replace it as they arrive).
    """
    if with_eye:
        return switches(condition, jax.tree_util.tree_map(jnp.asarray, eye_input(None, 0.0, 0.0)))
    return switches(condition)


def episode_switches(sw_base, with_eye: bool, guard: float = 0.0, memory: float = 0.0):
    """The switches each of :func:`run_loop`'s episodes starts with: ``sw_base``
    (:func:`loop_switches`), with the eye's input emptied (no estimate yet; ``guard``,
    ``memory`` [s] as :func:`eye_timing`) where the eye drives.
    """
    return sw_base._replace(eye=eye_input(None, guard, memory)) if with_eye else sw_base


def ready_step_fns(loop: Loop, key: jax.Array, condition: str, with_eye: bool) -> StepFns:
    """:func:`make_step_fns` for :func:`run_loop`'s ``loop``, ``key`` and ``condition``, compiled.

    ``with_eye``: for a run with the eye's ``estimates``. ``init`` and ``step`` are called with
    the argument types :func:`run_loop` gives them, and the state's copy and unpacking run once,
    so that :func:`run_loop` given these functions compiles nothing. :func:`run_realtime` calls
    it before it sets the loop's scheduling: with ``pool_idle``, XLA's threads are under
    ``SCHED_IDLE`` there, and a compilation on a busy machine waited for idle CPUs
    (docs/realtime.md, session 78).
    """
    dtype = float_dtype()
    ls = loop.learner_init(key, dtype)
    sw = loop_switches(condition, with_eye)
    fns = make_step_fns(loop, ls, sw)
    obs = np.zeros(OBS_SIZE)  # a resting arm of unit mass matrix: only the types matter here
    obs[_OBS_SLICES["M"]] = np.eye(3).ravel()
    sw_np_dtype = np.dtype(fns.dtype)
    sw = episode_switches(sw, with_eye)  # the argument types of run_loop's init calls
    ps = fns.init(jnp.asarray(obs), ls, sw)
    ps_vec = jnp.asarray(fns.ps.pack_np(ps._replace(switches=None)), fns.dtype)
    sw_vec = fns.sw.pack_np(sw, sw_np_dtype)
    # run_loop's calls on the state around the step: its copies and the learner's unpacking
    ps_vec, _ = fns.step(jnp.array(ps_vec), sw_vec, obs, np.asarray(1.0, sw_np_dtype))
    jax.block_until_ready(fns.ps.unpack(ps_vec))
    return fns


def eye_timing(cam: CameraConfig, dt: float) -> tuple[float, float]:
    """(touch_guard, touch_memory) [s] of :class:`~hec_jax.loop.object_state.EyeInput`, as the
    simulated camera loop sets them.
    """
    period = steps_per_frame(cam, dt)
    guard = cam.touch_guard_frames * period * dt
    return guard, guard + cam.latency_s + cam.max_coast_frames * period * dt


def eye_input(estimate: dict | None, guard: float, memory: float) -> EyeInput:
    """The :class:`~hec_jax.loop.object_state.EyeInput` of the newest estimate (None or not
    seen: the object is unseen), used from its arrival on (NumPy).
    """
    z = np.zeros((2, 2))
    if estimate is None or not estimate["seen"] > 0:
        return EyeInput(1.0, 0.0, np.zeros(2), np.inf, z, z, z, guard, memory)
    t = float(estimate["t_stamp"])
    return EyeInput(
        use=1.0,
        seen=1.0,
        t_stamp=np.array([t, t]),
        t_switch=np.inf,
        x=np.stack([estimate["x"]] * 2),
        xd=np.stack([estimate["xd"]] * 2),
        xdd=np.stack([estimate["xdd"]] * 2),
        touch_guard=guard,
        touch_memory=memory,
    )


# ---------------------------------------------------------------------------------------------
# The loop


@dataclass
class LoopRun:
    """What :func:`run_loop` returns (NumPy).

    Attributes:
        logs: per episode, the simulated loops' log names (``x_e``, ``f_contact``, ``t``,
            ``qpos``, ...), one row per physics step (rows of steps without a controller call
            repeat the last call's signals).
        ticks: per episode, one row per physics step j: ``t_due``, ``t_wake``, ``t_obs``,
            ``t_step``, ``t_write`` [s] (clock times of the step the clock waited for, the
            wake-up, the observation ready, the jitted step done, the torques taken by the
            plant; NaN where the step had no tick; after a stall the plant catches up and
            returns a later sample than the one waited for, so ``t_due`` < j dt, and the
            wake-up may precede j dt), ``kind`` (plant: 0 fresh, 1 late, 2 skipped),
            ``t_stamp`` [s] (exposure of the eye's estimate in force, NaN: none); the control
            thread's CPU time [ns] of each stage, ``cpu_read`` (plant read), ``cpu_observe``
            (eye estimate, arm model, observation vector), ``cpu_step`` (the jitted call, its
            argument and result conversions), ``cpu_write`` (plant write; the MuJoCo plant
            integrates the physics step in it); ``cpu_other_threads`` [ns] the CPU time of the
            process's other threads meanwhile (XLA's pool threads running parts of the step);
            ``switches_voluntary`` / ``switches_involuntary``: the control thread's context
            switches during the tick's work (waits for XLA's threads / preemptions);
            ``faults_major`` / ``faults_minor``: the control thread's page faults from the
            previous tick's torques to this tick's (a major fault reads the page from disk:
            code or a mapped file the kernel had dropped).
        arrivals: per episode, one row per eye estimate taken: ``tick``, ``t_tick`` [s],
            ``t_stamp`` [s], ``frame``, ``number`` (in the episode; 0: the release frame,
            answered before the release), ``seen``, ``t_wall_exposure``, ``t_wall_done``,
            ``t_wall_taken`` [s] (monotonic), ``valid`` (the frame's own fit passed; else the
            filter's prediction).
        counts: per episode, the plant's :class:`~hec_jax.realtime.plant.PlantCounts`.
        learner: the learner state after the last episode.
        wall_s: per episode, the clock time of its ticks [s].
        rest_s: per episode, the rest before its lead [s] (``rt_budget_rest``; 0: none).
        origin_s: per episode, the monotonic clock time [s] of its time 0 (``ticks``' times
            and j dt are relative to it; the camera's and eye's wall times are absolute);
            0 for an un-timed clock.
    """

    logs: list = field(default_factory=list)
    ticks: list = field(default_factory=list)
    arrivals: list = field(default_factory=list)
    counts: list = field(default_factory=list)
    learner: Any = None
    wall_s: list = field(default_factory=list)
    rest_s: list = field(default_factory=list)
    origin_s: list = field(default_factory=list)


def run_loop(
    loop: Loop,
    plant: Plant,
    clock: Clock,
    key: jax.Array,
    condition: str,
    episode_steps: list[int],
    arm: ArmModel,
    estimates: Board | None = None,
    cam: CameraConfig | None = None,
    lead_s: float = 0.02,
    gc_off: bool = True,
    fns: StepFns | None = None,
    progress: bool = False,
    acquire_timeout_s: float = 10.0,
    rt_budget_rest: bool = True,
    step_marker: np.ndarray | None = None,
) -> LoopRun:
    """Episodes of the closed loop on ``plant`` at ``clock``'s ticks.

    Args:
        loop: the task's loop (:func:`~hec_jax.loop.policy.build_loop`).
        plant: the robot or its simulation (``begin_episode``/``start``/``read``/``write``).
        clock: :class:`~hec_jax.realtime.clock.WallClock` (real time) or
            :class:`~hec_jax.realtime.clock.FreeClock` (un-timed).
        key: PRNG key of the network initialisation.
        condition: "plain", "frozen" or "learned".
        episode_steps: control steps of each episode (swings, then the continuous run).
        arm: the controller's model of the arm.
        estimates: the eye's board (``workers.ESTIMATE_FIELDS``); None: the plant's object
            state (``--eye truth``).
        cam: the camera's settings (with ``estimates``).
        lead_s: [s] from the start of each episode's clock to tick 0.
        gc_off: no garbage collection during an episode.
        fns: the jitted functions (:func:`make_step_fns`; compiled: :func:`ready_step_fns`), to
            share across calls.
        progress: print one line per episode.
        acquire_timeout_s: [s] with the eye: before each release, how long to wait for its
            answer on the release frame (the cube held in view until the eye has it).
        rt_budget_rest: at real-time priority, sleep :func:`~.clock.rt_budget_rest_s` before
            each episode's lead (the kernel's real-time throttling then cannot stop its first
            ticks); recorded in :attr:`LoopRun.rest_s`.
        step_marker: each timed step's start (``time.monotonic_ns()``) is written to
            ``step_marker[0]`` before the jitted call and 0 after it
            (:class:`~hec_jax.realtime.clock.pool_rescue` watches it); None: nothing written.

    Raises:
        TimeoutError: the eye did not answer on a release frame in time.
    """
    dtype = float_dtype()
    dt = plant.dt
    ls = loop.learner_init(key, dtype)
    guard = memory = 0.0
    if estimates is not None:
        guard, memory = eye_timing(cam, dt)
    sw = loop_switches(condition, estimates is not None)
    fns = make_step_fns(loop, ls, sw) if fns is None else fns
    sw_base = sw
    n_tau = 3
    out = LoopRun()
    obs_np = np.zeros(OBS_SIZE)
    arm_out = arm_views(obs_np)
    for e, n in enumerate(episode_steps):
        plant.begin_episode(n)
        clock.start(3600.0)  # held: tick 0 an hour away while the episode is prepared
        plant.start(clock)
        s0 = plant.read()
        fill_observation(obs_np, s0, arm.observe(s0.q, s0.qd))
        sw = episode_switches(sw_base, estimates is not None, guard, memory)
        # the switches stay a NumPy vector, made anew at each estimate's arrival: the jitted
        # step takes it as it takes the observation (no extra cost per call), and an arrival
        # costs no device array (measured: 40 us hot, 3x that cold, on every 33rd tick)
        sw_np_dtype = np.dtype(fns.dtype)
        one_step = np.asarray(1.0, sw_np_dtype)
        sw_vec = fns.sw.pack_np(sw, sw_np_dtype)
        ps = fns.init(jnp.asarray(obs_np), ls, sw)
        ps_vec = jnp.asarray(fns.ps.pack_np(ps._replace(switches=None)), fns.dtype)
        for _ in range(20):  # compiled and warm before the clock runs (on copies: donated)
            np.asarray(fns.step(jnp.array(ps_vec), sw_vec, obs_np.copy(), one_step)[1])
        warm_obs = obs_np.copy()
        warm_views = arm_views(warm_obs)
        rec = {k: np.full(n, np.nan) for k in (*TICK_TIMES, *TICK_CPU)}
        rows = np.zeros((n, n_tau + fns.aux.size))
        ticked = np.zeros(n, bool)
        arrivals: list[tuple] = []
        seq = estimates.seq if estimates is not None else 0
        if estimates is not None:  # the cube held in view until the eye has answered on it

            def acquired(e=e):
                written, est = estimates.read()
                return written > 0 and int(est["episode"]) == e

            wait_for(acquired, acquire_timeout_s, 1e-3, f"the eye's release frame {e}")
            seq = -1  # its answer is taken at tick 0
        stamp = np.nan
        if gc_off:
            gc.collect()
            gc.disable()
        # the set-up above (at real-time priority: the eye's wait; in episode 0 without ready
        # fns, the step's compilation, seconds) may have used the kernel's real-time budget of
        # the current second; resting the rest of it here keeps the throttling's stop (up to
        # 50 ms) off the lead and the first ticks
        rest = rt_budget_rest_s() if rt_budget_rest else 0.0
        if rest > 0:
            time.sleep(rest)
        out.rest_s.append(rest)
        out.origin_s.append(clock.start(lead_s))
        # until shortly before tick 0, dry ticks (the arm model and the jitted step on copies of
        # the release sample) keep the tick's code and data in the caches: after the episode's
        # set-up and the lead's wait, the first tick took 2-10x the median (docs/realtime.md).
        # The plant, the policy state and the learning are not touched; un-timed: none.
        while clock.now() < -WARM_UNTIL_S:
            arm.observe(s0.q, s0.qd, warm_views)
            np.asarray(fns.step(jnp.array(ps_vec), sw_vec, warm_obs.copy(), one_step)[1])
        try:
            j = j_last = 0  # the policy state's previous sample: the release's, step 0
            u_prev = _rusage(_THREAD)  # tick 0's page faults count from here (after the lead)
            while j < n:
                t_due = j * dt  # the step the clock waits for; the plant may return a later one
                t_wake = clock.wait_until(t_due)
                c0, p0, u0 = _thread_ns(), _process_ns(), _rusage(_THREAD)
                s = plant.read()
                j = s.index
                if j >= n:
                    break
                c1 = _thread_ns()
                fresh = None
                if estimates is not None and estimates.seq != seq:
                    # never waits on the eye: a write in progress is read at the next tick
                    fresh = estimates.try_read()
                if fresh is not None:
                    seq, est = fresh
                    if int(est["episode"]) == e:
                        sw_vec = fns.sw.pack_np(
                            sw_base._replace(eye=eye_input(est, guard, memory)), sw_np_dtype
                        )
                        stamp = float(est["t_stamp"]) if est["seen"] > 0 else np.nan
                        arrivals.append(
                            (
                                j,
                                j * dt,
                                float(est["t_stamp"]),
                                float(est["frame"]),
                                float(est["number"]),
                                float(est["seen"]),
                                float(est["t_wall_exposure"]),
                                float(est["t_wall_done"]),
                                monotonic_s(),
                                float(est["valid"]),
                            )
                        )
                arm.observe(s.q, s.qd, arm_out)  # in place: the arm's part of obs_np
                fill_sample(obs_np, s)
                t_obs = clock.now()
                c2 = _thread_ns()
                # after skipped steps the accelerations' differences span the gap
                gap = one_step if j <= j_last + 1 else np.asarray(j - j_last, sw_np_dtype)
                if step_marker is not None:
                    step_marker[0] = time.monotonic_ns()
                ps_vec, row = fns.step(ps_vec, sw_vec, obs_np.copy(), gap)
                j_last = j
                row = np.asarray(row)
                if step_marker is not None:
                    step_marker[0] = 0
                t_step = clock.now()
                c3 = _thread_ns()
                t_write = plant.write(row[:n_tau])
                c4, p4, u4 = _thread_ns(), _process_ns(), _rusage(_THREAD)
                rows[j] = row
                ticked[j] = True
                rec["t_due"][j], rec["t_wake"][j], rec["t_obs"][j] = t_due, t_wake, t_obs
                rec["t_step"][j], rec["t_write"][j], rec["t_stamp"][j] = t_step, t_write, stamp
                rec["cpu_read"][j], rec["cpu_observe"][j] = c1 - c0, c2 - c1
                rec["cpu_step"][j], rec["cpu_write"][j] = c3 - c2, c4 - c3
                rec["cpu_other_threads"][j] = (p4 - p0) - (c4 - c0)
                rec["switches_voluntary"][j] = u4.ru_nvcsw - u0.ru_nvcsw
                rec["switches_involuntary"][j] = u4.ru_nivcsw - u0.ru_nivcsw
                rec["faults_major"][j] = u4.ru_majflt - u_prev.ru_majflt
                rec["faults_minor"][j] = u4.ru_minflt - u_prev.ru_minflt
                u_prev = u4
                j += 1
        finally:
            if gc_off:
                gc.enable()
        plog = plant.episode_log()
        counts = plant.counts
        # steps the controller never saw repeat the previous call's signals
        idx = np.maximum.accumulate(np.where(ticked, np.arange(n), -1))
        idx = np.where(idx < 0, int(np.argmax(ticked)), idx)
        aux = fns.aux.unpack_np(rows[idx, n_tau:])
        logs = dict(aux, f_contact=plog["f_contact"], t=plog["t"])
        logs.update(qpos=plog["qpos"], qvel=plog["qvel"], ctrl=plog["ctrl"])
        rec["kind"] = plog["kind"]
        out.logs.append(logs)
        out.ticks.append(rec)
        names = ("tick", "t_tick", "t_stamp", "frame", "number", "seen", "t_wall_exposure")
        names += ("t_wall_done", "t_wall_taken", "valid")
        arr = np.asarray(arrivals, float).reshape(-1, len(names))
        out.arrivals.append({k: arr[:, i] for i, k in enumerate(names)})
        out.counts.append(counts)
        out.wall_s.append(float(np.nanmax(rec["t_write"]) if ticked.any() else 0.0))
        ls = fns.ps.unpack(ps_vec).learner._replace(was_inside=jnp.asarray(False))
        if progress:
            late = counts.late + counts.skipped
            print(
                f"  episode {e}: {n} steps, {late} missed, "
                f"{len(arrivals)} eye estimates, {time.strftime('%H:%M:%S')}",
                flush=True,
            )
    out.learner = ls
    return out


def stack_episodes(loop: Loop, run: LoopRun) -> dict:
    """The loop's episodes as the simulated runs' logs: arrays (1, swings, steps, ...) and, with
    a continuous run, ``final`` (1, 1, final_steps, ...).
    """
    swings = loop.config.swings
    logs = {k: np.stack([lg[k] for lg in run.logs[:swings]])[None] for k in run.logs[0]}
    if len(run.logs) > swings:
        logs["final"] = {k: v[None, None] for k, v in run.logs[swings].items()}
    return logs


# ---------------------------------------------------------------------------------------------
# The eye's process


class EyeProcess:
    """The eye in its own process (:func:`~hec_jax.realtime.workers.eye_main`), publishing to
    :attr:`estimates`.

    Args:
        task: the task (the robot's geometry for its self-mask).
        cam: the camera settings.
        camera: the plant's camera (``MujocoPlant.camera()``).
        dt: [s] control period.
        q0: (nq,) qpos at the release (warm-up frame's arm posture).
        priority: SCHED_FIFO priority once ready (0: normal scheduling).
        nice: the eye process's nice value.
        skip_unseen: the tracker predicts over frame times it never saw (``BoxTracker.skip``).
        gc_off: no Python garbage collection while an episode runs (collected at each release
            frame, which the loop waits for anyway).
        save_failed: keep up to this many frames whose tracked fit failed, for an offline
            replay (:func:`~hec_jax.realtime.workers.failed_frame_record`; the log's
            ``failed_frames``).
    """

    def __init__(
        self,
        task,
        cam: CameraConfig,
        camera,
        dt: float,
        q0,
        priority: int = 0,
        nice: int = 0,
        skip_unseen: bool = True,
        gc_off: bool = False,
        save_failed: int = 0,
    ):
        from hec_jax.realtime.plant import _child_env

        self.estimates = Board(workers.ESTIMATE_FIELDS)
        self._ready, self._stop, self._log = _CTX.Event(), _CTX.Event(), _CTX.Queue()
        self._last_words = None  # the message of an eye that died (taken by wait_ready)
        fps = 1.0 / (steps_per_frame(cam, dt) * dt)
        cache = jax.config.jax_compilation_cache_dir
        with _child_env():
            self.proc = _CTX.Process(
                target=workers.eye_main,
                args=(task, cam, fps, q0, camera, self.estimates, jax.config.jax_enable_x64, cache),
                kwargs=dict(
                    ready=self._ready,
                    stop=self._stop,
                    log_queue=self._log,
                    priority=priority,
                    nice=nice,
                    skip_unseen=skip_unseen,
                    gc_off=gc_off,
                    save_failed=save_failed,
                ),
                daemon=True,
                name="hec-eye",
            )
            self.proc.start()

    def wait_ready(self, timeout_s: float) -> None:
        """Waits until the eye has compiled its tracker.

        Raises:
            RuntimeError: the eye process died (its traceback in the message).
        """

        def ok():
            if not self.proc.is_alive():
                try:  # kept for close(), which would otherwise wait for it in vain
                    self._last_words = self._log.get(timeout=5)
                except queue.Empty:
                    self._last_words = {"error": "nothing (it died before it could say why)"}
                raise RuntimeError(f"the eye process died: {self._last_words}")
            return self._ready.is_set()

        wait_for(ok, timeout_s, 0.05, "the eye process")

    def close(self) -> dict | None:
        """Stops the eye; returns its per-frame log (what it said before it died, if it did)."""
        if self.proc is None:
            return None
        self._stop.set()
        log = self._last_words
        if log is None:
            # while it runs it gets 60 s to send its log; a dead one has sent all it will
            for _ in range(600):
                try:
                    log = self._log.get(timeout=0.1)
                    break
                except queue.Empty:
                    if not self.proc.is_alive():
                        try:
                            log = self._log.get(timeout=0.5)  # sent just before it ended
                        except queue.Empty:
                            log = None
                        break
        self.proc.join(timeout=10)
        if self.proc.is_alive():
            self.proc.terminate()
        self.proc = None
        return log


# ---------------------------------------------------------------------------------------------
# An experiment in real time


@dataclass
class RealtimeResult:
    """What :func:`run_realtime` returns.

    Attributes:
        config: the experiment as run (one seed; swings from ``duration_s``).
        realtime: the real-time settings.
        logs: the run's logs (arrays (1, swings, steps, ...), as the simulated runs').
        metrics: the task's metrics of the run's condition.
        report: the deadline report (:func:`~hec_jax.realtime.report.deadline_report`).
        twins: {"truth" | "camera": {"logs", "metrics", "wall_s"}}: the same run in simulated
            time.
        comparison: {twin: real-time / simulated metric ratios}.
        loop_run: the raw records (:class:`LoopRun`).
        camera_log, eye_log: the camera's and the eye's per-frame logs (None without camera).
        load: ``os.getloadavg()`` before and after the real-time part.
        dt: [s] control period.
        eye_failed_frames: the eye's saved failed frames (``RealtimeConfig.eye_save_failed``;
            :func:`~hec_jax.realtime.workers.failed_frames_file`); None: not saved.
    """

    config: ExperimentConfig
    realtime: RealtimeConfig
    logs: dict
    metrics: dict
    report: dict
    twins: dict
    comparison: dict
    loop_run: LoopRun
    camera_log: dict | None
    eye_log: dict | None
    load: dict
    dt: float
    eye_failed_frames: dict | None = None


def realtime_experiment(exp: ExperimentConfig, rt: RealtimeConfig) -> ExperimentConfig:
    """``exp`` as the real-time loop runs it: one seed; swings from ``rt.duration_s``; the
    camera's tracker with ``rt.eye_local_starts``, ``rt.eye_local_keep``,
    ``rt.eye_local_merge``, ``rt.eye_defer_search`` and ``rt.eye_small_kernels``, without its
    manoeuvre restart unless ``rt.eye_maneuver_restart``; the camera's multisampling
    ``rt.camera_msaa`` and planes' grid ``rt.camera_plane_grid_m`` where given.
    The simulated twin runs the same, so that its camera loop sees frames rendered as the
    real-time camera renders them.
    """
    task = exp.task
    if rt.duration_s is not None:
        swings = max(int(math.ceil(rt.duration_s / task.swing_s - 1e-9)), 1)
        task = dataclasses.replace(task, swings=swings)
    track = dataclasses.replace(
        exp.camera.tracker,
        local_starts=rt.eye_local_starts,
        local_keep=rt.eye_local_keep,
        local_merge=float(rt.eye_local_merge),
        defer_search=rt.eye_defer_search,
        cpu_small_kernels=rt.eye_small_kernels,
    )
    if not rt.eye_maneuver_restart:
        track = dataclasses.replace(track, maneuver_nis=None)
    cam = dataclasses.replace(exp.camera, track=track)
    if rt.camera_msaa is not None:
        cam = dataclasses.replace(cam, msaa=rt.camera_msaa)
    if rt.camera_plane_grid_m is not None:
        cam = dataclasses.replace(cam, plane_grid_m=float(rt.camera_plane_grid_m))
    return dataclasses.replace(exp, task=task, seeds=1, camera=cam)


def void_camera_experiment(
    preset: str, seed: int, width: int, height: int, msaa: int | None, rt: RealtimeConfig
) -> ExperimentConfig:
    """``preset`` (a :data:`~hec_jax.loop.config.PRESETS` name) driven by the camera in the void
    scene without defects (``CameraConfig.void_perfect`` at ``width`` x ``height`` [px],
    ``msaa``), as the real-time loop runs it with ``rt`` (:func:`realtime_experiment`): the
    set-up the benchmarks replay the real-time eye on.
    """
    cam = CameraConfig.void_perfect(width=width, height=height, msaa=msaa)
    return realtime_experiment(PRESETS[preset](camera=cam, eye="camera", seed=seed), rt)


def twin_camera_latency_s(latency_p50_s: float, cam: CameraConfig, dt: float) -> float:
    """[s] The ``CameraConfig.latency_s`` that gives the simulated camera loop the real-time
    eye's latency.

    ``latency_p50_s`` is the real-time run's median, over the estimates taken after the
    release, of the time from a frame's exposure (the plant time of the state it shows,
    mid-exposure) to the tick that first used its estimate (``deadline.json``'s
    ``eye.latency_ms``). The simulated loop counts its latency from the exposure's end (its
    estimate is used from the first control step at or after ``s dt + latency_s``, the frame
    showing step ``s - e``, ``e`` half the exposure in whole steps:
    :func:`hec_jax.loop.camera_loop.exposure_offsets`). So the median is taken in whole steps
    (halves up), ``e`` is subtracted, and the latency is set half a step short of that step
    (at least 0): the loop's time is a running sum of steps, and an arrival exactly on a step
    would be used at that step or the next by its round-off.
    """
    if not (math.isfinite(latency_p50_s) and latency_p50_s >= 0):
        raise ValueError(f"latency_p50_s must be finite and >= 0, got {latency_p50_s}")
    half_exposure = mid_exposure_steps(cam, dt)
    steps = int(math.floor(latency_p50_s / dt + 0.5)) - half_exposure
    return max(steps - 0.5, 0.0) * dt


def simulated_twins(exp: ExperimentConfig, loop: Loop, condition: str, which: str, progress=True):
    """The same run in simulated time: {"truth": MJX episodes with the simulator's object
    state, "camera": the simulated camera loop with ``exp.camera`` (``which`` "auto" and a
    camera run; its entry also holds ``latency_s``, the camera's)}, each {"logs", "metrics",
    "wall_s"}.
    """
    out = {}
    if which == "none":
        return out
    conditions = exp.task.pendulum.conditions()
    keys = jax.random.split(jax.random.PRNGKey(exp.seed), 1)
    t0 = time.perf_counter()
    logs = make_episodes(loop)(keys, switches(condition), conditions)
    logs = jax.tree_util.tree_map(np.asarray, jax.block_until_ready(logs))
    out["truth"] = {
        "logs": logs,
        "metrics": condition_metrics(loop, logs, condition),
        "wall_s": time.perf_counter() - t0,
    }
    if which == "auto" and exp.eye == "camera":
        t0 = time.perf_counter()
        logs, _, _ = run_camera(loop, conditions, keys, condition, exp.camera, progress=progress)
        out["camera"] = {
            "logs": logs,
            "metrics": condition_metrics(loop, logs, condition),
            "wall_s": time.perf_counter() - t0,
            "latency_s": exp.camera.latency_s,
        }
    return out


def run_realtime(
    exp: ExperimentConfig, rt: RealtimeConfig | None = None, progress: bool = True
) -> RealtimeResult:
    """``exp`` (its task, eye and camera; one seed) in real time on a MuJoCo C plant, its
    deadline report, and the same run in simulated time.

    Args:
        exp: the experiment (e.g. ``hec_jax.loop.catching(eye="camera",
            camera=CameraConfig.void_perfect())``: the real-time camera).
        rt: the real-time settings (default :class:`~hec_jax.realtime.config.RealtimeConfig`).
        progress: print one line per episode.

    Raises:
        ValueError: un-timed mode with the camera (the camera loop in simulated time is
            :func:`hec_jax.loop.run_camera`); ``eye="paper"``; with ``eye="camera"``, camera
            defects or a trigger phase (simulated time only: ``CameraConfig.realtime_refused``);
            ``rt.pool_idle`` where it could not be undone
            (:func:`~hec_jax.realtime.clock.pool_idle_refused`).
    """
    rt = RealtimeConfig() if rt is None else rt
    exp = realtime_experiment(exp, rt)
    if exp.eye == "paper":
        raise ValueError("the real-time eye is the box tracker: eye='truth' or 'camera'")
    if exp.eye == "camera" and not rt.timed:
        raise ValueError("un-timed mode runs with eye='truth' (simulated camera: loop.run_camera)")
    # the camera (unused with the truth eye) has no defects and no trigger phase in real time
    refused = exp.camera.realtime_refused() if exp.eye == "camera" else None
    if refused:
        raise ValueError(refused)
    refused = pool_idle_refused(rt.pool_idle_applies)
    if refused:
        raise ValueError(refused)
    task = exp.task
    loop = build_loop(task)
    key = jax.random.split(jax.random.PRNGKey(exp.seed), 1)[0]
    cam = exp.camera if exp.eye == "camera" else None
    episodes = [loop.swing_steps] * task.swings + ([loop.final_steps] if loop.final_steps else [])
    arm = ArmModel(plant_model(task), loop.ids)
    eye = None
    load = {"before": os.getloadavg()}
    nice = rt.child_nice if rt.timed else 0
    control_cpus = None
    with MujocoPlant(
        task,
        loop.q_home,
        cam,
        True,
        rt.camera_priority,
        nice,
        rt.camera_msaa,
        rt.camera_shadows,
    ) as plant:
        try:
            if cam is not None:
                plant.wait_camera(rt.startup_timeout_s)
                eye = EyeProcess(
                    task,
                    cam,
                    plant.camera(),
                    plant.dt,
                    plant.q_release,
                    rt.eye_priority,
                    nice,
                    rt.eye_skips_unseen,
                    rt.gc_off and rt.timed,
                    rt.eye_save_failed,
                )
                eye.wait_ready(rt.startup_timeout_s)
            children: dict = {}
            control_cpus = (
                _pin_children(plant, eye, children, rt.eye_on_control_cpu)
                if rt.pin_cpus and rt.timed
                else None
            )
            clock = WallClock(rt.spin_us * 1e-6) if rt.timed else FreeClock()
            # compiled here, at the process's own scheduling on every CPU: under the loop's
            # (below) XLA's threads may be under SCHED_IDLE, and on a busy machine the
            # compilation then waited for idle CPUs (docs/realtime.md, session 78)
            t_ready = time.monotonic()
            fns = ready_step_fns(loop, key, rt.condition, eye is not None)
            ready_s = time.monotonic() - t_ready
            load["start"] = os.getloadavg()
            steal_start = host_steal_ms()
            latency = cpu_latency_request(rt.cpu_latency_us if rt.timed else None)
            # pool_idle where it applies (the condition checked above) and the CPUs got pinned
            priority = realtime_priority(
                rt.rt_priority if rt.timed else 0, rt.pool_idle_applies and control_cpus is not None
            )
            others = set(os.sched_getaffinity(0)) - (control_cpus or set())
            filler = idle_filler(rt.idle_filler if control_cpus else None, others)
            rescue = None
            with filler, pinned(control_cpus), priority, latency, contextlib.ExitStack() as stack:
                if priority.pool_idle:  # its watchdog on the other CPUs, as nice as the children
                    rescue = stack.enter_context(
                        pool_rescue(
                            priority.idle_threads,
                            rt.pool_rescue_us,
                            rt.pool_rescue_poll_us,
                            others,
                            nice,
                        )
                    )
                run = run_loop(
                    loop,
                    plant,
                    clock,
                    key,
                    rt.condition,
                    episodes,
                    arm,
                    None if eye is None else eye.estimates,
                    cam,
                    rt.lead_ms * 1e-3,
                    rt.gc_off,
                    progress=progress,
                    acquire_timeout_s=rt.acquire_timeout_s,
                    rt_budget_rest=rt.rt_budget_rest,
                    step_marker=None if rescue is None else rescue.marker,
                    fns=fns,
                )
            load["end"] = os.getloadavg()
            steal_end = host_steal_ms()
        finally:
            eye_log = eye.close() if eye is not None else None
            camera_log = plant.close()
    for name, log in (("eye", eye_log), ("camera", camera_log)):
        if isinstance(log, dict) and "error" in log:
            raise RuntimeError(f"the {name} process failed:\n{log['error']}")
    failed_frames = eye_log.pop("failed_frames", None) if eye_log else None
    logs = stack_episodes(loop, run)
    metrics = condition_metrics(loop, logs, rt.condition)
    fps = None if cam is None else 1.0 / (steps_per_frame(cam, plant.dt) * plant.dt)
    report = deadline_report(run, plant.dt, fps, camera_log, eye_log)
    report["timed"] = rt.timed
    # [s] the jitted step's compilation and first calls, before the loop's scheduling was set
    report["step_fns_ready_s"] = ready_s
    report["placement"] = {  # where the control process's threads ran
        "control_cpus": None if control_cpus is None else sorted(control_cpus),
        **children,
        "cpus": os.cpu_count(),
        "rt_priority": rt.rt_priority if rt.timed else 0,
        # the other threads under SCHED_IDLE while the loop ran (with rt_priority 0)
        "pool_idle": priority.pool_idle,
        # its watchdog (clock.pool_rescue): settings, rescues, time rescued (None: none ran)
        "pool_rescue": None if rescue is None else rescue.summary,
        # the CPUs' wake-up latency asked of the kernel while the loop ran (None: nothing)
        "cpu_latency_us": rt.cpu_latency_us if rt.timed else None,
        # the other CPUs kept busy at SCHED_IDLE while the loop ran (None: not)
        "idle_filler": rt.idle_filler if control_cpus else None,
        # [s] the control thread's rest before each episode's lead (the real-time budget's)
        "rt_budget_rest_s": max(run.rest_s, default=0.0),
        # JAX's CPU dispatch as configured (it takes effect when JAX creates its CPU client)
        "jax_cpu_async_dispatch": bool(jax.config.values["jax_cpu_enable_async_dispatch"]),
    }
    # [ms] per CPU: the time the machine's host took from each CPU while the loop ran (a VM's
    # steal; None: not accounted)
    steal = (
        np.subtract(steal_end, steal_start).tolist() if len(steal_end) == len(steal_start) else []
    )
    report["host"] = {"steal_ms_per_cpu": steal or None}
    if not rt.timed:  # no clock: latencies are not wall times, no timing target applies
        report["targets"] = {}
    twin_exp = exp
    measured = (report.get("eye") or {}).get("latency_ms", {})
    if rt.twin_latency == "measured" and cam is not None and measured.get("n", 0) > 0:
        twin_latency_s = twin_camera_latency_s(1e-3 * measured["p50"], cam, plant.dt)
        twin_cam = dataclasses.replace(cam, latency_s=twin_latency_s)
        twin_exp = dataclasses.replace(exp, camera=twin_cam)
    twins = simulated_twins(twin_exp, loop, rt.condition, rt.twin, progress)
    if "camera" in twins:
        twins["camera"]["latency_source"] = (
            "measured"
            if twin_exp is not exp
            else "configured (no estimate measured)"
            if rt.twin_latency == "measured"
            else "configured"
        )
    scales = {"settle_force": task.learner.f_desired}  # [N] F_cd: the settle force's scale
    comparison = {k: compare_metrics(metrics, v["metrics"], 0.2, scales) for k, v in twins.items()}
    return RealtimeResult(
        exp,
        rt,
        logs,
        metrics,
        report,
        twins,
        comparison,
        run,
        camera_log,
        eye_log,
        load,
        plant.dt,
        failed_frames,
    )


def _pin_children(
    plant: MujocoPlant, eye: EyeProcess | None, where: dict, eye_on_control_cpu: bool = False
) -> set[int] | None:
    """The camera's and the eye's processes (all their threads) on every CPU but the first (with
    three or more: the camera on the second, the eye on the others); returns the first, for the
    control loop's process (:class:`~.clock.pinned`). None on a single CPU. ``where`` receives
    the CPUs of each child process (``camera_cpus``, ``eye_cpus``). ``eye_on_control_cpu``: the
    eye's CPUs include the first (``RealtimeConfig.eye_on_control_cpu``).
    """
    cpus = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
    if len(cpus) < 2:
        return None
    rest = set(cpus[1:])
    # with three CPUs or more the camera gets the second to itself and the eye the rest (the
    # renderer's and the tracker's bursts then never wait for each other); else both share
    camera_cpus, eye_cpus = ({cpus[1]}, set(cpus[2:])) if len(cpus) >= 3 else (rest, rest)
    if eye_on_control_cpu:
        eye_cpus = eye_cpus | {cpus[0]}
    for name, proc, cpu_set in (
        ("camera_cpus", plant._camera_proc, camera_cpus),
        ("eye_cpus", eye and eye.proc, eye_cpus),
    ):
        if proc is not None:
            pin_process(proc.pid, cpu_set)
            where[name] = sorted(cpu_set)
    return {cpus[0]}
