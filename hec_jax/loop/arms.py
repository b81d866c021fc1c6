"""Arms, baselines and ablations of the paper protocol (:mod:`hec_jax.loop.protocol`) on the same
held-out pendulums and seeds, and the tables of ``docs/experiments.md``.

Arms:

* ``plain``: impedance control alone (F_o = 0).
* ``frozen``: the initial networks (neutral: O about 0), no learning.
* ``fixed_energy`` / ``fixed_speed``: the best constant virtual impedance (K_o, B_o, M_o; the
  same on both axes) from a grid search on the *training* pendulums, by the mean task energy
  integral (the loss the learner and BPTT minimise) and, for catching, by the mean relative speed
  at contact among candidates that hold the cube in every training swing (the paper's catching
  criterion; the strongest simple baseline for it).
* ``online``: the paper's rule (Eqs. 52-58) over the training swings, then online on each
  held-out pendulum.
* ``online_exact``: the same with the exact one-step dE/dF_act (:mod:`hec_jax.loop.exact`).
* ``bptt``: networks trained offline on the training pendulums by BPTT + Adam
  (:mod:`hec_jax.loop.bptt`), then frozen.

Ablations (``online`` with one change): ``gain_off`` (alpha = 0 / beta = -1 at every distance),
``mu_0`` (no force term), ``vin_off`` (eta of the VIN 0), ``gate_off`` (learning also while the
object recedes), ``velocity_after_contact`` (Eq. 59 as printed), ``accel_raw`` (X_o'' the 1 kHz
backward difference instead of the camera-rate low-pass).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import jax
import jax.numpy as jnp
import numpy as np

from hec_jax.loop import paper_metrics as pm
from hec_jax.loop.config import ExperimentConfig, TaskConfig, replace
from hec_jax.loop.policy import Loop, build_loop, switches
from hec_jax.loop.protocol import (
    HELD_OUT_SEED_OFFSET,
    ConditionRange,
    draw_conditions,
    initial_params,
    make_protocol,
    run_protocol,
)
from hec_jax.mjx_scene import rollout
from hec_jax.nets import impedance_nets as nets

BASELINES = ("plain", "frozen", "fixed_energy", "fixed_speed")
LEARNED = ("online", "online_exact", "bptt")
ABLATIONS = {
    "gain_off": {"gain": "off"},
    "mu_0": {"mu": 0.0},
    "vin_off": {"eta": (0.3, 0.3, 0.0)},
    "gate_off": {"gate_receding": False},
    "velocity_after_contact": {"velocity_after_contact": True},
    "accel_raw": {"object_accel_tau_s": 0.0},
}
ArmName = Literal[
    "plain",
    "frozen",
    "fixed_energy",
    "fixed_speed",
    "online",
    "online_exact",
    "bptt",
    "gain_off",
    "mu_0",
    "vin_off",
    "gate_off",
    "velocity_after_contact",
    "accel_raw",
]
ALL_ARMS: tuple[str, ...] = BASELINES + LEARNED + tuple(ABLATIONS)


@dataclass(frozen=True)
class PaperProtocol:
    """One table: a paper preset under the protocol, its arms and their budgets.

    Attributes:
        experiment: the preset (``catching_paper()`` / ``hitting_paper()``; ``task.swings``
            training swings, ``seed`` and ``seeds`` the network initialisations).
        ranges: where the pendulum of each training swing and held-out run is drawn.
        held_out: held-out pendulums per seed (the same for every arm and seed).
        eval_s: [s] each held-out run (catching: a swing; hitting: a continuous run).
        arms: the arms and ablations to run (``ALL_ARMS``).
        fixed_grid: grid points per parameter of the fixed-impedance search (K_o, B_o), over
            -0.9 ... 0.9 of the output bound U/2; M_o takes ``fixed_grid_m`` points.
        fixed_grid_m: grid points of M_o (1: M_o = 0).
        fixed_search_pendulums: training pendulums the search scores each candidate on.
        bptt_epochs: Adam steps of the BPTT arm (one per batch swing).
        bptt_lr: Adam learning rate; bptt_clip: global gradient-norm clip.
        bptt_horizon_s: [s] BPTT's loss covers the first this-many seconds of each training
            swing (release, approach, impact: where the velocity term lives; the arrival falls
            at 0.4-0.9 s), so reverse mode stores a shorter trajectory.
    """

    experiment: ExperimentConfig = field(default_factory=ExperimentConfig)
    ranges: ConditionRange = field(default_factory=ConditionRange)
    held_out: int = 8
    eval_s: float = 3.0
    arms: tuple[ArmName, ...] = ALL_ARMS
    fixed_grid: int = 7
    fixed_grid_m: int = 3
    fixed_search_pendulums: int = 6
    bptt_epochs: int = 10
    bptt_lr: float = 3e-3
    bptt_clip: float = 1.0
    bptt_horizon_s: float = 1.2

    def __post_init__(self):
        unknown = set(self.arms) - set(ALL_ARMS)
        if unknown:
            raise ValueError(f"unknown arms {sorted(unknown)}; known: {ALL_ARMS}")
        for name in ("held_out", "fixed_grid", "fixed_grid_m", "fixed_search_pendulums"):
            v = getattr(self, name)
            if not (isinstance(v, int) and v >= 1):
                raise ValueError(f"PaperProtocol.{name} must be an integer >= 1, got {v}")
        for name in ("eval_s", "bptt_horizon_s", "bptt_lr", "bptt_clip"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"PaperProtocol.{name} must be finite and > 0, got {v}")
        if not (isinstance(self.bptt_epochs, int) and self.bptt_epochs >= 0):
            raise ValueError(f"bptt_epochs must be an integer >= 0, got {self.bptt_epochs}")


def arm_task(task: TaskConfig, arm: str) -> TaskConfig:
    """The task an arm runs: the preset's, with the ablation's change (others: unchanged)."""
    for name, value in ABLATIONS.get(arm, {}).items():
        task = replace(task, **{name: value})
    return task


def _dtype():
    return jnp.float64 if jax.config.jax_enable_x64 else jnp.float32


def _with_zero(n: int) -> np.ndarray:
    """``n`` points over -0.9 ... 0.9 with an exact 0 (an odd ``n``'s middle point, which
    linspace gives as -1.1e-16 for 7, snapped to 0; an even ``n`` gets 0 added: n + 1 points).
    """
    grid = np.linspace(-0.9, 0.9, n)
    grid[np.abs(grid) < 1e-12] = 0.0
    return np.union1d(grid, [0.0])


def fixed_candidates(task: TaskConfig, n: int, n_m: int) -> np.ndarray:
    """Constant virtual impedances (C, 2, 3) on a grid: K_o, B_o over -0.9 ... 0.9 of U/2 (the
    networks' output range, so every candidate satisfies Eq. 49 as the networks do), M_o over
    ``n_m`` points (1: 0); the same values on both axes. Zero is always among the values (an
    even ``n`` or ``n_m`` gets it added: one value more), so the baseline can pick plain
    impedance (F_o = 0) and is never weaker than it.
    """
    imp = task.impedance
    u = np.asarray(
        nets.u_max(task.learner.net, np.asarray(imp.m_e), np.asarray(imp.b_e), np.asarray(imp.k_e))
    )  # (2, 3)
    grid, grid_m = _with_zero(n), _with_zero(n_m) if n_m > 1 else np.zeros(1)
    out = [
        np.stack([u[:, 0] / 2 * k, u[:, 1] / 2 * b, u[:, 2] / 2 * mm], axis=-1)
        for k in grid
        for b in grid
        for mm in grid_m
    ]
    return np.asarray(out)


def held_in_one_contact(on: jax.Array, tail: int, min_gap: int) -> jax.Array:
    """Whether a swing holds the cube, as :func:`paper_metrics.catching_run_metrics`' ``held``
    says, in jittable form: some contact, in contact over the last ``tail`` samples, and no run
    of ``min_gap`` or more samples out of contact after the first contact (shorter gaps are one
    episode, as :func:`~hec_jax.loop.metrics.contact_events` merges them).

    Args:
        on: (steps,) bool, |F_int| above the contact threshold.
        tail: samples of the settle window, >= 1.
        min_gap: samples of the shortest gap that splits two contacts, >= 1.
    """
    steps = on.shape[0]
    after_first = jnp.arange(steps) > jnp.argmax(on)
    off = jnp.concatenate([jnp.zeros(1, jnp.int32), jnp.cumsum(~on & after_first)])
    # out-of-contact samples in each window [i, i + min_gap) after the first contact
    if min_gap > steps:
        long_gap = jnp.asarray(False)
    else:
        long_gap = jnp.any(off[min_gap:] - off[:-min_gap] >= min_gap)
    return jnp.any(on) & jnp.all(on[-tail:]) & ~long_gap


def make_fixed_scores(loop: Loop):
    """``scores(fixed (C, 2, 3), conditions (P,)) -> dict of (C, P)``: per candidate and pendulum
    one swing with that constant impedance, reduced in the jitted function to the task energy
    integral ``loss`` [m^2/s + ...] (inside the sphere, as the learner's E), the relative speed at
    the first contact ``rel_speed`` [m/s] (NaN: no contact), ``peak`` [N], and ``held``
    (:func:`held_in_one_contact`, the table's "held"; until 2026-12-04 only "in contact over the
    last settle window", which a cube that bounced off and came back to rest also met).
    """
    cfg, dt, n = loop.config, loop.ids.timestep, loop.swing_steps
    tail = max(int(round(cfg.settle_s / dt)), 1)
    min_gap = int(round(pm.CONTACT_MERGE_S / dt))

    def one(fixed, c):
        m = loop.model_for(c)
        d0 = loop.data_for(m, c)
        ls0 = loop.learner_init(jax.random.PRNGKey(0), d0.qpos.dtype)
        ps0 = loop.initial_policy_state(m, d0, ls0, switches("frozen", fixed=fixed))
        f_ext = jnp.zeros((n, 3), d0.qpos.dtype)
        _, traj = rollout(m, loop.ids, d0, loop.policy, ps0, f_ext, c)
        aux = traj.aux
        f = jnp.linalg.norm(traj.f_contact[:, jnp.array([0, 2])], axis=-1)
        on = f > cfg.contact_threshold
        first = jnp.argmax(on)
        before = jnp.maximum(first - 1, 0)
        rel = jnp.linalg.norm(aux["xd_o_true"][before] - aux["xd_e"][before])
        return dict(
            loss=jnp.sum(jnp.where(aux["inside"], aux["energy"], 0.0)) * dt,
            rel_speed=jnp.where(jnp.any(on), rel, jnp.nan),
            peak=jnp.max(f),
            held=held_in_one_contact(on, tail, min_gap),
        )

    return jax.jit(jax.vmap(jax.vmap(one, in_axes=(None, 0)), in_axes=(0, None)))


def search_fixed(loop: Loop, protocol: PaperProtocol, train_conditions) -> dict:
    """The grid search of the fixed-impedance baselines on the training pendulums; returns the
    chosen impedances (2, 3) ``fixed_energy`` and (catching) ``fixed_speed``, and the search's
    table.
    """
    cand = fixed_candidates(loop.config, protocol.fixed_grid, protocol.fixed_grid_m)
    n = min(protocol.fixed_search_pendulums, int(train_conditions.rod_length.shape[0]))
    conds = jax.tree_util.tree_map(lambda x: x[:n], train_conditions)
    t0 = time.perf_counter()
    scores = jax.tree_util.tree_map(
        np.asarray, make_fixed_scores(loop)(jnp.asarray(cand, _dtype()), conds)
    )
    wall = time.perf_counter() - t0
    loss = scores["loss"].mean(1)
    out = {
        "fixed_energy": cand[int(np.nanargmin(loss))],
        "search": {
            "candidates": len(cand),
            "pendulums": n,
            "wall_s": wall,
            "best_energy_loss": float(np.nanmin(loss)),
        },
    }
    if loop.config.learner.task == "catching":
        held_all = scores["held"].all(1)
        contact_all = np.isfinite(scores["rel_speed"]).all(1)
        ok = held_all & contact_all
        speed = np.where(
            ok, np.nanmean(np.where(contact_all[:, None], scores["rel_speed"], 0), 1), np.inf
        )
        if np.isfinite(speed).any():
            out["fixed_speed"] = cand[int(np.argmin(speed))]
            out["search"]["best_speed"] = float(np.min(speed))
        else:  # no candidate holds the cube in every training swing: the fastest-to-hold rule
            out["fixed_speed"] = None
            out["search"]["best_speed"] = None
        out["search"]["candidates_holding_every_swing"] = int(ok.sum())
    return out


def _bptt_params(loop: Loop, protocol: PaperProtocol, train_conditions, params0) -> tuple:
    """BPTT + Adam on the training pendulums (their first ``bptt_horizon_s``) from each seed's
    initial networks.
    """
    from hec_jax.loop.bptt import train_bptt_params

    horizon = min(protocol.bptt_horizon_s, loop.config.swing_s)
    loop = build_loop(dataclasses.replace(loop.config, swing_s=horizon, settle_s=horizon / 2))
    out, hist = [], []
    for s in range(params0["output"]["bias"].shape[0]):
        p0 = jax.tree_util.tree_map(lambda x, s=s: x[s], params0)
        p, h = train_bptt_params(
            loop, train_conditions, p0, protocol.bptt_epochs, protocol.bptt_lr, protocol.bptt_clip
        )
        out.append(p)
        hist.append(h)
    return jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *out), hist


def run_arms(protocol: PaperProtocol, progress: Callable[[str], None] | None = None) -> dict:
    """Runs every arm of ``protocol`` on the same seeds and held-out pendulums; returns
    {"arms": {arm: {"summary", "per_run", "learning_curve", "timing_s", ...}}, "pendulums",
    "fixed_search"} and the logs of the ``online`` arm (for figures) under "logs".
    """
    exp = protocol.experiment
    task = exp.task
    dt_type = _dtype()
    lc = task.learner
    eval_s = task.final_s if task.final_s > 0 else protocol.eval_s
    train_c = draw_conditions(protocol.ranges, task.pendulum, task.swings, exp.seed, dt_type)
    held_c = draw_conditions(
        protocol.ranges, task.pendulum, protocol.held_out, HELD_OUT_SEED_OFFSET + exp.seed, dt_type
    )
    no_train = jax.tree_util.tree_map(lambda x: x[:0], train_c)
    base_loop = build_loop(task)
    dt = base_loop.ids.timestep
    params0 = initial_params(base_loop, exp.seed, exp.seeds, dt_type)
    results: dict = {"arms": {}, "logs": {}}
    results["pendulums"] = {
        "training": {k: np.asarray(v).tolist() for k, v in train_c._asdict().items()},
        "held_out": {k: np.asarray(v).tolist() for k, v in held_c._asdict().items()},
    }
    keys = pm.CATCHING_KEYS if lc.task == "catching" else pm.HITTING_KEYS
    # the base loop's jitted protocol and its executables, shared by the non-ablation arms
    shared = make_protocol(base_loop, eval_s)
    compiled_cache: dict = {}
    fixed = None

    def evaluate(arm, loop, params, sw_train, sw_eval, train, run=None):
        train_logs, eval_logs, timing = run_protocol(
            loop, params, sw_train, sw_eval, train, held_c, eval_s, run, compiled_cache
        )
        per_run = [
            pm.task_run_metrics(lc.task, r, dt, lc.f_desired, task.contact_threshold, task.settle_s)
            for r in pm.runs_of(eval_logs)
        ]
        entry = {
            "summary": pm.summarize(per_run, keys),
            "per_run": per_run,
            "timing_s": timing,
            "strictly_stable_every_sample": bool(np.all(eval_logs["margins"] > 0))
            and bool(train_logs["margins"].size == 0 or np.all(train_logs["margins"] > 0)),
        }
        if train_logs["f_contact"].shape[1] > 0:
            entry["learning_curve"] = _learning_curve(lc.task, train_logs, dt, lc.f_desired, task)
        results["arms"][arm] = entry
        if arm == "online":
            results["logs"] = {"train": train_logs, "eval": eval_logs}
        if progress is not None:
            progress(arm)

    for arm in protocol.arms:
        t0 = time.perf_counter()
        loop, run = base_loop, shared  # the ablations and online_exact build their own below
        if arm == "plain":
            sw = switches("plain")
            evaluate(arm, loop, params0, sw, sw, no_train, run)
        elif arm == "frozen":
            sw = switches("frozen")
            evaluate(arm, loop, params0, sw, sw, no_train, run)
        elif arm in ("fixed_energy", "fixed_speed"):
            if fixed is None:
                fixed = search_fixed(base_loop, protocol, train_c)
                results["fixed_search"] = {
                    **fixed["search"],
                    **{
                        k: (None if fixed.get(k) is None else np.asarray(fixed[k]).tolist())
                        for k in ("fixed_energy", "fixed_speed")
                    },
                }
            if fixed.get(arm) is None:
                results["arms"][arm] = {"skipped": "no candidate qualifies (see fixed_search)"}
                continue
            sw = switches("frozen", fixed=jnp.asarray(fixed[arm], dt_type))
            evaluate(arm, loop, params0, sw, sw, no_train, run)
        elif arm == "online":
            sw = switches("learned")
            evaluate(arm, loop, params0, sw, sw, train_c, run)
        elif arm == "bptt":
            trained, hist = _bptt_params(base_loop, protocol, train_c, params0)
            sw = switches("frozen")
            evaluate(arm, loop, trained, sw, sw, no_train, run)
            # per seed, the mean loss over the training pendulums at each evaluation
            results["arms"][arm]["bptt_loss_per_epoch"] = [
                [float(np.mean(x)) for x in h["loss"]] for h in hist
            ]
        elif arm == "online_exact":
            from hec_jax.loop.exact import build_exact_loop

            loop = build_exact_loop(task)
            sw = switches("learned")
            evaluate(arm, loop, params0, sw, sw, train_c)
        else:  # an ablation of the online arm
            loop = build_loop(arm_task(task, arm))
            sw = switches("learned")
            evaluate(arm, loop, params0, sw, sw, train_c)
        results["arms"][arm]["wall_s"] = time.perf_counter() - t0
    return results


def _learning_curve(task_name: str, train_logs: dict, dt: float, f_d: float, task) -> dict:
    """Per training swing, the mean over seeds of the task's main metrics."""
    s, w = train_logs["f_contact"].shape[:2]
    curve: dict = {}
    for j in range(w):
        per = [
            pm.task_run_metrics(
                task_name,
                {k: v[i, j] for k, v in train_logs.items()},
                dt,
                f_d,
                task.contact_threshold,
                task.settle_s,
            )
            for i in range(s)
        ]
        keys = ("relative_speed_at_contact", "peak_force", "t_c_s")
        for key in keys if task_name == "catching" else ("hits", "max_pulse", "sustained"):
            vals = [p[key] for p in per if p.get(key) is not None]
            curve.setdefault(key, []).append(float(np.mean(vals)) if vals else None)
    return curve


def table_rows(results: dict, task: str) -> list[dict]:
    """One row per arm: mean +- std of the main metrics over seeds x held-out pendulums."""
    keys = pm.CATCHING_KEYS if task == "catching" else pm.HITTING_KEYS
    rows = []
    for arm, entry in results["arms"].items():
        if "summary" not in entry:
            rows.append({"arm": arm, "note": entry.get("skipped", "")})
            continue
        row = {"arm": arm}
        for key in keys:
            v = entry["summary"].get(key)
            if v is None:
                row[key] = "not recorded"
            elif "fraction" in v:
                row[key] = f"{v['fraction']:.2f}"
            elif v["mean"] is None:
                row[key] = "n/a"
            else:
                row[key] = f"{v['mean']:.3g} +- {v['std']:.2g}" + (
                    f" ({v['n']}/{entry['summary']['runs']})"
                    if v["n"] < entry["summary"]["runs"]
                    else ""
                )
        rows.append(row)
    return rows


def markdown_table(rows: list[dict]) -> str:
    """A Markdown table of :func:`table_rows`."""
    cols = list(dict.fromkeys(k for r in rows for k in r))
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(str(r.get(c, "")) for c in cols) + " |" for r in rows]
    return "\n".join(lines)


def protocol_settings(protocol: PaperProtocol) -> dict:
    """The protocol as plain data (for config.json)."""
    return dataclasses.asdict(protocol)
