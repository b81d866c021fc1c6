"""The paper protocol: learning across swings whose pendulum is drawn per swing, evaluated on
held-out pendulums, for the arms and ablations of ``docs/experiments.md``.

Per seed (one network initialisation), an arm runs

1. **training**: ``swings`` swings, each from a release drawn from a :class:`ConditionRange`
   (release angle, arrival phase, cube mass), the world restarted each swing, the learner's
   state carried over (one ``lax.scan`` over swings, the conditions as its ``xs``);
2. **evaluation**: from the trained learner state, one run of ``eval_s`` on each held-out
   pendulum (drawn from the same range with another seed; ``vmap`` over them), learning on or
   off as the arm says.

Arms that do not learn online (plain, frozen, fixed impedance, BPTT-trained) skip the training
swings. Everything is one jitted function per learner configuration: ``(params, switches for
training, switches for evaluation, training conditions, held-out conditions) -> logs``, vmapped
over seeds.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from hec_jax.loop.policy import Loop, Switches
from hec_jax.mjx_scene import PendulumConditions, PendulumConfig, rollout

# Held-out pendulums are drawn with the seed ``HELD_OUT_SEED_OFFSET + seed``; training pendulums
# with ``seed``: the two sets never share a draw.
HELD_OUT_SEED_OFFSET = 10_000


@dataclass(frozen=True)
class ConditionRange:
    """Uniform ranges (low, high) of the pendulum conditions drawn per swing (the others: the
    preset's); ``<field>_range`` draws :class:`~hec_jax.mjx_scene.PendulumConditions`' ``<field>``.

    The defaults keep every release outside the virtual sphere (the cube starts 0.34-0.48 m from
    a hand at the rest-touch point, r = 0.25 m) and vary the impact speed (about 1.0-1.5 m/s at
    the bottom), the arrival time and the mass the hand must stop.
    """

    release_angle_range: tuple[float, float] = (-0.6, -0.4)  # [rad]
    arrival_phase_range: tuple[float, float] = (0.0, 0.25)  # [s]
    cube_mass_range: tuple[float, float] = (0.5, 0.9)  # [kg]

    def __post_init__(self):
        for f in dataclasses.fields(self):
            lo, hi = getattr(self, f.name)
            if not (np.isfinite(lo) and np.isfinite(hi) and lo <= hi):
                raise ValueError(
                    f"ConditionRange.{f.name} must be finite (low, high), got {lo, hi}"
                )
        if self.cube_mass_range[0] <= 0 or self.arrival_phase_range[0] < 0:
            raise ValueError("ConditionRange: cube_mass must be > 0 and arrival_phase >= 0")


def draw_conditions(
    ranges: ConditionRange, pendulum: PendulumConfig, n: int, seed: int, dtype=float
) -> PendulumConditions:
    """``n`` pendulum conditions (leaves (n,)) drawn uniformly from ``ranges`` with NumPy's
    generator of ``seed``; the fields ``ranges`` does not name are ``pendulum``'s.
    """
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    rng = np.random.default_rng(seed)
    base = pendulum.conditions()
    drawn = {
        f.name.removesuffix("_range"): rng.uniform(*getattr(ranges, f.name), n)
        for f in dataclasses.fields(ranges)
    }
    values = {
        k: jnp.asarray(drawn[k] if k in drawn else np.full(n, float(getattr(base, k))), dtype)
        for k in PendulumConditions._fields
    }
    return PendulumConditions(**values)


def make_protocol(loop: Loop, eval_s: float):
    """``run(params, sw_train, sw_eval, train_conditions, eval_conditions) -> (train_logs,
    eval_logs)`` for a batch of seeds (jitted; compiled once per shape).

    ``params``: the networks of each seed (leading axis seeds); ``sw_train`` / ``sw_eval``:
    :class:`~hec_jax.loop.policy.Switches` of the training swings and the evaluation runs;
    ``train_conditions``: leaves (swings,) (length 0: no training); ``eval_conditions``: leaves
    (n_eval,). Logs: train (seeds, swings, swing_steps, ...), eval (seeds, n_eval, eval_steps,
    ...).
    """
    swing_steps = loop.swing_steps
    eval_steps = int(round(eval_s / loop.ids.timestep))

    def one_run(ls, sw, conditions, n_steps):
        m = loop.model_for(conditions)
        d0 = loop.data_for(m, conditions)
        ps0 = loop.initial_policy_state(m, d0, ls, sw)
        f_ext = jnp.zeros((n_steps, 3), d0.qpos.dtype)
        (_, ps), traj = rollout(m, loop.ids, d0, loop.policy, ps0, f_ext, conditions)
        ls = ps.learner._replace(was_inside=jnp.asarray(False))
        log = dict(traj.aux, f_contact=traj.f_contact, qpos=traj.qpos, qvel=traj.qvel)
        return ls, log

    def per_seed(params, sw_train, sw_eval, train_conditions, eval_conditions):
        ls0 = loop.learner_init(jax.random.PRNGKey(0), params["output"]["bias"].dtype)
        ls0 = ls0._replace(params=params)
        ls, train_logs = jax.lax.scan(
            lambda ls, c: one_run(ls, sw_train, c, swing_steps), ls0, train_conditions
        )
        _, eval_logs = jax.vmap(lambda c: one_run(ls, sw_eval, c, eval_steps))(eval_conditions)
        return train_logs, eval_logs

    return jax.jit(jax.vmap(per_seed, in_axes=(0, None, None, None, None)))


def initial_params(loop: Loop, seed: int, n_seeds: int, dtype) -> dict:
    """The networks of ``n_seeds`` initialisations (leading axis seeds) from PRNG ``seed``."""
    keys = jax.random.split(jax.random.PRNGKey(seed), n_seeds)
    return jax.vmap(lambda k: loop.learner_init(k, dtype).params)(keys)


def run_protocol(
    loop: Loop,
    params: dict,
    sw_train: Switches,
    sw_eval: Switches,
    train_conditions: PendulumConditions,
    eval_conditions: PendulumConditions,
    eval_s: float,
    run=None,
    compiled_cache: dict | None = None,
) -> tuple[dict, dict, dict]:
    """Runs :func:`make_protocol` (or the given jitted ``run``) once; returns (train logs,
    eval logs) as NumPy and the timing {"compile", "run"} [s] (compile 0: reused).

    ``compiled_cache``: executables of the given ``run`` (kept alive by the caller) by argument
    structure and shapes, so arms that share the loop and the shapes (plain, frozen,
    BPTT-trained) compile once.
    """
    if run is None:  # a fresh function: nothing of it can be in the cache
        run, compiled_cache = make_protocol(loop, eval_s), None
    args = (params, sw_train, sw_eval, train_conditions, eval_conditions)
    leaves, tree = jax.tree_util.tree_flatten(args)
    key = (id(run), tree, tuple((jnp.shape(x), jnp.result_type(x)) for x in leaves))
    t0 = time.perf_counter()
    compiled = None if compiled_cache is None else compiled_cache.get(key)
    if compiled is None:
        compiled = run.lower(*args).compile()
        if compiled_cache is not None:
            compiled_cache[key] = compiled
    t1 = time.perf_counter()
    out = jax.block_until_ready(compiled(*args))
    t2 = time.perf_counter()
    train, evals = jax.tree_util.tree_map(np.asarray, out)
    return train, evals, {"compile": t1 - t0, "run": t2 - t1}
