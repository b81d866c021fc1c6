"""Episodes of the closed loop: swings in ``lax.scan``, seeds and conditions ``vmap``-ed.

One swing is one ``lax.scan`` over control steps (``hec_jax.mjx_scene.rollout``); successive
swings are a ``lax.scan`` over swings that restarts the world at the same release and carries the
learner's state (weights) over; an optional continuous run follows. The loop is built once per
task; the pendulum's conditions are arguments of the compiled function.
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np

from hec_jax.loop.policy import CONDITIONS, Loop, Switches, switches
from hec_jax.mjx_scene import PendulumConditions, rollout


def _float_dtype():
    return jnp.float64 if jax.config.jax_enable_x64 else jnp.float32


def make_seed_run(loop: Loop):
    """``run(key, switches, conditions) -> logs`` of one seed and one condition (pure): the task's
    swings (world restarted at the release each swing, learner state carried over), then the
    optional continuous run (``logs["final"]``, leading axis 1).
    """

    def one_swing(ls, sw, conditions, m, n_steps):
        d0 = loop.data_for(m, conditions)
        ps0 = loop.initial_policy_state(m, d0, ls, sw)
        f_ext = jnp.zeros((n_steps, 3))
        (_, ps), traj = rollout(m, loop.ids, d0, loop.policy, ps0, f_ext, conditions)
        ls = ps.learner._replace(was_inside=jnp.asarray(False))
        log = dict(traj.aux, f_contact=traj.f_contact, t=traj.t, qpos=traj.qpos, qvel=traj.qvel)
        return ls, log

    def run(key, sw, conditions):
        m = loop.model_for(conditions)
        ls0 = loop.learner_init(key, _float_dtype())
        ls, logs = jax.lax.scan(
            lambda ls, _: one_swing(ls, sw, conditions, m, loop.swing_steps),
            ls0,
            None,
            length=loop.config.swings,
        )
        if loop.final_steps > 0:
            _, final = one_swing(ls, sw, conditions, m, loop.final_steps)
            logs = dict(logs, final=jax.tree_util.tree_map(lambda x: x[None], final))
        return logs

    return run


def make_episodes(loop: Loop):
    """``run(keys, switches, conditions) -> logs`` for a batch of seeds under one condition
    (jitted; compiled once per shape, whatever the conditions' values).

    ``keys``: (n_seeds, 2) PRNG keys (network initialisations); ``switches``: a :class:`Switches`
    shared by the batch; ``conditions``: scalar :class:`PendulumConditions`. Returns a dict of
    arrays with leading axes (n_seeds, swings, swing_steps); with a continuous run also
    ``final`` (n_seeds, 1, final_steps).
    """
    return jax.jit(jax.vmap(make_seed_run(loop), in_axes=(0, None, None)))


def sweep_in_axes(per_run_switches: bool = False) -> tuple:
    """``make_sweep``'s ``vmap`` axes of (keys, switches, conditions) (``loop.devices``)."""
    sw_axes = Switches(use_virtual=0, learn=0, eye=None) if per_run_switches else None
    return (0, sw_axes, 0)


def make_sweep(loop: Loop, per_run_switches: bool = False):
    """``run(keys, switches, conditions) -> logs`` over a batch of runs: ``keys`` (B, 2) and every
    leaf of ``conditions`` (B,), one pendulum condition and network seed per run (``vmap``). With
    ``per_run_switches`` the ``use_virtual``/``learn`` leaves of ``switches`` are (B,) too, so
    plain and learned runs share one batch (and one compile). Not jitted here, so the caller can
    choose devices (:mod:`hec_jax.loop.devices`).
    """
    return jax.vmap(make_seed_run(loop), in_axes=sweep_in_axes(per_run_switches))


def run_conditions(
    loop: Loop,
    conditions: PendulumConditions | None = None,
    seed: int = 0,
    n_seeds: int = 5,
    progress=None,
):
    """All three conditions (plain, frozen, learned) for ``n_seeds`` seeds with the simulator's
    object state; ``conditions`` default to the task's pendulum. Returns
    ({condition: logs as NumPy}, {condition: wall time [s]}, with ``compile`` apart);
    ``progress(condition)`` is called after each condition.
    """
    conditions = loop.config.pendulum.conditions() if conditions is None else conditions
    run = make_episodes(loop)
    keys = jax.random.split(jax.random.PRNGKey(seed), n_seeds)
    out, timing = {}, {}
    t0 = time.perf_counter()
    compiled = run.lower(keys, switches("plain"), conditions).compile()
    timing["compile"] = time.perf_counter() - t0
    for condition in CONDITIONS:
        t0 = time.perf_counter()
        logs = compiled(keys, switches(condition), conditions)
        logs = jax.tree_util.tree_map(np.asarray, jax.block_until_ready(logs))
        timing[condition] = time.perf_counter() - t0
        out[condition] = logs
        if progress is not None:
            progress(condition)
    return out, timing
