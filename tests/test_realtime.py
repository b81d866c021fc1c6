"""The real-time loop (``hec_jax.realtime``): the plant interface against the simulated loops, the
plant's deadline bookkeeping, and short real-time runs that check their own deadline reports.

Oracles:

* Un-timed, the loop on :class:`~hec_jax.realtime.MujocoPlant` must be the simulated MuJoCo C
  loop: :func:`hec_jax.mjx_scene.rollout_c` (the reference C step sequence, tested against MJX in
  ``test_control_closed_loop``) with the observation of :func:`hec_jax.loop.observe_c` on the
  plant's own data and the loop's policy step (``Loop.policy_obs``, the function the MJX loop runs
  after ``observe``). Same physics calls, same policy function; what differs is the plumbing under
  test (the robot-side interface: joint state in, torques out; the controller's own arm model;
  the flat vectors at the jit boundary; episodes and weights carried over). The only possible
  difference is XLA compiling the flat-vector step with another operation order: round-off, so
  the tolerance is 1e-10 (measured: bit-identical), through contact and learning.
* Against the MJX episodes (``slow``): MuJoCo C and MJX differ by solver details in contact; the
  tolerance is ``test_control_closed_loop``'s for MJX vs C with contact (1e-7 m), with learning
  on.
* Timed runs assert no timing target (flaky on shared CPUs): they check that the report is
  consistent with the recorded tick times. The targets are measured by ``experiments/realtime.py``
  (docs/realtime.md).
"""

import dataclasses
import json
import os
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hec_jax import loop as L
from hec_jax import realtime as RT
from hec_jax.loop.observation import observe_c
from hec_jax.mjx_scene import c_quantities, make_data_c, rollout_c
from hec_jax.realtime.report import tick_table
from hec_jax.realtime.runner import float_dtype
from hec_jax.realtime.shared import Board, FrameRing

SWINGS, SWING_S = 2, 0.5  # the cube touches the hand at ~0.34 s of each swing


def _task():
    return L.replace(L.catching(eye="truth", seeds=1), swings=SWINGS, swing_s=SWING_S, settle_s=0.3)


@pytest.fixture(scope="module")
def untimed():
    """Two learned swings un-timed on the C plant (eye truth)."""
    exp = _task()
    loop = L.build_loop(exp.task)
    key = jax.random.split(jax.random.PRNGKey(0), 1)[0]
    plant = RT.MujocoPlant(exp.task, loop.q_home)
    arm = RT.ArmModel(RT.plant_model(exp.task), loop.ids)
    steps = [loop.swing_steps] * SWINGS
    run = RT.run_loop(loop, plant, RT.FreeClock(), key, "learned", steps, arm)
    return exp, loop, key, run


def test_untimed_loop_is_the_simulated_c_loop(untimed):
    exp, loop, key, run = untimed
    ids, c = loop.ids, exp.task.pendulum.conditions()
    m = RT.plant_model(exp.task)
    policy, init = jax.jit(loop.policy_obs), jax.jit(loop.initial_policy_state_obs)
    sw = L.switches("learned")
    ls = loop.learner_init(key, jnp.float64)

    def c_policy(ps, m_, d, cq, f_int, t):
        tau, ps, aux = policy(ps, observe_c(ids, d.qpos, d.qvel, cq, f_int), t)
        return np.asarray(tau), ps, jax.tree_util.tree_map(np.asarray, aux)

    peak = 0.0
    for swing in range(SWINGS):
        d = make_data_c(m, ids, c, np.asarray(loop.q_home))
        ps = init(observe_c(ids, d.qpos, d.qvel, c_quantities(m, d, ids), np.zeros(3)), ls, sw)
        ps, ref = rollout_c(m, ids, d, c_policy, ps, np.zeros((loop.swing_steps, 3)), c)
        ls = ps.learner._replace(was_inside=jnp.asarray(False))
        got = run.logs[swing]
        f_peak = np.abs(ref["f_contact"]).max()
        peak = max(peak, f_peak)
        for key_ in ("qpos", "qvel", "ctrl"):
            np.testing.assert_allclose(got[key_], ref[key_], rtol=1e-10, atol=1e-10, err_msg=key_)
        np.testing.assert_allclose(got["f_contact"], ref["f_contact"], atol=1e-10 * f_peak)
        for key_ in ("x_e", "k_o", "b_o", "f_o", "energy"):
            want = np.stack([a[key_] for a in ref["aux"]])
            np.testing.assert_allclose(got[key_], want, rtol=1e-10, atol=1e-10, err_msg=key_)
        diff = np.abs(got["qpos"] - ref["qpos"]).max()
        print(f"swing {swing}: max |qpos| diff {diff:.1e}, peak force {f_peak:.0f} N")
        assert run.counts[swing] == (loop.swing_steps, loop.swing_steps, 0, 0)
    assert peak > 50.0  # the comparison covers contact
    assert np.any(run.logs[1]["learning"])  # ... and learning, weights carried over


def _at_the_release(untimed):
    """(exp, loop, the observation at the release (MuJoCo C), the learner's initial state)."""
    exp, loop, key, _ = untimed
    ids, c = loop.ids, exp.task.pendulum.conditions()
    m = RT.plant_model(exp.task)
    d = make_data_c(m, ids, c, np.asarray(loop.q_home))
    obs = observe_c(ids, d.qpos, d.qvel, c_quantities(m, d, ids), np.zeros(3))
    return exp, loop, obs, loop.learner_init(key, jnp.float64)


def test_the_logged_margins_are_those_of_the_impedance_applied(untimed):
    """The policy logs the strict Eq. 49 margins of the virtual impedance it applied: a fixed
    one in place of the networks (the paper protocol's fixed arms), zero for plain impedance,
    the networks' own in the frozen condition. Until 2026-12-04 it logged the networks' margins
    in all three, so the fixed and plain arms' stability summaries described the wrong
    impedance. The state: the release, the cube inside the sphere (seen)."""
    from hec_jax.nets import stability_margins

    exp, loop, obs, ls = _at_the_release(untimed)
    imp = exp.task.impedance
    fixed = jnp.array([[-5.0, -1.0, -0.2], [3.0, 0.5, 0.1]])  # (K_o, B_o, M_o) per axis
    for sw, applied in (
        (L.switches("frozen", fixed=fixed), lambda aux: fixed),
        (L.switches("plain"), lambda aux: jnp.zeros((2, 3))),
        (L.switches("frozen"), lambda aux: jnp.stack([aux["k_o"], aux["b_o"], aux["m_o"]], -1)),
    ):
        ps = jax.jit(loop.initial_policy_state_obs)(obs, ls, sw)
        _, _, aux = jax.jit(loop.policy_obs)(ps, obs, 0.0)
        want = stability_margins(applied(aux), imp.m_e, imp.b_e, imp.k_e)
        np.testing.assert_allclose(aux["margins"], want, rtol=1e-12, atol=1e-12)
        assert not np.allclose(aux["k_o"], 0.0) or sw.use_virtual == 0  # the case is not void


def test_a_gap_of_steps_spans_the_accelerations_and_not_the_learning_step(untimed):
    """After skipped steps the policy's and the controller's backward differences (X_e'', X_o'')
    span the gap: the policy over a gap of 3 steps equals the one-step policy from a state whose
    previous velocities lie a third of the way back (the same accelerations, by construction);
    the learner's sampling interval stays one step in both. The state: the release, the cube
    inside the virtual sphere (F_o has a mass term); the velocities 3 steps on are made up."""
    exp, loop, obs0, ls = _at_the_release(untimed)
    ps = jax.jit(loop.initial_policy_state_obs)(obs0, ls, L.switches("learned"))
    toward = (obs0.x_e - obs0.x_o) / jnp.linalg.norm(obs0.x_e - obs0.x_o)  # the cube approaching
    obs = obs0._replace(
        xd_e=obs0.xd_e + jnp.array([0.03, -0.02]),
        xd_o=obs0.xd_o + 0.06 * toward + jnp.array([0.01, -0.02]),
    )
    policy = jax.jit(loop.policy_obs)
    tau3, ps3, aux3 = policy(ps, obs, 3e-3, jnp.asarray(3.0))
    cs = ps.controller
    third = cs._replace(
        xd_e_prev=obs.xd_e - (obs.xd_e - cs.xd_e_prev) / 3.0,
        xd_o_prev=obs.xd_o - (obs.xd_o - cs.xd_o_prev) / 3.0,
    )
    tau1, ps1, aux1 = policy(ps._replace(controller=third), obs, 3e-3)
    assert bool(aux1["inside"]) and bool(aux1["learning"])  # the case covers the learning step
    np.testing.assert_allclose(tau3, tau1, rtol=1e-9, atol=1e-12)
    for name in ("f_o", "k_o", "b_o", "m_o", "energy"):
        np.testing.assert_allclose(aux3[name], aux1[name], rtol=1e-9, atol=1e-12, err_msg=name)
    for a, b in zip(jax.tree.leaves(ps3.learner), jax.tree.leaves(ps1.learner), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12)
    after, before = jax.tree.leaves(ps1.learner.params), jax.tree.leaves(ps.learner.params)
    moved = max(  # the learning step moved the weights well past that tolerance
        float(np.max(np.abs(np.asarray(a) - np.asarray(b))))
        for a, b in zip(after, before, strict=True)
    )
    assert moved > 1e-8, moved
    # the gap matters here: the same state read as one step gives another virtual force
    _, _, aux_one = policy(ps, obs, 3e-3)
    assert np.max(np.abs(np.asarray(aux_one["f_o"]) - np.asarray(aux3["f_o"]))) > 1e-3


class _StallingClock(RT.FreeClock):
    """Un-timed, but the wait for ``at`` [s] returns at ``until`` [s] (a stall of the loop)."""

    def __init__(self, at, until):
        super().__init__()
        self.at, self.until = at, until

    def wait_until(self, t):
        return super().wait_until(self.until if abs(t - self.at) < 1e-9 else t)


def test_the_loop_gives_the_policy_the_steps_a_stall_skipped():
    """A stall from tick 5 to 8.1 ms: the plant integrates steps 5-7 with the held torques and
    the loop's next call (step 8) is told 4 steps passed; every other call, 1."""
    exp = _task()
    loop = L.build_loop(exp.task)
    key = jax.random.split(jax.random.PRNGKey(0), 1)[0]
    plant = RT.MujocoPlant(exp.task, loop.q_home)
    arm = RT.ArmModel(RT.plant_model(exp.task), loop.ids)
    sw = L.switches("learned")
    fns = RT.make_step_fns(loop, loop.learner_init(key, float_dtype()), sw)
    gaps, marks = [], []
    marker = np.full(4, -1, np.int64)  # what pool_rescue's watchdog reads

    def step(ps_vec, sw_vec, obs_vec, steps_elapsed):
        gaps.append(float(steps_elapsed))
        marks.append(int(marker[0]))
        return fns.step(ps_vec, sw_vec, obs_vec, steps_elapsed)

    clock = _StallingClock(5e-3, 8.1e-3)
    run = RT.run_loop(
        loop,
        plant,
        clock,
        key,
        "learned",
        [20],
        arm,
        fns=fns._replace(step=step),
        step_marker=marker,
    )
    ticks = gaps[-(20 - 3) :]  # the last 17 calls: the ticks (before them, the warm-up's)
    assert ticks == [1.0] * 5 + [4.0] + [1.0] * 11
    # each tick's call began with its start on the marker, cleared after it; warm-up calls: none
    assert marks[: -(20 - 3)] == [-1] * (len(marks) - 17) and marker[0] == 0
    assert min(marks[-17:]) > 0 and np.all(np.diff(marks[-17:]) > 0)
    np.testing.assert_array_equal(run.ticks[0]["kind"][5:8], 2)  # skipped
    assert run.counts[0].skipped == 3
    # the tick after the stall waited for step 5 and woke at 8.1 ms; the others for their own
    due = run.ticks[0]["t_due"]
    assert due[8] == pytest.approx(5e-3) and run.ticks[0]["t_wake"][8] >= 8.1e-3
    np.testing.assert_allclose(
        np.delete(due, [5, 6, 7, 8]), np.delete(np.arange(20), [5, 6, 7, 8]) * 1e-3
    )


def test_the_step_is_compiled_before_the_loops_scheduling_is_set(monkeypatch):
    """run_realtime compiles the jitted step before it sets the loop's scheduling (where, with
    pool_idle, XLA's threads are under SCHED_IDLE and a compilation on a busy machine waited for
    idle CPUs): JAX traces and compiles nothing inside that block, and the functions
    ready_step_fns returns leave run_loop nothing to compile."""
    from hec_jax.realtime import runner

    inside = {"now": False, "events": []}

    def listen(event, duration_s, **kwargs):
        if inside["now"] and event.startswith("/jax/core/compile/"):
            inside["events"].append(event)

    class _Watched(runner.realtime_priority):
        def __enter__(self):
            inside["now"] = True
            return super().__enter__()

        def __exit__(self, *exc):
            inside["now"] = False
            return super().__exit__(*exc)

    monkeypatch.setattr(runner, "realtime_priority", _Watched)
    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        exp = L.replace(L.catching(eye="truth"), swings=1, settle_s=0.1, swing_s=0.2)
        result = RT.run_realtime(exp, RT.RealtimeConfig(timed=False, twin="none"), False)
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
    assert result.loop_run.counts[0].fresh > 0  # the loop ran
    assert inside["events"] == []
    assert result.report["step_fns_ready_s"] > 0
    # the same on run_loop alone: given ready functions, its calls hit their caches
    loop = L.build_loop(exp.task)
    key = jax.random.split(jax.random.PRNGKey(0), 1)[0]
    fns = RT.ready_step_fns(loop, key, "learned", False)
    compiled = (fns.init._cache_size(), fns.step._cache_size())
    assert compiled == (1, 1)
    plant = RT.MujocoPlant(exp.task, loop.q_home)
    arm = RT.ArmModel(RT.plant_model(exp.task), loop.ids)
    # two episodes: the second starts from the learner state the first carried over
    RT.run_loop(loop, plant, RT.FreeClock(), key, "learned", [30, 30], arm, fns=fns)
    assert (fns.init._cache_size(), fns.step._cache_size()) == compiled
    # with the eye: run_loop starts each episode with the eye's input emptied (its arguments:
    # Python floats and NumPy arrays); ready_step_fns compiled init for exactly those
    fns = RT.ready_step_fns(loop, key, "learned", True)
    sw = runner.episode_switches(runner.loop_switches("learned", True), True, 0.0667, 0.1433)
    obs = np.zeros(runner.OBS_SIZE)
    obs[runner._OBS_SLICES["M"]] = np.eye(3).ravel()
    fns.init(jnp.asarray(obs), loop.learner_init(key, float_dtype()), sw)
    assert (fns.init._cache_size(), fns.step._cache_size()) == (1, 1)


def test_realtime_run_with_an_idle_pool_runs_its_watchdog_and_restores_every_thread():
    """A short timed run with pool_idle and a watchdog that rescues at once (1 us): it ran to the
    end, rescued, and every thread of the process has its own scheduling back after."""
    import contextlib

    from hec_jax.realtime import clock

    if len(os.sched_getaffinity(0)) < 2:
        pytest.skip("pool_idle needs the CPUs pinned (two or more)")
    why = clock.pool_idle_refused(True)
    if why is not None:
        pytest.skip("leaving SCHED_IDLE is not permitted here: " + why)

    def policies():
        out = {}
        for t in clock._threads():
            with contextlib.suppress(ProcessLookupError):
                out[t] = os.sched_getscheduler(t)
        return out

    before = policies()
    exp = L.replace(L.catching(eye="truth"), swings=1, swing_s=0.5, settle_s=0.3)
    rt = RT.RealtimeConfig(twin="none", pool_idle=True, pool_rescue_us=1.0)
    result = RT.run_realtime(exp, rt, progress=False)
    placement = result.report["placement"]
    assert placement["pool_idle"]
    rescue = placement["pool_rescue"]
    assert rescue["after_us"] == 1.0 and rescue["alive_to_the_end"]
    assert rescue["rescues"] > 0 and rescue["refused_changes"] == 0
    after = policies()
    both = set(before) & set(after)  # threads that lived through the run
    assert both and {t: after[t] for t in both} == {t: before[t] for t in both}
    assert result.loop_run.counts[0].fresh > 0


@pytest.mark.slow
def test_untimed_loop_matches_mjx_episodes(untimed):
    """The same run against the MJX episodes (the simulated-time runs' code path)."""
    exp, loop, key, run = untimed
    logs = L.make_episodes(loop)(key[None], L.switches("learned"), exp.task.pendulum.conditions())
    logs = jax.tree_util.tree_map(np.asarray, logs)
    for swing in range(SWINGS):
        got = run.logs[swing]
        peak = np.abs(logs["f_contact"][0, swing]).max()
        err = np.abs(got["qpos"] - logs["qpos"][0, swing]).max()
        err_f = np.abs(got["f_contact"] - logs["f_contact"][0, swing]).max()
        err_k = np.abs(got["k_o"] - logs["k_o"][0, swing]).max()
        print(f"swing {swing}: qpos {err:.1e}, force {err_f:.1e} N of {peak:.0f}, K_o {err_k:.1e}")
        assert err < 1e-7 and err_f < 1e-5 * peak and err_k < 1e-5


class _ScriptedClock:
    """A clock whose time the test sets."""

    origin = 0.0

    def __init__(self):
        self.t = 0.0

    def start(self, lead_s=0.0):
        return 0.0

    def now(self):
        return self.t

    def wait_until(self, t):
        self.t = max(self.t, t)
        return self.t


def test_a_late_last_write_ends_the_episode_at_its_length():
    """The last tick of a 10-step episode writes 3.5 ms after its deadline: its own step is
    late and the plant integrates nothing past the episode's end (it counted 3 steps more as
    skipped, which the runner's counts then disagreed with the report about)."""
    exp = _task()
    loop = L.build_loop(exp.task)
    plant = RT.MujocoPlant(exp.task, loop.q_home)
    clock, n = _ScriptedClock(), 10
    plant.begin_episode(n)
    plant.start(clock)
    for j in range(n):
        clock.t = j * 1e-3 + 1e-4
        assert plant.read().index == j
        clock.t = j * 1e-3 + (2e-4 if j < n - 1 else 4.5e-3)
        plant.write(np.zeros(3))
    assert plant.counts == (n, n - 1, 1, 0)
    assert plant.episode_log()["kind"].tolist() == [0] * (n - 1) + [1]
    assert plant.read().index == n  # the runner's loop ends there


def test_plant_holds_the_torque_on_late_and_skipped_steps():
    """Deadline of step j: (j + 1) dt. A late torque is applied from the next step on; steps
    whose deadline passes with no call are integrated with the held torque."""
    exp = _task()
    loop = L.build_loop(exp.task)
    plant = RT.MujocoPlant(exp.task, loop.q_home)
    clock = _ScriptedClock()
    plant.begin_episode(10)
    plant.start(clock)
    ms = 1e-3
    taus = [np.full(3, k + 1.0) for k in range(4)]
    script = [  # (time of the read, time of the write) [s]
        (0.1 * ms, 0.2 * ms),  # step 0 fresh
        (1.0 * ms, 2.1 * ms),  # step 1 late: the held taus[0] (taus[1] held from step 2)
        (2.2 * ms, 2.3 * ms),  # step 2 fresh
        (6.1 * ms, 6.2 * ms),  # steps 3-5 skipped (held taus[2]), step 6 fresh
    ]
    indices, written = [], []
    for (t_read, t_write), tau in zip(script, taus, strict=True):
        clock.t = t_read
        indices.append(plant.read().index)
        clock.t = t_write
        written.append(plant.write(tau))
    assert indices == [0, 1, 2, 6]
    assert written == [t for _, t in script]
    assert plant.counts == (7, 3, 1, 3)
    log = plant.episode_log()
    np.testing.assert_array_equal(log["kind"], [0, 1, 0, 2, 2, 2, 0])
    applied = log["ctrl"][:, 0]
    np.testing.assert_array_equal(applied, [1.0, 1.0, 3.0, 3.0, 3.0, 3.0, 4.0])


def test_the_board_shows_the_plants_clock_and_the_camera_wakes_on_it():
    """The plant's board carries its clock time at each write (NaN before the episode's clock
    runs). The camera's sleep ends two steps before the frame is due, counted from the step
    shown, or on the plant's clock when the step shown is behind it (a catch-up burst)."""
    from hec_jax.realtime.workers import _POLL_S, camera_sleep_s

    exp = _task()
    loop = L.build_loop(exp.task)
    plant = RT.MujocoPlant(exp.task, loop.q_home)
    plant._camera_proc = object()  # publishes as with a camera process (none is started)
    clock = _ScriptedClock()
    plant.begin_episode(50)
    _, rec = plant.board.read()
    assert rec["step"] == 0 and np.isnan(rec["t_clock"])
    plant.start(clock)
    clock.t = 0.3e-3
    plant.read()
    plant.write(np.zeros(3))  # step 0 on time: the board shows step 1 at clock 0.3 ms
    _, rec = plant.board.read()
    assert rec["step"] == 1 and rec["t_clock"] == pytest.approx(0.3e-3)
    clock.t = 34.2e-3  # a stall: the read integrates steps 1-33 with the held torque
    assert plant.read().index == 34
    _, rec = plant.board.read()
    assert rec["step"] == 34 and rec["t_clock"] == pytest.approx(34.2e-3)
    plant._camera_proc = None

    dt, due = 1e-3, 33
    # on time (step s written at about (s - 1) dt + 0.3 ms, read 0.1 ms later): the count from
    # the step shown, as before the clock was on the board
    for s in (1, 10, 30):
        on_time = {"step": s, "t_clock": (s - 1) * dt + 3e-4, "t_wall": 100.0}
        assert camera_sleep_s(on_time, due, dt, 100.0 + 1e-4) == pytest.approx(
            max(_POLL_S, (due - s - 2) * dt)
        )
    # a burst: step 5 written at clock 34.2 ms; the frame's time has passed, so no sleep
    burst = {"step": 5, "t_clock": 34.2e-3, "t_wall": 100.0}
    assert camera_sleep_s(burst, due, dt, 100.0) == _POLL_S
    # behind by 10 steps at clock 20 ms: until clock 31 ms, not 26 steps on
    behind = {"step": 10, "t_clock": 20e-3, "t_wall": 100.0}
    assert camera_sleep_s(behind, due, dt, 100.002) == pytest.approx(9e-3)
    # the clock not running (NaN): the count alone; never under the poll interval
    held = {"step": 0, "t_clock": np.nan, "t_wall": 100.0}
    assert camera_sleep_s(held, due, dt, 100.0) == pytest.approx(31e-3)
    assert camera_sleep_s({**held, "step": 32}, due, dt, 100.0) == _POLL_S


def test_rt_budget_rest_covers_the_part_the_kernel_keeps():
    """The rest before an episode's lead: the part of each real-time period that real-time
    threads may not use plus the margin, only under a real-time policy with a limit."""
    import os

    from hec_jax.realtime import clock

    fifo, rr, other = os.SCHED_FIFO, os.SCHED_RR, os.SCHED_OTHER
    assert clock.rt_budget_rest_s(fifo, 1_000_000, 950_000) == pytest.approx(0.06)
    assert clock.rt_budget_rest_s(rr, 1_000_000, 800_000, margin_s=0.0) == pytest.approx(0.2)
    assert clock.rt_budget_rest_s(other, 1_000_000, 950_000) == 0.0
    assert clock.rt_budget_rest_s(fifo, 1_000_000, -1) == 0.0  # no limit
    assert clock.rt_budget_rest_s(fifo, 1_000_000, 1_000_000) == 0.0
    # read from this thread and this kernel: normal scheduling here, so none
    assert os.sched_getscheduler(0) == other and clock.rt_budget_rest_s() == 0.0
    with open(clock.RT_PERIOD_FILE) as f, open(clock.RT_RUNTIME_FILE) as g:
        period, runtime = int(f.read()), int(g.read())
    expect = 0.0 if runtime < 0 or runtime >= period else (period - runtime) * 1e-6 + 0.01
    assert clock.rt_budget_rest_s(fifo) == pytest.approx(expect)


def test_shared_board_and_frame_ring_round_trip():
    board = Board({"t": (), "x": (2,)})
    assert board.seq == 0
    board.write(t=1.5, x=[2.0, 3.0])
    seq, rec = board.read()
    assert seq == 2 and rec["t"] == 1.5 and rec["x"].tolist() == [2.0, 3.0]
    # a writer preempted mid-write (the sequence odd): the control loop's try_read returns at
    # once with nothing, read waits and then gives up; once the write completes both read it
    board._buf[0] += 1.0
    board._buf[1] = 9.0
    t0 = time.monotonic()
    assert board.try_read() is None and time.monotonic() - t0 < 0.01
    with pytest.raises(TimeoutError):
        board.read(timeout_s=0.02)
    board._buf[0] += 1.0
    assert board.try_read()[0] == board.read()[0] == 4 and board.try_read()[1]["t"] == 9.0
    ring = FrameRing(4, 6, {"t": ()}, slots=2)
    assert ring.get() is None
    for i in range(3):
        ring.put(i, np.full((4, 6, 3), i, np.uint8), t=0.1 * i)
    image, meta = ring.get(after=0)
    assert int(meta["index"]) == 2 and image[0, 0, 0] == 2 and meta["t"] == pytest.approx(0.2)
    assert ring.get(after=2) is None


def _check_report(result):
    """The deadline report agrees with the recorded tick times and the plant's step log."""
    rep, dt = result.report["control"], result.dt
    tt = tick_table(result.loop_run)
    n = rep["counts"]
    steps = sum(len(r["kind"]) for r in result.loop_run.ticks)
    assert n["steps"] == steps == result.logs["t"].size
    assert n["fresh"] + n["late"] + n["skipped"] == n["steps"]
    ticked = np.isfinite(tt["t_write"])
    assert n["ticks"] == ticked.sum() == n["fresh"] + n["late"]
    t_sched = tt["index"] * dt
    lat = tt["t_write"][ticked] - t_sched[ticked]
    assert np.all(lat > 0)
    phases = np.stack([tt[k][ticked] for k in ("t_wake", "t_obs", "t_step", "t_write")])
    assert np.all(np.diff(phases, axis=0) >= 0)
    assert np.all(np.diff(tt["t_write"][ticked][tt["episode"][ticked] == 0]) > 0)
    # the clock waited for the step after the previous tick's (t_due); the plant returned it,
    # or after a stall a later one
    rows = np.flatnonzero(ticked)
    first = np.r_[True, tt["episode"][rows][1:] != tt["episode"][rows][:-1]]
    want = np.where(first, 0, np.r_[0, tt["index"][rows][:-1] + 1]) * dt
    np.testing.assert_allclose(tt["t_due"][rows], want, rtol=0, atol=1e-12)
    assert np.all(tt["t_due"][rows] <= tt["index"][rows] * dt + 1e-12)
    # a tick is late exactly when its torques came at or after its deadline
    late = tt["t_write"][ticked] >= (tt["index"][ticked] + 1) * dt  # the plant's comparison
    assert n["late"] == n["late_from_recorded_times"] == late.sum()
    np.testing.assert_array_equal(tt["kind"][ticked] == 1, late)
    assert not np.any(ticked & (tt["kind"] == 2))  # a skipped step has no tick
    # each episode's time 0 on the monotonic clock: its ticks' wall times are origin + t, and
    # they fall between the run's start and now
    origin = tt["t_origin"][ticked]
    assert len(result.loop_run.origin_s) == len(result.loop_run.ticks)
    assert np.all(np.diff(result.loop_run.origin_s) > 0)
    assert np.all(origin + tt["t_write"][ticked] <= RT.clock.monotonic_s())
    assert n["missed"] == n["late"] + n["skipped"] and n["consistent"]
    assert sum(rep["histogram"]["counts"]) == n["ticks"]
    p = rep["latency_us"]
    assert 0 < p["p50"] <= p["p99"] <= p["p99_9"] <= p["max"] == pytest.approx(lat.max() * 1e6)
    # every step's deadline: the ticks' latencies, and a skipped step's at least its period
    every = RT.report.deadline_latency(tt, dt)
    np.testing.assert_array_equal(every[ticked], lat)
    # a skipped step waits for the next ticked step's torques of its episode (at least its
    # period), or for the episode's end; computed here row by row
    want = []
    for i in np.flatnonzero(~ticked):
        later = [
            k
            for k in range(i + 1, len(ticked))
            if tt["episode"][k] == tt["episode"][i] and ticked[k]
        ]
        if later:
            want.append(max(tt["t_write"][later[0]] - tt["index"][i] * dt, dt))
        else:
            last = max(k for k in range(len(ticked)) if tt["episode"][k] == tt["episode"][i])
            want.append(max((tt["index"][last] + 1 - tt["index"][i]) * dt, dt))
    np.testing.assert_allclose(every[~ticked], want, rtol=0, atol=1e-12)
    d = rep["deadline_latency_us"]
    assert d["n"] == n["steps"] and d["max"] >= p["max"]
    targets = result.report["targets"]
    assert targets["p99_9_deadline_within_period"] == (d["p99_9"] < dt * 1e6)
    assert targets["p99_9_tick_latency_within_period"] == (p["p99_9"] < dt * 1e6)
    # the control thread's CPU time per stage: recorded for every tick, positive, and within the
    # wall time the tick took (a thread runs at most as long as the clock between its stamps)
    cpu = rep["cpu"]
    assert cpu["step_us"]["n"] == cpu["tick_us"]["n"] == n["ticks"]
    assert all(cpu[f"{k}_us"]["p50"] > 0 for k in ("read", "observe", "step", "write"))
    wall_step = (tt["t_step"] - tt["t_obs"])[ticked]
    assert np.all(tt["cpu_step"][ticked] * 1e-9 <= wall_step + 2e-5)
    # every late tick is given one cause
    causes = rep["miss_causes"]
    assert causes["late"] == n["late"] == sum(causes["counts"].values())
    assert causes["events"] == sum(causes["event_counts"].values()) <= n["missed"]
    assert (causes["events"] > 0) == (n["missed"] > 0)
    # the control thread's page faults: counted for every tick, at most one run per event
    faults = cpu["faults"]
    assert np.isfinite(tt["faults_major"][ticked]).all()
    assert faults["major"] == int(tt["faults_major"][ticked].sum()) >= faults["ticks_with_major"]
    assert faults["missed_events_with_major"] <= causes["events"]
    print("\n".join(RT.report.deadline_table(result.report)))


def _check_camera_twin_report(folder, run, capsys):
    """``write_report`` and ``print_report`` with a camera twin: its entry filled from the run's
    own logs (the report's plumbing, not the twin)."""
    logs = dict(run.logs, x_e=np.asarray(run.logs["x_e"]) + 0.5)  # the twin's told apart
    twin = dict(
        logs=logs, metrics=run.metrics, wall_s=1.0, latency_s=0.0085, latency_source="measured"
    )
    comparison = {"camera": RT.report.compare_metrics(run.metrics, run.metrics, 0.2, {})}
    result = dataclasses.replace(run, twins={"camera": twin}, comparison=comparison)
    RT.write_report(folder, result)
    saved = json.loads((folder / "metrics.json").read_text())
    assert saved["simulated_camera_latency"] == {"latency_s": 0.0085, "source": "measured"}
    assert saved["targets"]["task_metrics_within_20pct_of_camera"] is True
    with np.load(folder / "trajectory_simulated_camera.npz") as z:
        np.testing.assert_array_equal(z["x_e"], logs["x_e"])
    with np.load(folder / "trajectory_realtime.npz") as z:
        np.testing.assert_array_equal(z["x_e"], run.logs["x_e"])
    capsys.readouterr()
    RT.print_report(result)
    out = capsys.readouterr().out
    assert "its estimates used 8.5 ms after the exposure's end (measured)" in out


def test_realtime_run_reports_itself(tmp_path, capsys):
    exp = L.replace(L.catching(eye="truth"), swings=1, swing_s=1.0, settle_s=0.3)
    result = RT.run_realtime(exp, RT.RealtimeConfig(twin="none"), progress=False)
    _check_report(result)
    # normal scheduling: no rest before the lead, recorded as such
    assert result.loop_run.rest_s == [0.0] and result.report["placement"]["rt_budget_rest_s"] == 0
    assert result.report["placement"]["pool_rescue"] is None  # no pool_idle: no watchdog
    assert result.logs["x_e"].shape == (1, 1, 1000, 2)
    assert result.metrics["peak_force"]["mean"] > 0
    # the host's steal over the run: per CPU where the kernel accounts it, never negative
    steal = result.report["host"]["steal_ms_per_cpu"]
    assert steal is None or (len(steal) == os.cpu_count() and min(steal) >= 0)
    RT.write_report(tmp_path, result)
    saved = json.loads((tmp_path / "deadline.json").read_text())
    assert saved["control"]["counts"] == result.report["control"]["counts"]
    assert (tmp_path / "deadline_histogram.png").stat().st_size > 0
    (tmp_path / "camera_twin").mkdir()
    _check_camera_twin_report(tmp_path / "camera_twin", result, capsys)


@pytest.mark.slow
def test_realtime_camera_run_reports_itself(monkeypatch):
    """The camera and the eye in their processes: frames and estimates add up; the camera
    twin is given the run's measured eye latency (the twins themselves are not run here)."""
    from hec_jax.loop.camera_loop import mid_exposure_steps, steps_per_frame
    from hec_jax.realtime import runner

    given = []
    monkeypatch.setattr(runner, "simulated_twins", lambda exp, *args, **kw: given.append(exp) or {})
    cam = L.CameraConfig.void_perfect(width=320, height=240)
    exp = L.replace(L.catching(eye="camera", camera=cam), swings=1, swing_s=1.5, settle_s=0.3)
    result = RT.run_realtime(
        exp, RT.RealtimeConfig(twin="auto", eye_save_failed=50), progress=False
    )
    _check_report(result)
    eye = result.report["eye"]
    (twin_exp,) = given
    measured = eye["latency_ms"]
    expected = (  # with no estimate seen after the release, the camera's own
        cam.latency_s
        if measured["n"] == 0
        else runner.twin_camera_latency_s(1e-3 * measured["p50"], cam, result.dt)
    )
    assert twin_exp.camera.latency_s == expected
    assert dataclasses.replace(twin_exp.camera, latency_s=cam.latency_s) == result.config.camera
    cam_log, eye_log = result.camera_log, result.eye_log
    assert eye["camera"]["frames_rendered"] == len(cam_log["index"]) > 0
    assert np.array_equal(cam_log["index"], np.arange(len(cam_log["index"])))
    # each frame is due at the simulated loop's mid-exposure step, shown no earlier, and read
    # out after its render (held where the render beat the exposure's end)
    back = mid_exposure_steps(cam, result.dt)
    period = steps_per_frame(cam, result.dt)
    np.testing.assert_array_equal(
        cam_log["step_due"], np.maximum(cam_log["number"] * period - back, 0)
    )
    assert np.all(cam_log["step"] >= cam_log["step_due"])
    assert np.all(cam_log["t_wall_put"] >= cam_log["t_wall_done"])
    assert eye["camera"]["readout_wait_ms"]["n"] == len(cam_log["index"])
    assert eye["camera"]["frames_not_read_out"] == cam_log["not_read_out"] == 0
    # each rendered frame up to the eye's last was processed once, in order, or dropped
    processed, dropped = eye["eye"]["frames_processed"], eye["eye"]["frames_dropped"]
    seen_by_eye = eye_log["index"].astype(int)
    assert np.all(np.diff(seen_by_eye) > 0) and set(seen_by_eye) <= set(cam_log["index"])
    assert processed == len(seen_by_eye)
    rendered_up_to_last = cam_log["index"][cam_log["index"] <= seen_by_eye.max()]
    assert dropped == len(set(rendered_up_to_last) - set(seen_by_eye))
    # the rest of the rendered frames came after the eye's last: counted apart, not lost
    after_last = eye["eye"]["frames_after_last_processed"]
    assert after_last == len(cam_log["index"]) - len(rendered_up_to_last)
    assert processed + dropped + after_last == eye["camera"]["frames_rendered"]
    assert eye["estimates_taken"] >= 1
    assert eye["latency_ms"]["n"] == 0 or eye["latency_ms"]["p50"] > 0
    # the published state per frame, acceleration included: finite once the track has started
    started = eye_log["initialised"].astype(bool)
    for name in ("x_est", "xd_est", "xdd_est"):
        assert eye_log[name].shape == (len(eye_log["index"]), 2)
        assert np.all(np.isfinite(eye_log[name][started]))
        assert np.all(np.isnan(eye_log[name][~started]))
    # the eye's stages (mask, the tracker's detection and estimation) lie within its frame time
    stages = eye_log["mask_ms"] + eye_log["detection_ms"] + eye_log["estimation_ms"]
    assert np.all(eye_log["mask_ms"] >= 0) and np.all(eye_log["estimation_ms"] > 0)
    assert np.all(stages <= eye_log["eye_ms"] + 1e-6)
    assert set(eye["eye"]) >= {"mask_ms", "detection_ms", "estimation_ms"}
    # every frame after the release has one source: a hypothesis of the tracker, or invalid
    by_source = eye["eye"]["fits_by_source"]
    later = eye_log["number"] > 0
    assert sum(by_source.values()) == int(later.sum())
    assert by_source["invalid"] == int(np.sum(~eye_log["valid"][later]))
    # the processes' CPU time and the host's steal, per frame; the slow frames are the ones
    # published more than a frame period after their exposure
    assert np.all(eye_log["eye_cpu_ms"] >= 0) and np.all(cam_log["render_cpu_ms"] > 0)
    assert eye_log["eye_steal_ms"].shape[0] == len(eye_log["index"])
    assert cam_log["render_steal_ms"].shape[0] == len(cam_log["index"])
    # JAX's compiles in the eye's process: the warm-up's are heard (a fresh process traces
    # every path), and the frames that compiled are counted from the per-frame log
    assert eye["eye"]["warm_up_compile_ms"] > 0
    assert eye["eye"]["frames_compiling"] == int(np.sum(eye_log["jax_compile_events"] > 0))
    # the camera CPU's speed over the run: per-second medians of the render's CPU time
    by_second = eye["camera"]["render_cpu_ms_per_second"]
    assert by_second["min"] <= by_second["p50"] <= by_second["max"]
    assert by_second["min"] >= cam_log["render_cpu_ms"].min()
    pipeline = 1e3 * (eye_log["t_wall_done"] - eye_log["t_wall_exposure"])
    # each estimate written after the eye was done with its frame, and taken by the loop after
    # that (not after the write's time stamp: the loop may read the finished write first);
    # every frame published (each episode's release frame is answered, and the frames after
    # it with it)
    published = eye_log["t_wall_published"]
    assert np.all(published >= eye_log["t_wall_done"])
    assert eye["eye"]["publish_ms"]["n"] == int(later.sum())
    for a in result.loop_run.arrivals:
        assert np.all(a["t_wall_taken"] >= a["t_wall_done"])
    assert eye["done_to_taken_ms"]["n"] == eye["latency_wall_ms"]["n"]
    # the oldest state: the age's maximum, and the estimate that ended it in stages that add up
    oldest = eye["oldest_state"]
    assert oldest["age_ms"] == pytest.approx(eye["age_ms"]["max"])
    ended = oldest["ended_by"]
    if ended is not None:
        assert sum(ended["stages_ms"].values()) == pytest.approx(ended["latency_ms"])
        assert ended["done_to_written_ms"] >= 0 and ended["renders_during_eye_ms"] >= 0
        # the CPU's speed then, from the logs' CPU times: positive ratios (None only where the
        # log lacks the next frame or the fit source has fewer than 5 frames)
        own, following = ended["render_cpu_vs_median"]
        assert own > 0 and (following is None or following > 0)
        assert ended.get("eye_cpu_vs_median") is None or ended["eye_cpu_vs_median"] > 0
    period_ms = eye["frame_period_ms"]
    assert eye["slow_frames"]["over_one_period"] == int(np.sum(later & (pipeline > period_ms)))
    assert 0 <= eye["slow_frames"]["with_control_missed"] <= eye["slow_frames"]["over_one_period"]
    # the saved failed frames: every frame after the release whose tracked fit failed (up to
    # 50), each replaying to the fit the run logged
    from hec_jax.geometry.track import FIT_SOURCES
    from hec_jax.realtime.workers import replay_failed_frames

    saved = result.eye_failed_frames
    failed = later & (eye_log["fit_source"] != FIT_SOURCES.index("tracked"))
    assert [r["row"]["index"] for r in saved["frames"]] == eye_log["index"][failed][:50].tolist()
    for record, step in zip(saved["frames"], replay_failed_frames(saved), strict=True):
        assert step.fit_source == record["fit_source"] and step.valid == record["valid"]
        np.testing.assert_array_equal(step.measured_position, record["measured_position"])


def test_realtime_experiment_sets_the_eyes_tracker():
    """The real-time tracker: the scene's, with the local starts (unless asked, 4 of the
    turned starts through the fine gates, the turned starts at one centre where the
    two are close, the search from scratch deferred by one failed frame, and without the
    manoeuvre restart unless asked (the run and its twin run this one)."""
    exp = L.catching(eye="camera", camera=L.CameraConfig.void_perfect())
    scene = exp.camera.tracker
    assert scene.maneuver_nis == 16.3 and scene.stop_hypothesis
    track = RT.runner.realtime_experiment(exp, RT.RealtimeConfig()).camera.tracker
    assert track.maneuver_nis is None and track.local_starts == 12 and track.local_keep == 4
    assert track == L.replace(
        scene, maneuver_nis=None, local_starts=12, local_keep=4, local_merge=0.1, defer_search=1
    )
    assert scene.defer_search == 0  # the simulated task's tracker searches every failed frame
    rt = RT.RealtimeConfig(
        eye_maneuver_restart=True,
        eye_local_starts=0,
        eye_local_keep=4,
        eye_local_merge=0.0,
        eye_defer_search=0,
        duration_s=7.0,
    )
    kept = RT.runner.realtime_experiment(exp, rt)
    assert kept.camera.tracker == L.replace(scene, local_starts=0, local_keep=4)
    assert kept.task.swings == 3 and kept.seeds == 1
    # the camera's multisampling: the scene's unless given, then the twin renders alike
    assert kept.camera.msaa is exp.camera.msaa is None
    assert RT.runner.realtime_experiment(exp, RT.RealtimeConfig(camera_msaa=0)).camera.msaa == 0
    # the planes' render grid and the eye's compiler options likewise
    assert kept.camera.plane_grid_m is None and not kept.camera.tracker.cpu_small_kernels
    fast = RT.runner.realtime_experiment(
        exp, RT.RealtimeConfig(camera_plane_grid_m=0.05, eye_small_kernels=True)
    )
    assert fast.camera.plane_grid_m == 0.05 and fast.camera.tracker.cpu_small_kernels
    assert fast.camera.tracker == L.replace(track, cpu_small_kernels=True)


def test_realtime_refused_says_why_and_leaves_the_scheduling(monkeypatch):
    import os

    from hec_jax.realtime import clock

    assert clock.realtime_refused(0) is None
    before = (os.sched_getscheduler(0), os.sched_getparam(0))
    allowed = clock.realtime_refused(10)  # None where permitted (root), else the reason
    assert (os.sched_getscheduler(0), os.sched_getparam(0)) == before
    assert allowed is None or "not permitted" in allowed

    def deny(*args):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(clock.os, "sched_setscheduler", deny)
    why = clock.realtime_refused(50)
    assert "SCHED_FIFO 50" in why and "--rt-priority" in why


def _waiting_thread():
    """A started thread that waits on its event (set it, then join)."""
    import threading

    go = threading.Event()
    t = threading.Thread(target=go.wait)
    t.start()
    return t, go


def test_pool_idle_puts_the_other_threads_under_sched_idle_and_restores_their_own():
    import os
    import threading

    from hec_jax.realtime.clock import pool_idle_refused, realtime_priority
    from hec_jax.realtime.config import RealtimeConfig

    with pytest.raises(ValueError, match="pool_idle must be a bool"):
        RealtimeConfig(pool_idle=1)
    assert pool_idle_refused(False) is None
    assert RealtimeConfig(pool_idle=True).pool_idle_applies
    for off in (
        dict(pool_idle=False),
        dict(rt_priority=50),
        dict(timed=False),
        dict(pin_cpus=False),
    ):
        assert not RealtimeConfig(**{"pool_idle": True, **off}).pool_idle_applies
    # with real-time priority the pool runs one below the loop instead (not entered here: it
    # needs the privilege)
    assert not realtime_priority(50, pool_idle=True).pool_idle
    why = pool_idle_refused(True)
    if why is not None:  # not root here: refused before a run, with the reason
        assert "--pool-idle" in why and "nice limit" in why
        pytest.skip("leaving SCHED_IDLE is not permitted here: " + why)
    other, go = _waiting_thread()
    batch, go_b = _waiting_thread()
    try:
        me, tid = threading.get_native_id(), other.native_id
        os.sched_setscheduler(batch.native_id, os.SCHED_BATCH, os.sched_param(0))
        assert os.sched_getscheduler(me) == os.sched_getscheduler(tid) == os.SCHED_OTHER
        with realtime_priority(0, pool_idle=True) as p:
            assert p.pool_idle
            assert os.sched_getscheduler(tid) == os.sched_getscheduler(batch.native_id)
            assert os.sched_getscheduler(tid) == os.SCHED_IDLE
            assert os.sched_getscheduler(me) == os.SCHED_OTHER  # the loop keeps its own
        # each thread gets its own back (not SCHED_OTHER for all)
        assert os.sched_getscheduler(tid) == os.SCHED_OTHER
        assert os.sched_getscheduler(batch.native_id) == os.SCHED_BATCH
        with realtime_priority(0) as p:  # off: nothing changes
            assert not p.pool_idle and os.sched_getscheduler(tid) == os.SCHED_OTHER
        with pytest.raises(KeyError), realtime_priority(0, pool_idle=True):
            raise KeyError("the run failed")  # restored on the way out, the error kept
        assert os.sched_getscheduler(tid) == os.SCHED_OTHER
    finally:
        go.set()
        go_b.set()
        other.join()
        batch.join()


def _burner(cpu: int, seconds: float):
    """A process that spins on ``cpu`` for ``seconds`` at normal scheduling, started: it has
    begun spinning when this returns."""
    import subprocess
    import sys

    code = (
        f"import os, time\nos.sched_setaffinity(0, {{{cpu}}})\nt = time.monotonic()\n"
        f"print(flush=True)\nwhile time.monotonic() - t < {seconds}:\n    pass\n"
    )
    p = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE)
    p.stdout.readline()
    return p


def _step_through_idle_pool(rescue_after_us):
    """[s] one stand-in step: the calling thread (the loop) hands 1 ms of CPU work to another
    thread of this process under SCHED_IDLE and waits for it, with a process spinning on their
    CPU; with ``rescue_after_us`` (not None) under :class:`pool_rescue`. Returns the wait and
    the watchdog's summary."""
    import os
    import threading
    import time

    from hec_jax.realtime import clock

    cpus = sorted(os.sched_getaffinity(0))
    ask, done, finish = threading.Event(), threading.Event(), threading.Event()

    def pool():
        ask.wait()
        t = time.thread_time()
        while time.thread_time() - t < 1e-3:
            pass
        done.set()
        finish.wait()  # alive (its scheduling readable) until the end

    worker = threading.Thread(target=pool)
    worker.start()
    burner = None
    try:
        with clock.pinned({cpus[0]}), clock.realtime_priority(0, pool_idle=True) as prio:
            assert os.sched_getscheduler(worker.native_id) == os.SCHED_IDLE
            with clock.pool_rescue(
                prio.idle_threads, rescue_after_us, 250.0, cpus=[cpus[1]]
            ) as rescue:
                burner = _burner(cpus[0], 0.6)
                time.sleep(0.02)
                if rescue.marker is not None:
                    rescue.marker[0] = time.monotonic_ns()
                t0 = time.monotonic()
                ask.set()
                done.wait(5.0)
                waited = time.monotonic() - t0
                if rescue.marker is not None:
                    rescue.marker[0] = 0
                    # the step done: the watchdog puts the pool under SCHED_IDLE again
                    end = time.monotonic() + 1.0
                    while os.sched_getscheduler(worker.native_id) != os.SCHED_IDLE:
                        assert time.monotonic() < end, "the pool was not put back under SCHED_IDLE"
                        time.sleep(1e-3)
        return waited, rescue.summary
    finally:
        ask.set()
        finish.set()
        worker.join()
        if burner is not None:
            burner.kill()
            burner.wait()


def test_pool_rescue_bounds_a_step_that_waits_for_an_idle_pool_behind_another_process():
    """The hazard of pool_idle reproduced with a stand-in pool thread (1 ms of work) and a
    process spinning 0.6 s on its CPU: without the watchdog the step waits for much of the
    burst, with it (rescued after 1 ms) for a few ms; the thread goes back under SCHED_IDLE
    after."""
    import os

    from hec_jax.realtime import clock
    from hec_jax.realtime.config import RealtimeConfig

    with pytest.raises(ValueError, match="after_us"):
        clock.pool_rescue({1: (0, 0)}, 0.0)
    for bad in (-1.0, True):
        with pytest.raises(ValueError, match="pool_rescue_us"):
            RealtimeConfig(pool_rescue_us=bad)
    with clock.pool_rescue({1: (0, 0)}, None) as off:  # None: no watchdog, no marker
        assert off.marker is None
    assert off.summary is None
    if len(os.sched_getaffinity(0)) < 2:
        pytest.skip("the watchdog needs a CPU other than the loop's")
    why = clock.pool_idle_refused(True)
    if why is not None:
        pytest.skip("leaving SCHED_IDLE is not permitted here: " + why)
    # with the watchdog the step never waits long, whatever else runs on the machine
    rescued, summary = _step_through_idle_pool(1000.0)
    assert rescued < 0.1, f"rescued step waited {rescued:.3f} s"
    assert summary["rescues"] <= 1 and summary["alive_to_the_end"]
    assert summary["refused_changes"] == 0
    # the control: without it the same step waits for the burst (0.34-0.37 s on the quiet
    # 2-core VM). Under other load the idle thread at times gets the CPU at once (seen with
    # both CPUs busy), so the hazard is tried up to three times before the test gives up on it
    stalls = []
    for _ in range(3):
        stalled, none = _step_through_idle_pool(None)
        assert none is None
        stalls.append(stalled)
        if stalled > 0.15:
            break
    else:
        pytest.skip(f"the hazard did not show under this load (waits {stalls} s)")
    if summary["rescues"] == 0:  # the step was not held up that time: try the watchdog again
        rescued, summary = _step_through_idle_pool(1000.0)
        assert rescued < 0.1, f"rescued step waited {rescued:.3f} s"
    assert summary["rescues"] in (0, 1) and 0 <= summary["rescued_ms"] < 100


def test_pool_rescue_counts_and_warns_of_scheduling_changes_it_was_refused():
    """A change the kernel refuses (here an invalid policy for the thread's own scheduling) is
    counted, and the watchdog's exit warns: the pool was not rescued."""
    import os
    import time

    from hec_jax.realtime import clock

    other, go = _waiting_thread()
    tid = other.native_id
    own = os.sched_getscheduler(tid), os.sched_getparam(tid)
    try:
        with pytest.warns(RuntimeWarning, match="changes refused"):
            with clock.pool_rescue({tid: (12345, 0)}, 1.0, 250.0) as rescue:
                rescue.marker[0] = time.monotonic_ns() - 10**9  # a step waiting 1 s
                end = time.monotonic() + 5.0
                while rescue.marker[4] == 0 and time.monotonic() < end:
                    time.sleep(1e-3)
        assert rescue.summary["refused_changes"] >= 1 and rescue.summary["rescues"] == 1
        assert rescue.summary["alive_to_the_end"] and rescue.summary["rescued_ms"] > 0
    finally:
        os.sched_setscheduler(tid, own[0], own[1])
        go.set()
        other.join()


def test_pool_idle_that_cannot_be_undone_is_refused_before_a_run_and_raises_on_exit(
    monkeypatch,
):
    import contextlib
    import os

    from hec_jax.realtime import clock

    real = os.sched_setscheduler
    # this process's threads can be put back for real afterwards (else only the refusal)
    privileged = clock.pool_idle_refused(True) is None
    before = {}
    for t in clock._threads():  # (a thread just joined can linger in the listing)
        with contextlib.suppress(ProcessLookupError):
            before[t] = os.sched_getscheduler(t), os.sched_getparam(t)

    def unprivileged(tid, policy, param):  # as Linux without CAP_SYS_NICE or a nice limit
        if policy != os.SCHED_IDLE and clock.os.sched_getscheduler(tid) == os.SCHED_IDLE:
            raise PermissionError(1, "Operation not permitted")
        real(tid, policy, param)

    monkeypatch.setattr(clock.os, "sched_setscheduler", unprivileged)
    why = clock.pool_idle_refused(True)
    assert why is not None and "--pool-idle" in why and "not permitted" in why
    if not privileged:
        return
    other, go = _waiting_thread()
    try:
        with pytest.raises(PermissionError, match="stay under SCHED_IDLE"):
            with clock.realtime_priority(0, pool_idle=True):
                pass
        with pytest.raises(KeyError):  # an error on its way is not replaced
            with clock.realtime_priority(0, pool_idle=True):
                raise KeyError("the run failed")
    finally:
        for tid, (policy, param) in before.items():  # this process's threads put back
            with contextlib.suppress(ProcessLookupError):
                real(tid, policy, param)
        go.set()
        other.join()


def test_children_are_pinned_off_the_control_cpu_unless_the_eye_may_share_it():
    import os
    import subprocess
    import sys
    from types import SimpleNamespace

    from hec_jax.realtime.config import RealtimeConfig
    from hec_jax.realtime.runner import _pin_children

    cpus = sorted(os.sched_getaffinity(0))
    if len(cpus) < 2:
        pytest.skip("placement needs two CPUs")
    sleeper = [sys.executable, "-c", "import time; time.sleep(30)"]
    procs = [subprocess.Popen(sleeper) for _ in range(2)]
    try:
        plant = SimpleNamespace(_camera_proc=procs[0])
        eye = SimpleNamespace(proc=procs[1])
        for shared in (False, True):
            where: dict = {}
            control = _pin_children(plant, eye, where, shared)
            assert control == {cpus[0]}
            camera, seen = os.sched_getaffinity(procs[0].pid), os.sched_getaffinity(procs[1].pid)
            assert cpus[0] not in camera and where["camera_cpus"] == sorted(camera)
            assert where["eye_cpus"] == sorted(seen)
            assert (cpus[0] in seen) == shared and set(cpus[1:]) >= seen - {cpus[0]}
    finally:
        for p in procs:
            p.kill()
            p.wait()
    # sharing the loop's CPU without real-time priority would let the eye compete with it
    for bad in (dict(rt_priority=0), dict(rt_priority=50, pin_cpus=False)):
        with pytest.raises(ValueError, match="eye_on_control_cpu"):
            RealtimeConfig(eye_on_control_cpu=True, **bad)
    with pytest.raises(ValueError, match="eye_on_control_cpu must be a bool"):
        RealtimeConfig(eye_on_control_cpu=1)
    assert RealtimeConfig(eye_on_control_cpu=True, rt_priority=50).eye_on_control_cpu


def test_cpu_latency_request_writes_holds_and_withdraws(tmp_path):
    import os
    import struct

    from hec_jax.realtime import clock
    from hec_jax.realtime.config import RealtimeConfig

    # on a stand-in file: the int32 request is written on entry and the file closed on exit
    path = tmp_path / "cpu_dma_latency"
    path.write_bytes(b"")
    req = clock.cpu_latency_request(25, str(path))
    with req:
        assert struct.unpack("i", path.read_bytes()) == (25,)
        assert req._fd is not None and os.fstat(req._fd).st_ino == path.stat().st_ino
    assert req._fd is None
    with clock.cpu_latency_request(None, str(tmp_path / "absent")):
        pass  # None asks nothing: the file is never opened
    assert clock.cpu_latency_refused(None, str(tmp_path / "absent")) is None
    missing = str(tmp_path / "absent")
    assert "--cpu-latency-us" in clock.cpu_latency_refused(0, missing)
    with pytest.raises(FileNotFoundError), clock.cpu_latency_request(0, missing):
        pass
    for bad in (-1, 2.0, 2**31):
        with pytest.raises(ValueError, match="latency_us"):
            clock.cpu_latency_request(bad)
        with pytest.raises(ValueError, match="cpu_latency_us"):
            RealtimeConfig(cpu_latency_us=bad)
    # on Linux's own PM QoS file (root): reading it gives the CPUs' current target, which the
    # request sets while held and which returns to its previous value afterwards
    device = clock.CPU_LATENCY_DEVICE
    if clock.cpu_latency_refused(0) is not None:
        pytest.skip("the PM QoS request needs root and /dev/cpu_dma_latency")

    def target():
        with open(device, "rb") as f:
            return struct.unpack("i", f.read(4))[0]

    before = target()
    with clock.cpu_latency_request(0):
        assert target() == 0
    assert target() == before


def test_late_ticks_are_given_the_part_of_their_latency_that_grew():
    """Hand-made ticks (dt 1 ms): the usual tick wakes on time, runs 250 us on the CPU and
    takes 300 us to its torques. Late: tick 2 wakes 900 us late; ticks 4 and 9 run 850 us
    longer on the CPU; tick 6 is 900 us off the CPU and its stall goes on (step 7 skipped,
    tick 8 wakes late: the same event). Tick 9 ends episode 0 and tick 10 opens episode 1
    late (woke late): two events, not one."""
    import numpy as np

    from hec_jax.realtime.report import latency_parts, miss_causes

    dt = 1e-3
    n = 12
    index = np.array([*range(10), 0, 1])  # episode 1 starts at row 10
    nan = np.nan
    woke = np.array([0, 0, 900, 0, 0, 0, 0, nan, 800, 0, 900, 0]) * 1e-6
    cpu_step = np.array([100, 100, 100, 100, 950, 100, 100, nan, 100, 950, 100, 100]) * 1e3
    off = np.array([50, 50, 50, 50, 50, 50, 950, nan, 50, 50, 50, 50]) * 1e-6
    cpu = (2 * 75e3 + cpu_step) * 1e-9  # read and observe 75 us each
    t_wake = index * dt + woke
    tt = {
        "index": index,
        "episode": np.array([0] * 10 + [1] * 2),
        # fresh (0), late (1), skipped (2), as the plant's log
        "kind": np.array([0, 0, 1, 0, 1, 0, 1, 2, 1, 1, 1, 0]),
        "t_wake": t_wake,
        "t_write": t_wake + cpu + off,  # NaN: step 7 had no tick
        "cpu_read": np.full(n, 75e3),
        "cpu_observe": np.full(n, 75e3),
        "cpu_step": cpu_step,
    }
    parts = latency_parts(tt, dt)
    ok = np.isfinite(tt["t_write"])
    total = sum(parts.values())[ok]
    np.testing.assert_allclose(total, (tt["t_write"] - index * dt)[ok], atol=1e-12)
    np.testing.assert_allclose(parts["off_cpu"][ok], off[ok], atol=1e-12)
    np.testing.assert_allclose(parts["cpu_work"][ok], cpu[ok], atol=1e-12)
    causes = miss_causes(tt, dt)
    assert causes["late"] == 6
    assert causes["counts"] == {"woke_late": 3, "cpu_work": 2, "off_cpu": 1}
    # events: {2}, {4}, {6, 7, 8, 9} (its first late tick: 6), {10} in the next episode
    assert causes["events"] == 4
    assert causes["event_counts"] == {"woke_late": 2, "cpu_work": 1, "off_cpu": 1}
    assert causes["median_us"] == pytest.approx({"woke_late": 0, "cpu_work": 250, "off_cpu": 50})
    assert causes["late_us"]["woke_late"]["max"] == pytest.approx(900)
    assert causes["late_us"]["cpu_work"]["max"] == pytest.approx(1100)
    assert causes["late_us"]["off_cpu"]["max"] == pytest.approx(950)
    # a run of skipped steps alone (the thread ran after them, on time for its own step)
    skipped_only = dict(tt, kind=np.where(np.arange(n) == 7, 2, 0))
    for k in ("t_wake", "t_write", "cpu_step"):
        skipped_only[k] = tt[k].copy()
    for j in np.flatnonzero(tt["kind"] == 1):  # every tick on time
        skipped_only["t_wake"][j] = index[j] * dt
        skipped_only["cpu_step"][j] = 100e3
        skipped_only["t_write"][j] = index[j] * dt + 300e-6
    causes = miss_causes(skipped_only, dt)
    assert causes["late"] == 0 and causes["events"] == 1
    assert causes["event_counts"] == {"woke_late": 1, "cpu_work": 0, "off_cpu": 0}
    # no missed step: nothing counted
    on_time = {k: v[:2] for k, v in tt.items()}
    none = miss_causes(on_time, dt)
    assert none["events"] == 0 and none["counts"] == {"woke_late": 0, "cpu_work": 0, "off_cpu": 0}


def test_a_stall_before_the_plant_read_is_given_its_cause_from_the_step_waited_for():
    """Hand-made ticks (dt 1 ms) with ``t_due``, the step the clock waited for. The usual tick
    wakes on time, runs 250 us on the CPU and takes 300 us to its torques. Stall A: the clock
    waits for step 3 and the thread wakes at 7.4 ms; the plant catches up (its read 500 us of
    CPU) and returns sample 7, late (steps 3-6 skipped). Stall B: the clock waits for step 12,
    the thread wakes on time, and is held off the CPU until 15.05 ms before its read; the
    plant returns sample 15, on time for its own step (steps 12-14 skipped). Stall C: tick 18
    runs 2.2 ms on the CPU (late), and the plant then returns 20 (step 19 skipped). Without
    ``t_due`` stall A counts as CPU work (the catch-up) and B as a late wake-up: the old
    records cannot tell them apart."""
    import numpy as np

    from hec_jax.realtime.report import latency_parts, miss_causes, page_faults

    dt, n = 1e-3, 24
    index = np.arange(n)
    skipped = np.isin(index, [3, 4, 5, 6, 12, 13, 14, 19])
    nan = np.nan
    due = np.where(skipped, nan, index * dt)
    due[7], due[15], due[20] = 3e-3, 12e-3, 19e-3
    t_wake = due.copy()
    t_wake[7] = 7.4e-3  # woke 4.4 ms after step 3's time
    read = np.where(skipped, nan, 75e3)
    read[7] = 500e3  # [ns] the catch-up's integration
    step = np.where(skipped, nan, 100e3)
    step[18] = 2200e3
    cpu = (read + 75e3 + step) * 1e-9
    off = np.where(skipped, nan, 50e-6)
    off[15] = 15.05e-3 - 12e-3  # held off the CPU between the wake-up and the read
    t_write = t_wake + cpu + off
    for j in (8, 20):  # the tick after a late one wakes when that one has written
        t_wake[j] = t_write[j - 1 if j == 8 else 18]
        t_write[j] = t_wake[j] + cpu[j] + off[j]
    late = t_write >= (index + 1) * dt
    kind = np.where(skipped, 2, np.where(late, 1, 0))
    assert kind[7] == 1 and kind[15] == 0 and kind[18] == 1 and kind[20] == 0
    tt = {
        "index": index,
        "episode": np.zeros(n, int),
        "kind": kind,
        "t_due": due,
        "t_wake": t_wake,
        "t_write": t_write,
        "cpu_read": read,
        "cpu_observe": np.where(skipped, nan, 75e3),
        "cpu_step": step,
    }
    parts = latency_parts(tt, dt)
    ok = ~skipped
    # the parts span each tick's stretch from the step it waited for
    np.testing.assert_allclose(sum(parts.values())[ok], (t_write - due)[ok], atol=1e-12)
    assert parts["woke_late"][7] == pytest.approx(4.4e-3)
    causes = miss_causes(tt, dt)
    assert causes["late"] == 2  # ticks 7 and 18
    assert causes["counts"] == {"woke_late": 1, "cpu_work": 1, "off_cpu": 0}
    # events {3..7} (ended by tick 7: woke late), {12..14} (ended by tick 15, on time for its
    # own step: held off the CPU), {18, 19} (tick 18's CPU work)
    assert causes["events"] == 3
    assert causes["event_counts"] == {"woke_late": 1, "cpu_work": 1, "off_cpu": 1}
    assert causes["late_us"]["woke_late"]["max"] == pytest.approx(4400)
    # the same ticks as recorded before t_due: stall A is the catch-up's CPU work, B a
    # late wake-up by default
    old = {k: v for k, v in tt.items() if k != "t_due"}
    causes = miss_causes(old, dt)
    assert causes["event_counts"] == {"woke_late": 1, "cpu_work": 2, "off_cpu": 0}
    # page faults: a major one in the wait before tick 7 (stall A) and one in tick 10 (on
    # time); minor ones in every tick
    tt["faults_major"] = np.where(skipped, nan, np.isin(index, [7, 10]).astype(float))
    tt["faults_minor"] = np.where(skipped, nan, 2.0)
    faults = page_faults(tt, ~skipped)
    assert faults == {
        "major": 2,
        "minor": 2 * (n - skipped.sum()),
        "ticks_with_major": 2,
        "missed_events_with_major": 1,
    }


def test_every_step_s_deadline_counts_the_skipped_ones():
    """The target's measure (``deadline_latency``): a ticked step's own latency; a skipped
    step waits for the next tick's torques in its episode, or, with none left, for the
    episode's end. Hand-made ticks (dt 1 ms), two episodes: episode 0's steps 3-4 skipped by a
    stall (tick 5 writes 400 us into its period), its last step 6 skipped too; episode 1 on
    time. Then 2000 steps, all ticked on time but for 5 skipped: the ticks' p99.9 is within
    the period, every step's is not (0.25% of the deadlines missed)."""
    from types import SimpleNamespace

    import numpy as np

    from hec_jax.realtime.report import deadline_latency, deadline_report, percentiles

    dt = 1e-3
    nan = np.nan
    index = np.array([0, 1, 2, 3, 4, 5, 6, 0, 1])
    lat_ticked = np.array([300, 300, 2900, nan, nan, 400, nan, 300, 300]) * 1e-6
    tt = {
        "index": index,
        "episode": np.array([0] * 7 + [1] * 2),
        "t_write": index * dt + lat_ticked,
    }
    got = deadline_latency(tt, dt) * 1e6
    expect = [300, 300, 2900, 2400, 1400, 400, 1000, 300, 300]  # 5.4 ms - 3 ms, - 4 ms; 7 - 6
    np.testing.assert_allclose(got, expect, atol=1e-6)
    # 2000 steps, 5 skipped (each followed by a tick on time)
    n = 2000
    index = np.arange(n)
    t_write = index * dt + 300e-6
    t_write[np.arange(100, 2000, 400)] = nan
    tt = {"index": index, "episode": np.zeros(n, int), "t_write": t_write}
    steps = percentiles(deadline_latency(tt, dt), 1e6)
    ticks = percentiles((t_write - index * dt)[np.isfinite(t_write)], 1e6)
    assert steps["n"] == n and ticks["n"] == n - 5
    assert ticks["p99_9"] == pytest.approx(300) and steps["max"] == pytest.approx(1300)
    assert steps["p99_9"] > dt * 1e6
    # the report judges the target on every step, and keeps the ticks' reading beside it
    kind = np.where(np.isfinite(t_write), 0, 2)
    rec = {"kind": kind, "t_wake": index * dt, "t_obs": index * dt + 1e-4}
    rec.update(t_step=index * dt + 2e-4, t_write=t_write)
    rep = deadline_report(SimpleNamespace(ticks=[rec]), dt, None)
    assert rep["control"]["counts"]["skipped"] == 5 and rep["control"]["counts"]["consistent"]
    assert rep["control"]["deadline_latency_us"] == steps
    assert rep["targets"]["p99_9_deadline_within_period"] is False
    assert rep["targets"]["p99_9_tick_latency_within_period"] is True
    # a skipped last step of an episode whose length rounds (n dt - j dt < dt in floats)
    for m in (1500, 3000, 60000):
        last = {"index": np.arange(m), "episode": np.zeros(m, int)}
        last["t_write"] = np.where(np.arange(m) < m - 1, np.arange(m) * dt + 3e-4, nan)
        assert deadline_latency(last, dt)[-1] == dt


def test_in_contact_follows_the_episode_logs():
    from types import SimpleNamespace

    import numpy as np

    from hec_jax.realtime.report import in_contact

    f0 = np.zeros((4, 3))
    f0[2] = [0.0, 0.0, 1.5]  # contact at sample 2 of episode 0
    f1 = np.zeros((3, 3))
    f1[0] = [-2.0, 0.0, 0.0]  # and at sample 0 of episode 1
    run = SimpleNamespace(logs=[{"f_contact": f0}, {"f_contact": f1}])
    tt = {"episode": np.array([0, 0, 0, 0, 1, 1, 1]), "index": np.array([0, 1, 2, 3, 0, 1, 2])}
    np.testing.assert_array_equal(in_contact(run, tt), [0, 0, 1, 0, 1, 0, 0])
    assert in_contact(SimpleNamespace(logs=[{"t": np.zeros(3)}]), tt) is None


def test_measured_age_counts_from_the_last_valid_fit_taken():
    # independent arithmetic: dt 10 ms, episode 0 takes estimates at ticks 2 (the release
    # frame, number 0: not a measurement of the swing), 4 (valid, exposed at 0.03 s) and 7
    # (a failed frame's prediction, exposed at 0.06 s); episode 1 one valid estimate at tick 1.
    # The age of the state in force would restart at tick 7; the measured age does not
    from types import SimpleNamespace

    import numpy as np

    from hec_jax.realtime.report import measured_age

    def arrivals(tick, stamp, number, valid):
        return {
            "tick": np.array(tick, float),
            "t_stamp": np.array(stamp),
            "number": np.array(number, float),
            "valid": np.array(valid, float),
        }

    run = SimpleNamespace(
        arrivals=[
            arrivals([2, 4, 7], [0.0, 0.03, 0.06], [0, 1, 2], [1, 1, 0]),
            arrivals([1], [0.005], [1], [1]),
        ]
    )
    tt = {"episode": np.array([0] * 9 + [1] * 3)}
    age = measured_age(run, tt, 0.01)
    want = [np.nan] * 4 + [0.01, 0.02, 0.03, 0.04, 0.05] + [np.nan, 0.005, 0.015]
    np.testing.assert_allclose(age, want, atol=1e-12)
    old = SimpleNamespace(arrivals=[{k: v for k, v in run.arrivals[0].items() if k != "valid"}])
    assert measured_age(old, tt, 0.01) is None  # runs from before the field


def test_the_real_time_camera_renders_the_simulated_loops_scene():
    """``plant.camera_model``: the void is the plant's own model (no shadows); the lab is the
    room around the plant's world with the lab camera's pose, as the simulated camera loop
    renders it (``render_model_like(scene_model("lab"), ...)``)."""
    import mujoco

    from hec_jax.mjx_scene.lab import scene_model
    from hec_jax.mjx_scene.render import render_model_like
    from hec_jax.realtime.plant import camera_model, plant_model

    task = L.catching().task
    plant = plant_model(task)
    void, shadows = camera_model(task, L.CameraConfig.void_perfect())
    assert not shadows and void.ngeom == plant.ngeom
    lab, shadows = camera_model(task, L.CameraConfig.void_perfect(scene="lab"))
    assert shadows and lab.ngeom == scene_model("lab").ngeom > plant.ngeom
    # RealtimeConfig.camera_shadows overrides the scene's, the model unchanged
    lab_flat, shadows = camera_model(task, L.CameraConfig.void_perfect(scene="lab"), False)
    assert shadows is False and lab_flat.ngeom == lab.ngeom
    assert camera_model(task, L.CameraConfig.void_perfect(), True)[1] is True
    # the planes' render grid (CameraConfig.plane_grid_m), as the simulated loop draws them
    grid, _ = camera_model(task, L.CameraConfig.void_perfect(plane_grid_m=0.05))
    planes = grid.geom_type == int(mujoco.mjtGeom.mjGEOM_PLANE)
    np.testing.assert_array_equal(grid.geom_size[planes, 2], 0.05)
    np.testing.assert_array_equal(grid.geom_size[~planes], void.geom_size[~planes])
    assert np.all(void.geom_size[planes, 2] == plant.geom_size[planes, 2])
    # the plant's world (moved hinge, rod) sits on scene.xml's rows, the room after them
    np.testing.assert_array_equal(lab.body_pos[: plant.nbody], plant.body_pos)
    np.testing.assert_array_equal(lab.geom_size[: plant.ngeom], plant.geom_size)
    want = render_model_like(scene_model("lab"), plant)
    poses = []
    for m in (lab, want, void):  # the camera's pose only: no renderer needed
        data = mujoco.MjData(m)
        mujoco.mj_kinematics(m, data)
        mujoco.mj_camlight(m, data)
        cid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_CAMERA, "eye")
        poses.append(np.concatenate([data.cam_xpos[cid], data.cam_xmat[cid]]))
    np.testing.assert_array_equal(poses[0], poses[1])
    assert np.linalg.norm(poses[0][:3] - poses[2][:3]) > 0.1  # the lab's camera is elsewhere


def test_host_steal_is_read_per_cpu_from_proc_stat(tmp_path):
    # a /proc/stat as Linux writes it: the steal is the 8th number of each cpuN line, in clock
    # ticks (SC_CLK_TCK per second)
    from hec_jax.realtime.clock import _CLOCK_TICKS, host_steal_ms

    stat = tmp_path / "stat"
    stat.write_text(
        "cpu  10 0 5 100 0 0 0 7 0 0\n"
        "cpu0 5 0 2 50 0 0 0 3 0 0\n"
        "cpu1 5 0 3 50 0 0 0 4 0 0\n"
        "intr 12 0\nctxt 99\n"
    )
    assert host_steal_ms(str(stat)) == [3e3 / _CLOCK_TICKS, 4e3 / _CLOCK_TICKS]
    stat.write_text("cpu0 5 0 2 50\n")  # no steal column (old kernels)
    assert host_steal_ms(str(stat)) == []
    assert host_steal_ms(str(tmp_path / "missing")) == []
    if os.path.exists("/proc/stat"):
        assert len(host_steal_ms()) in (0, os.cpu_count())


def test_the_eye_publishes_each_estimate_before_its_bookkeeping(monkeypatch):
    """``workers.eye_main`` in this process, with a stand-in camera and tracker: each frame's
    estimate is written to the board before the frame's CPU and steal readings (a camera at
    real-time priority on the eye's CPU preempts it at each exposure's end, and an estimate
    done but not yet written waited for the whole render: docs/realtime.md, session 83). The
    published vectors are those of before (``np.nan_to_num``, zeros while unseen), and the log
    records when each was written."""
    import queue
    import threading
    from types import SimpleNamespace

    from hec_jax.realtime import clock as rt_clock
    from hec_jax.realtime import workers

    events: list[str] = []
    monkeypatch.setattr(rt_clock, "host_steal_ms", lambda: events.append("steal") or [0.0, 0.0])
    cpu_time = time.process_time
    monkeypatch.setattr(workers.time, "process_time", lambda: events.append("cpu") or cpu_time())

    class StandInMeter:  # no listener left registered with jax.monitoring
        ms, events = 0.0, 0

        def install(self):
            return self

    monkeypatch.setattr(workers, "CompileMeter", StandInMeter)
    image = np.zeros((240, 320, 3), np.uint8)
    # the tracker's state per frame: none yet (released, not acquired), then one with a NaN
    # velocity component (published as 0), then a finite one
    position = np.array([0.01, 0.02, 0.9])
    states = [
        dict(initialised=False, valid=False, velocity=np.zeros(3)),
        dict(initialised=True, valid=True, velocity=np.array([np.nan, 0.0, 0.5])),
        dict(initialised=True, valid=True, velocity=np.array([0.1, 0.0, -0.2])),
    ]

    class StandInTracker:
        def __init__(self, *args, **kwargs):
            self.frames = 0

        def warm_up(self, image, occluded):
            pass

        def reset(self):
            pass

        def skip(self, frames):
            pass

        def predict(self, dt):
            return None

        def update(self, image, occluded):
            events.append("update")
            s = states[self.frames]
            self.frames += 1
            timing = {"detection_ms": 0.0, "estimation_ms": 0.0}
            st = dict(position=position, acceleration=np.zeros(3), timing_ms=timing)
            return SimpleNamespace(**st, **s, fit_source="tracked" if s["valid"] else "")

    monkeypatch.setattr("hec_jax.geometry.BoxTracker", StandInTracker)
    stop = threading.Event()

    class StandInCamera:
        calibration = SimpleNamespace(ready=lambda n: True)

        def background(self):
            return image

        def release_frame(self):
            return image

        def latest(self, last):
            if last + 1 == len(states):
                stop.set()
                return None
            k = last + 1
            return SimpleNamespace(
                index=k,
                episode=0,
                number=k,
                image=image,
                q_arm=np.zeros(3),
                t_exposure=0.033 * k,
                t_wall_exposure=time.monotonic(),
            )

    class RecordingBoard:
        def __init__(self):
            self.written = []

        def write(self, **values):
            events.append("write")
            self.written.append(values)

    cam = L.CameraConfig.void_perfect(width=320, height=240, self_mask_margin_m=None)
    board, logs = RecordingBoard(), queue.Queue()
    workers.eye_main(
        L.catching(eye="camera", camera=cam).task,
        cam,
        30.0,
        L.build_loop(L.catching().task).q_home,
        StandInCamera(),
        board,
        bool(jax.config.jax_enable_x64),
        None,
        ready=threading.Event(),
        stop=stop,
        log_queue=logs,
    )
    log = logs.get_nowait()
    assert "error" not in log, log.get("error")
    # per frame: the readings at its start, the tracker, the write (every frame: the release
    # frame is always answered), and only then the readings at its end
    assert events == ["cpu", "steal", "update", "write", "cpu", "steal"] * len(states)
    assert log["t_wall_published"].shape == (len(states),)
    assert np.all(log["t_wall_published"] >= log["t_wall_done"])
    # the published vectors: as np.nan_to_num did before, zeros where the eye has not seen
    for values, s, x_est, xd_est in zip(
        board.written, states, log["x_est"], log["xd_est"], strict=True
    ):
        if not s["initialised"]:
            assert values["seen"] == 0.0 and np.all(np.isnan(x_est))
            np.testing.assert_array_equal(values["x"], np.zeros(2))
            np.testing.assert_array_equal(values["xd"], np.zeros(2))
            continue
        assert values["seen"] == 1.0
        np.testing.assert_array_equal(values["x"], np.nan_to_num(x_est))
        np.testing.assert_array_equal(values["xd"], np.nan_to_num(xd_est))
    assert np.isnan(log["xd_est"][1][0]) and board.written[1]["xd"][0] == 0.0


def test_the_published_vectors_are_nan_to_num_of_the_state():
    """``workers._board_vector``: ``np.nan_to_num`` (NaN to 0, infinities to the largest
    finite numbers), the same array where finite, zeros where unseen."""
    from hec_jax.realtime.workers import _board_vector

    for v in (
        np.array([0.25, -1.5]),
        np.array([np.nan, 2.0]),
        np.array([np.inf, -np.inf]),
        np.array([-0.0, np.nan]),
    ):
        got = _board_vector(v, True)
        np.testing.assert_array_equal(got, np.nan_to_num(v))
        assert np.array_equal(np.signbit(got), np.signbit(np.nan_to_num(v)))
        np.testing.assert_array_equal(_board_vector(v, False), np.zeros(2))
    finite = np.array([0.25, -1.5])
    assert _board_vector(finite, True) is finite


def test_slow_frames_are_the_ones_published_after_a_frame_period():
    # four frames of a 30 fps eye, exposed at wall times 0, 1/30, 2/30, 3/30 s; frame 0 is the
    # release frame (not counted); frames 1 and 3 take 40 and 35 ms from exposure to estimate
    from hec_jax.geometry.track import FIT_SOURCES
    from hec_jax.realtime.report import slow_frames
    from hec_jax.realtime.workers import _steal_delta

    exposure = np.arange(4) / 30
    eye_log = {
        "index": np.arange(4),
        "episode": np.zeros(4, int),
        "number": np.arange(4),
        "t_wall_exposure": exposure,
        "t_wall_done": exposure + np.array([0.2, 0.040, 0.010, 0.035]),
        "eye_ms": np.array([150.0, 30, 4, 5]),
        "eye_cpu_ms": np.array([140.0, 5, 4, 5]),
        "eye_steal_ms": np.array([[0, 0], [0, 20], [0, 0], [0, 0]], float),
        "fit_source": np.array([FIT_SOURCES.index("tracked")] * 3 + [FIT_SOURCES.index("")]),
    }
    camera_log = {
        "index": np.arange(4),
        "render_ms": np.array([6.0, 7, 6, 25]),
        "render_cpu_ms": np.array([6.0, 7, 6, 6]),
        "render_steal_ms": np.array([[0, 0], [0, 0], [0, 0], [0, 10]], float),
    }
    out = slow_frames(camera_log, eye_log, 1e3 / 30)
    assert out["over_one_period"] == 2
    first, second = out["frames"]
    assert (first["index"], second["index"]) == (1, 3)
    assert first["pipeline_ms"] == pytest.approx(40) and second["pipeline_ms"] == pytest.approx(35)
    assert first["eye_steal_ms"] == [0, 20] and second["render_steal_ms"] == [0, 10]
    assert (first["render_ms"], second["render_cpu_ms"]) == (7, 6)
    assert (first["fit_source"], second["fit_source"]) == ("tracked", "invalid")
    assert slow_frames(camera_log, eye_log, 1e3 / 30, limit=1)["frames"] == [first]
    assert "jax_compile_ms" not in first  # logs before session 47
    assert "control_missed" not in first and "with_control_missed" not in out  # no tick table
    # the control loop's missed steps during each slow frame: an episode whose time 0 is at
    # wall time -0.5 s (dt 1 ms), so step j's deadline is at -0.5 + (j + 1) 1e-3 s. Frame 1's
    # window [1/30, 1/30 + 0.040] holds the deadlines of steps 533-572: steps 540-544 (a run of
    # 5) and 560 missed there; frame 3's [0.1, 0.135] (steps 600-634) none, 650 after it
    n = 700
    kind = np.zeros(n, np.int8)
    kind[[540, 541, 542, 543, 544, 560, 650]] = [2, 2, 2, 2, 1, 1, 2]
    ticks = {"t_origin": np.full(n, -0.5), "index": np.arange(n), "kind": kind}
    timed = slow_frames(camera_log, eye_log, 1e3 / 30, ticks=ticks, dt=1e-3)
    assert timed["with_control_missed"] == 1
    assert [(f["control_missed"], f["control_longest_miss_ms"]) for f in timed["frames"]] == [
        (6, pytest.approx(5.0)),
        (0, 0.0),
    ]
    # the same steps in a second episode's rows (another time 0) do not count for these frames
    ticks2 = {k: np.concatenate([v, v]) for k, v in ticks.items()}
    ticks2["t_origin"][n:] = 100.0
    timed2 = slow_frames(camera_log, eye_log, 1e3 / 30, ticks=ticks2, dt=1e-3)
    assert timed2 == timed
    eye_log["jax_compile_ms"] = np.array([900.0, 0, 0, 12.5])
    compiled = slow_frames(camera_log, eye_log, 1e3 / 30)["frames"]
    assert [f["jax_compile_ms"] for f in compiled] == [0, 12.5]
    np.testing.assert_array_equal(_steal_delta([1.0, 2.0], [1.0, 12.0]), [0, 10])
    # a reading failed: NaN for each CPU (every row as long); none accounted: empty
    assert np.isnan(_steal_delta([1.0, 2.0], [])).tolist() == [True, True]
    assert _steal_delta([], []).size == 0
    from hec_jax.realtime.report import _steal_total

    assert _steal_total([[0.0, 10.0], [np.nan, np.nan], [10.0, 0.0]]) == [10.0, 10.0]
    assert _steal_total(np.zeros((3, 0))) is None


def test_compile_meter_counts_a_first_use_and_not_a_cached_call():
    # ground truth: a function jitted here is traced, lowered and compiled on its first call,
    # and its second call with the same shapes hits JAX's in-memory cache: nothing recorded
    from hec_jax.report import CompileMeter

    x3, x4 = jnp.ones(3), jnp.ones(4)  # made (and their programs compiled) before the meter
    meter = CompileMeter().install()
    try:
        fn = jax.jit(lambda x: jnp.sin(x) * 2.5)  # a new function object: never traced
        fn(x3).block_until_ready()
        first_ms, first_events = meter.ms, meter.events
        # one program: its trace, its lowering and the backend's compile
        assert (first_events, meter.compilations) == (3, 1) and first_ms > 0
        fn(x3).block_until_ready()
        assert (meter.ms, meter.events, meter.compilations) == (first_ms, 3, 1)
        fn(x4).block_until_ready()  # a new shape: traced and compiled again
        assert (meter.events, meter.compilations) == (6, 2)
    finally:
        meter.uninstall()


def test_render_cpu_by_second_is_the_spread_of_per_second_medians():
    # hand-made log: 3 whole seconds of 30 frames (medians 6, 9 and 12 ms, an outlier in the
    # second) and a last partial second of 2 frames (too few: left out)
    from hec_jax.realtime.report import render_cpu_by_second

    t = np.concatenate([100.0 + np.arange(90) / 30, [103.0, 103.02]])
    cpu = np.concatenate([np.full(30, 6.0), np.full(30, 9.0), np.full(30, 12.0), [50.0, 50.0]])
    cpu[45] = 40.0  # one slow render does not move its second's median
    got = render_cpu_by_second({"t_wall_start": t, "render_cpu_ms": cpu})
    assert (got["n"], got["min"], got["p50"], got["max"]) == (3, 6.0, 9.0, 12.0)
    assert got["max_over_min"] == 2.0
    assert render_cpu_by_second({"t_wall_start": t[:3], "render_cpu_ms": cpu[:3]}) is None
    assert render_cpu_by_second({"t_wall_start": [], "render_cpu_ms": []}) is None


def test_child_env_xla_flags_are_flags_xla_knows():
    """Each token of the child processes' ``XLA_FLAGS`` is a ``--`` flag (XLA skips a token
    without ``--`` silently) that XLA accepts: a JAX process started with them computes (an
    unknown flag aborts XLA at start-up).
    """
    import subprocess
    import sys

    from hec_jax.realtime.plant import _child_env

    flags = _child_env.SETTINGS["XLA_FLAGS"].split()
    assert flags and all(f.startswith("--") for f in flags), flags
    env = dict(os.environ, XLA_FLAGS=" ".join(flags), JAX_PLATFORMS="cpu")
    code = "import jax.numpy as jnp; print(float(jnp.ones(3).sum()))"
    done = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip() == "3.0"


def test_the_camera_twin_uses_estimates_as_old_as_the_runs():
    """``twin_camera_latency_s``: with it, the simulated camera loop first uses a frame's
    estimate the run's median latency (in whole steps) after the state the frame shows. Checked
    through the loop's own machinery: its frame grid (``frame_steps``, ``exposure_offsets``), the
    estimate queue (``_eye_input``) and the switch inside a segment (``eye_object_state``) on a
    time that is a running float64 sum of steps, as MJX's, for three exposures and frames all
    over a swing; a median shorter than half the exposure gives no latency; bad medians are
    refused."""
    from hec_jax.loop.camera_loop import _Estimate, _eye_input, exposure_offsets, frame_steps
    from hec_jax.loop.object_state import eye_object_state
    from hec_jax.realtime.runner import twin_camera_latency_s

    dt, z = 1e-3, np.zeros(2)
    for exposure_s in (0.0, 0.004, 0.010):
        cam = dataclasses.replace(L.CameraConfig.void_perfect(), exposure_s=exposure_s)
        back = int(exposure_offsets(cam, dt)[-1])  # the frame's state, steps before its end
        fs = frame_steps(cam, dt, 3000)
        times = np.cumsum(np.full(3000, dt)) - dt  # the loop's time: a running sum of steps
        for p50_ms in (6, 11, 12, 20, 40):
            latency = twin_camera_latency_s(p50_ms * 1e-3, cam, dt)
            for j in range(1, len(fs) - 2, 7):
                s = int(fs[j])
                old = _Estimate(0.0, 0.0, z, z, z)
                new = _Estimate(s * dt + latency, (s - back) * dt, z + 1.0, z, z)
                used = None
                for k in range(s, int(fs[j + 2])):  # the segments of frames j and j + 1
                    seg = int(fs[j] if k < fs[j + 1] else fs[j + 1])
                    nxt = int(fs[j + 1] if k < fs[j + 1] else fs[j + 2])
                    eye = _eye_input([old, new], times[seg], times[nxt], 0.0, 0.0)
                    x, _, _ = eye_object_state(jax.tree_util.tree_map(jnp.asarray, eye), times[k])
                    if float(x[0]) == 1.0:
                        used = k
                        break
                assert used is not None and used - (s - back) == max(p50_ms, back), (p50_ms, j)
        assert twin_camera_latency_s(0.0, cam, dt) == 0.0
    with pytest.raises(ValueError, match="latency_p50_s"):
        twin_camera_latency_s(float("nan"), L.CameraConfig.void_perfect(), dt)
    with pytest.raises(ValueError, match="twin_latency"):
        RT.RealtimeConfig(twin_latency="median")


def test_idle_filler_keeps_the_cpus_busy_at_idle_priority_and_leaves_nothing_behind():
    """``clock.idle_filler``: one process per CPU, pinned there at ``SCHED_IDLE``, never
    sleeping (running or runnable: its state "R", also when a busy CPU starves it), killed and
    reaped on exit; None starts nothing; an unknown kind is refused before anything starts."""
    import subprocess
    import sys
    import time

    from hec_jax.realtime.clock import idle_filler

    def state(pid):
        try:
            return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except FileNotFoundError:
            return "gone"

    cpu = max(os.sched_getaffinity(0))
    with idle_filler("spin", {cpu}) as filler:
        (proc,) = filler.procs
        assert os.sched_getscheduler(proc.pid) == os.SCHED_IDLE
        assert os.sched_getaffinity(proc.pid) == {cpu}
        # started (it said so before its priority was lowered); a starved filler reads "R" too
        states = {state(proc.pid) for _ in range(200) if time.sleep(0.005) is None}
        assert states == {"R"} and proc.poll() is None
    assert proc.poll() is not None and filler.procs == []
    # a parent killed without its clean-up takes its fillers with it
    parent = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import time\nfrom hec_jax.realtime.clock import idle_filler\n"
            f"with idle_filler('spin', {{{cpu}}}) as f:\n"
            "    print(f.procs[0].pid, flush=True)\n    time.sleep(60)\n",
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    orphan = int(parent.stdout.readline())  # bound to its parent before this line came
    assert state(orphan) == "R"
    parent.kill()
    parent.wait()
    # gone, or a zombie waiting for its new parent to reap it. At SCHED_IDLE on a CPU kept busy
    # (the other test worker) even dying waits for a time slice: measured 0.4-1.4 s there, so
    # the wait is bounded by a minute, not by a time the claim is about
    t0 = time.monotonic()
    while (now := state(orphan)) not in ("Z", "X", "gone"):
        assert time.monotonic() - t0 < 60, now
        time.sleep(0.01)
    with idle_filler(None, {cpu}) as filler:
        assert filler.procs == []
    with pytest.raises(ValueError, match="idle filler"):
        idle_filler("busy", {cpu})
    with pytest.raises(ValueError, match="idle_filler"):
        RT.RealtimeConfig(idle_filler="busy")


def _synthetic_eye_episode(lost_after_s: float | None, n: int = 3000, dt: float = 1e-3):
    """A 3 s episode on time: an estimate of every 33rd step's exposure taken 20 steps later,
    seen until the exposure passes ``lost_after_s`` (None: always), then reported lost (the
    controller's state then has no eye estimate in force: its stamp is NaN, as in run_loop)."""
    from types import SimpleNamespace

    j = np.arange(n)
    exposures = np.arange(0, n, 33)
    ticks = np.where(exposures > 0, exposures + 20, 0)
    keep = ticks < n
    exposures, ticks = exposures[keep], ticks[keep]
    seen = np.ones(len(ticks)) if lost_after_s is None else (exposures * dt < lost_after_s) * 1.0
    stamp, cur, at = np.full(n, np.nan), np.nan, {int(t): k for k, t in enumerate(ticks)}
    for t in j:
        if t in at:
            k = at[t]
            cur = exposures[k] * dt if seen[k] > 0 else np.nan
        stamp[t] = cur
    rec = {"kind": np.zeros(n, int), "t_wake": j * dt, "t_obs": j * dt + 1e-4}
    rec.update(t_step=j * dt + 2e-4, t_write=j * dt + 3e-4, t_stamp=stamp)
    zeros = np.zeros(len(ticks))
    arrival = {
        "tick": ticks * 1.0,
        "t_tick": ticks * dt,
        "t_stamp": exposures * dt,
        "frame": np.arange(len(ticks)) * 1.0,
        "number": np.arange(len(ticks)) * 1.0,
        "seen": seen,
        "valid": seen,
        "t_wall_exposure": zeros,
        "t_wall_done": zeros,
        "t_wall_taken": zeros,
    }
    return SimpleNamespace(ticks=[rec], arrivals=[arrival], logs=[{"f_contact": np.zeros((n, 3))}])


def _two_frame_run(n: int = 200, dt: float = 1e-3, origin: float = 100.0):
    """An episode of ``n`` steps with frames exposed every 33 steps (wall time ``origin`` + the
    exposure), each rendered 0.2-8.2 ms after its exposure and taken by the loop 20 steps
    after it, but frame 2: its eye ran 9.0-43.5 ms after its exposure (frame 3's render,
    33.2-41.2 ms, inside it), wrote its estimate 0.05 ms later and the loop took it at 45.2 ms
    (tick 111). Steps 80 (skipped) and 110 (late) missed their deadlines; the hand touched the
    object at step 110. Returns (run, tick table, camera log, eye log)."""
    from types import SimpleNamespace

    exposures = np.arange(0, n, 33)
    latency = np.full(len(exposures), 0.020)
    latency[0], latency[2] = 0.001, 0.0452
    ticks = exposures + np.floor(latency / dt + 1e-9).astype(int)
    keep = ticks < n
    exposures, latency, ticks = exposures[keep], latency[keep], ticks[keep]
    wall_exposure = origin + exposures * dt
    eye_start = wall_exposure + 0.009
    eye_done = np.where(exposures == 66, wall_exposure + 0.0435, wall_exposure + 0.015)
    stamp, cur = np.full(n, np.nan), np.nan
    for j in range(n):
        if j in ticks:
            cur = exposures[list(ticks).index(j)] * dt
        stamp[j] = cur
    kind = np.zeros(n, int)
    kind[80], kind[110] = 2, 1
    stamp[80] = np.nan  # a skipped step has no tick
    frames = np.arange(len(exposures))
    run = SimpleNamespace(
        arrivals=[
            {
                "tick": ticks * 1.0,
                "t_tick": ticks * dt,
                "t_stamp": exposures * dt,
                "frame": frames * 1.0,
                "number": frames * 1.0,
                "seen": np.ones(len(frames)),
                "valid": np.ones(len(frames)),
                "t_wall_exposure": wall_exposure,
                "t_wall_done": eye_done,
                "t_wall_taken": wall_exposure + latency,
            }
        ],
        logs=[{"f_contact": np.where(np.arange(n)[:, None] == 110, 1.0, 0.0) * np.ones(3)}],
    )
    tt = {
        "episode": np.zeros(n, int),
        "index": np.arange(n),
        "kind": kind,
        "t_stamp": stamp,
        "t_origin": np.full(n, origin),
    }
    camera_log = {
        "index": frames,
        "t_wall_start": wall_exposure + 0.0002,
        "t_wall_done": wall_exposure + 0.0082,
        "t_wall_put": wall_exposure + 0.0083,
        # frames 2 and 3 rendered at 2.25x and 2.5x the median CPU time (4 ms): a slow CPU
        "render_cpu_ms": np.array([4.0, 4.0, 9.0, 10.0, 4.0, 4.0])[: len(frames)],
    }
    eye_log = {
        "index": frames,
        "t_wall_start": eye_start,
        "t_wall_done": eye_done,
        "t_wall_published": eye_done + 5e-5,
        # frame 2: 2.4x the median of the five tracked fits (10 ms; 11 with the stopped fit's)
        "eye_cpu_ms": np.array([6.0, 8.0, 24.0, 10.0, 12.0, 30.0])[: len(frames)],
        "fit_source": np.array([1, 1, 1, 1, 1, 2])[: len(frames)],
    }
    return run, tt, camera_log, eye_log


def test_the_oldest_state_is_split_into_the_stages_of_the_estimate_that_ended_it():
    """``report.oldest_state`` on a hand-made episode: the age peaks at 77 ms at step 110 (frame
    1's estimate, exposed at 33 ms, still in force), and frame 2's estimate ends it; its 45.2 ms
    from exposure to taking split by hand: 0.2 to the render, 8.0 render, 0.8 read out and
    queued, 34.5 eye (8.0 of it frame 3's render), 1.7 done to taken, written 0.05 after done;
    one control step missed between done and taken, two over the whole latency."""
    from hec_jax.realtime.report import oldest_state, oldest_text

    run, tt, camera_log, eye_log = _two_frame_run()
    o = oldest_state(run, tt, 1e-3, camera_log, eye_log)
    assert (o["episode"], o["tick"], o["in_contact"]) == (0, 110, True)
    assert o["age_ms"] == pytest.approx(77.0)
    b = o["ended_by"]
    assert (b["frame"], b["number"], b["tick"], b["valid"]) == (2, 2, 111, True)
    assert b["latency_ms"] == pytest.approx(45.2)
    expected = {
        "to_render": 0.2,
        "render": 8.0,
        "read_out_and_queued": 0.8,
        "eye": 34.5,
        "done_to_taken": 1.7,
    }
    assert b["stages_ms"] == pytest.approx(expected, abs=1e-6)
    assert sum(b["stages_ms"].values()) == pytest.approx(b["latency_ms"])
    assert b["renders_during_eye_ms"] == pytest.approx(8.0)
    assert b["done_to_written_ms"] == pytest.approx(0.05)
    assert (b["eye_cpu_ms"], b["fit_source"]) == (24.0, "tracked")
    assert b["eye_cpu_vs_median"] == pytest.approx(2.4)
    assert b["render_cpu_vs_median"] == pytest.approx([2.25, 2.5])
    assert (b["control_missed_done_to_taken"], b["control_missed_in_latency"]) == (1, 2)
    text = oldest_text({"oldest_state": o})
    assert text.startswith("episode 0, step 110: 77 ms (in contact); frame 2's estimate")
    assert (
        "eye 34.5 (CPU 24.0, 2.40x the median of its fit source; later renders in it 8.0; "
        "tracked)" in text
    )
    assert "control steps missed meanwhile 1" in text
    assert text.endswith("render CPU this frame's / the next's 2.25x / 2.50x the median)")
    assert json.loads(json.dumps(o)) == o  # as deadline.json keeps it
    # the camera's log lacks the next frame: no next render; without CPU times, no ratios
    short = {k: np.delete(v, 3) for k, v in camera_log.items()}
    ended = oldest_state(run, tt, 1e-3, short, eye_log)["ended_by"]
    assert ended["render_cpu_vs_median"][0] == pytest.approx(9.0 / 4.0)
    assert ended["render_cpu_vs_median"][1] is None
    assert "render CPU this frame's / the next's 2.25x / - the median" in oldest_text(
        {"oldest_state": oldest_state(run, tt, 1e-3, short, eye_log)}
    )
    # the logs' rows are not the frames' indices: the camera's log without frame 0's render,
    # the eye's without frame 0 and with a frame 6 the loop never took (tracked, 9 ms)
    cam_from_1 = {k: np.delete(v, 0) for k, v in camera_log.items()}
    extra = {"index": 6, "fit_source": 1, "eye_cpu_ms": 9.0}
    eye_from_1 = {
        k: np.append(np.delete(v, 0), extra.get(k, v[-1] + 0.033)) for k, v in eye_log.items()
    }
    ended = oldest_state(run, tt, 1e-3, cam_from_1, eye_from_1)["ended_by"]
    assert ended["frame"] == 2 and ended["eye_cpu_ms"] == 24.0
    assert ended["eye_cpu_vs_median"] == pytest.approx(2.4)  # tracked: 8, 24, 10, 12, 9
    assert ended["render_cpu_vs_median"] == pytest.approx([2.25, 2.5])
    # a fit source with fewer than 5 frames in the run: no median to hold the frame against
    rare = dict(eye_log, fit_source=np.array([1, 1, 2, 1, 1, 2]))
    ended = oldest_state(run, tt, 1e-3, camera_log, rare)["ended_by"]
    assert ended["fit_source"] == "stopped" and ended["eye_cpu_vs_median"] is None
    assert "(CPU 24.0; later renders" in oldest_text(
        {"oldest_state": oldest_state(run, tt, 1e-3, camera_log, rare)}
    )
    plain_cam = {k: v for k, v in camera_log.items() if k != "render_cpu_ms"}
    plain_eye = {k: v for k, v in eye_log.items() if k != "eye_cpu_ms"}
    ended = oldest_state(run, tt, 1e-3, plain_cam, plain_eye)["ended_by"]
    assert "render_cpu_vs_median" not in ended and "eye_cpu_vs_median" not in ended
    # without the camera's and eye's logs: the estimate, not its stages
    bare = oldest_state(run, tt, 1e-3)["ended_by"]
    assert "stages_ms" not in bare and bare["latency_ms"] == pytest.approx(45.2)
    # no estimate after the oldest tick (the eye silent from step 150 on): none ended it
    silent = dict(run.arrivals[0])
    kept = silent["tick"] < 150
    run.arrivals[0] = {k: v[kept] for k, v in silent.items()}
    tt["t_stamp"][150:] = tt["t_stamp"][149]
    o = oldest_state(run, tt, 1e-3, camera_log, eye_log)
    assert (o["tick"], o["ended_by"]) == (199, None)
    assert o["age_ms"] == pytest.approx(199 - 99)
    assert oldest_text({"oldest_state": o}).endswith("no estimate after it in the episode")
    # no estimate in force at all
    tt["t_stamp"][:] = np.nan
    assert oldest_state(run, tt, 1e-3) is None


def test_the_eye_age_target_fails_when_the_eye_has_lost_the_cube():
    """An eye that tracks for 0.5 s and then reports the cube lost: the age of the estimates in
    force stays at 52 ms at most (within two frame periods), but 2.5 s of ticks have no eye state at
    all, and the target says so. The same episode with the cube seen throughout passes."""
    from hec_jax.realtime.report import deadline_report

    fps = 1 / 0.033
    lost = deadline_report(_synthetic_eye_episode(0.5), 1e-3, fps)
    assert lost["eye"]["age_ms"]["max"] == pytest.approx(52.0)
    assert lost["eye"]["ticks_without_estimate"] > 2400
    assert lost["targets"]["eye_age_within_two_frame_periods"] is False
    kept = deadline_report(_synthetic_eye_episode(None), 1e-3, fps)
    assert kept["eye"]["ticks_without_estimate"] == 0
    assert kept["eye"]["age_ms"]["max"] == pytest.approx(52.0)
    assert kept["targets"]["eye_age_within_two_frame_periods"] is True


class _StandInCamera:
    """``SceneCamera`` for ``workers.camera_main`` without rendering: black 8 x 8 frames."""

    def __init__(self, m, *args, **kwargs):
        import mujoco

        self.data = mujoco.MjData(m)

    def render(self, q):
        return np.zeros((8, 8, 3), np.uint8)

    def close(self):
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        pass


def _camera_main_on_steps(monkeypatch, steps, exposure_back):
    """``workers.camera_main`` (a stand-in renderer, frames every 33 steps) on a scripted plant
    board whose every read is the next of ``steps`` (a step of episode 0, or (episode, step)),
    stopping the camera once they are used up: its log, and per frame put in the ring (episode,
    number, the board's step at the put, t_exposure), and the events in order: ("read", step),
    ("sleep", s) and ("put", number)."""
    import queue
    import threading

    from hec_jax.mjx_scene import render as render_module
    from hec_jax.realtime import workers
    from hec_jax.realtime.shared import Images

    monkeypatch.setattr(render_module, "SceneCamera", _StandInCamera)
    cam = L.CameraConfig.void_perfect(width=8, height=8)
    exp = L.catching(eye="camera", camera=cam)
    nq = RT.plant_model(exp.task).nq
    stop = threading.Event()
    events = []
    sleep = time.sleep
    monkeypatch.setattr(workers.time, "sleep", lambda s: events.append(("sleep", s)) or sleep(s))

    class ScriptedBoard:
        def __init__(self):
            self.k, self.last = 0, None

        @property
        def seq(self):
            if self.k >= len(steps):
                stop.set()
            return 2 * (self.k + 1)

        def read(self):
            if self.k >= len(steps) - 1:
                stop.set()  # also for a camera waiting on an exposure's end
            at = steps[min(self.k, len(steps) - 1)]
            episode, step = at if isinstance(at, tuple) else (0, at)
            self.k += 1
            self.last = step
            events.append(("read", step))
            rec = {"t": step * 1e-3, "step": step, "episode": episode, "t_wall": 0.0}
            return 2 * self.k, {**rec, "t_clock": np.nan, "qpos": np.zeros(nq)}

    class Ring:
        def __init__(self, board):
            self.board, self.put_at = board, []

        def put(self, index, image, **meta):
            events.append(("put", int(meta["number"])))
            self.put_at.append(
                (int(meta["episode"]), int(meta["number"]), self.board.last, meta["t_exposure"])
            )

    board = ScriptedBoard()
    ring = Ring(board)
    log_queue = queue.Queue()
    workers.camera_main(
        exp.task, cam, 33, np.zeros(nq), board, ring, Images(2, 8, 8),
        stop=stop, log_queue=log_queue, dt=1e-3, exposure_back=exposure_back,
    )  # fmt: skip
    log = log_queue.get(timeout=10)
    assert "error" not in log, log.get("error")
    monkeypatch.setattr(workers.time, "sleep", sleep)
    return log, ring.put_at, events


def test_a_stalled_camera_renders_the_newest_frame_time_not_an_old_one(monkeypatch):
    """The camera (``workers.camera_main``, a stand-in renderer), its frames showing the state at
    the exposure's end, renders frame 0 at step 0, then is held off until step 118: frames 1-3
    (due at steps 33, 66, 99) have all come. It renders frame 3, 19 steps late, and counts
    frames 1 and 2 as skipped. It used to render frame 1 there, 85 steps late, which the eye
    would fit as the state of step 33."""
    # frame 0 at step 0 (then the read after its render), then the stall: step 118
    log, *_ = _camera_main_on_steps(monkeypatch, [0, 1, 118, 119], exposure_back=0)
    assert log["number"].tolist() == [0, 3] and log["step"].tolist() == [0, 118]
    assert log["skipped"] == 2


def test_the_camera_shows_the_states_the_simulated_camera_loop_shows(monkeypatch):
    """With a 4 ms exposure, the simulated camera loop's frame ``j`` shows the state at
    mid-exposure, step ``max(33 j - 2, 0)``. The real-time camera (``workers.camera_main``, a
    stand-in renderer, the plant's board stepping once per read) renders the same steps, stamps
    their plant time and puts no frame in the ring before the board reaches its exposure's end
    (``33 j``). It used to render steps ``33 j``: the two loops' frames fell 2 ms apart in every
    swing, and the real-time runs learned 2-3 times their twins' vertical damping
    (docs/realtime.md). After a stall to step 118 it renders frame 3 (due at step 97) from the
    state there is, step 118, and counts frames 1 and 2 skipped. A frame whose state comes
    before its episode ends but whose exposure would end after it (episode 0 ends at step 97,
    frame 3's exposure at 99) is not put, and counted."""
    from hec_jax.loop.camera_loop import exposure_offsets, frame_steps

    cam = L.CameraConfig.void_perfect()
    assert cam.exposure_s == pytest.approx(0.004)
    back = int(exposure_offsets(cam, 1e-3)[-1])
    assert back == 2
    log, put_at, _ = _camera_main_on_steps(monkeypatch, list(range(200)), back)
    want = np.maximum(frame_steps(cam, 1e-3, 200) - back, 0)  # the simulated loop's s_img
    assert want.tolist() == [0, 31, 64, 97, 130, 163, 196]
    # the last frame's exposure ends at step 198 and the board stops at 199: all 7 are put
    assert log["step"].tolist() == want.tolist() and log["step_due"].tolist() == want.tolist()
    assert log["number"].tolist() == list(range(7)) and log["skipped"] == 0
    for _, number, board_step, t_exposure in put_at:
        assert board_step >= 33 * number  # read out once the exposure has ended
        assert t_exposure == pytest.approx(want[number] * 1e-3)
    assert [p[1] for p in put_at] == list(range(7)) and log["not_read_out"] == 0
    assert np.all(log["t_wall_put"] >= log["t_wall_done"])
    log, *_ = _camera_main_on_steps(monkeypatch, [0, 1, 118, 119], back)  # a stall
    assert log["number"].tolist() == [0, 3] and log["step"].tolist() == [0, 118]
    assert log["step_due"].tolist() == [0, 97] and log["skipped"] == 2
    # episode 0 ends at step 97: frame 3 (state 97, exposure's end 99) rendered, not put
    steps = [(0, k) for k in range(98)] + [(1, k) for k in range(41)]
    log, put_at, _ = _camera_main_on_steps(monkeypatch, steps, back)
    assert [p[:2] for p in put_at] == [(0, 0), (0, 1), (0, 2), (1, 0), (1, 1)]
    assert log["step"].tolist() == [0, 31, 64, 0, 31] and log["not_read_out"] == 1
    # the plant past the exposure's end by the time the frame has rendered (step 40 read after
    # frame 1's render at 31): put at once, no sleep on the state read before the render
    log, _, events = _camera_main_on_steps(monkeypatch, [0, 1, 31, 40, 41], back)
    at = events.index(("read", 31))
    assert events[at + 1 : at + 3] == [("read", 40), ("put", 1)]
    assert log["step"].tolist() == [0, 31]


@pytest.mark.slow  # a spawned eye process: about 15 s, most of it the child's imports
def test_an_eye_that_dies_at_start_up_is_reported_and_closed_at_once():
    """An eye process that fails while it starts (here: no camera to read): ``wait_ready``
    raises with its traceback, and ``close`` returns that message at once (it waited 60 s on
    the log queue wait_ready had emptied)."""
    from hec_jax.realtime.runner import EyeProcess

    cam = L.CameraConfig.void_perfect(width=64, height=48)
    exp = L.catching(eye="camera", camera=cam)
    eye = EyeProcess(exp.task, cam, None, 1e-3, None)
    with pytest.raises(RuntimeError, match="the eye process died"):
        eye.wait_ready(120)
    t0 = time.monotonic()
    log = eye.close()
    assert time.monotonic() - t0 < 15 and "error" in log and "Traceback" in log["error"]
