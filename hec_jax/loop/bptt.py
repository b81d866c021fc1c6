"""Episodic training of the virtual-impedance networks with exact gradients (BPTT + optax), and
the learning-curve metrics that compare it with the online rules (``experiments/train_bptt.py``).

One set of networks serves a batch of pendulum conditions and is frozen within a swing; after each
swing of the whole batch one Adam step is taken on the gradient of the swing's task energy

    L = mean_conditions  sum_t [inside] E(t) dt       (E of Eqs. 59-62 as the learner computes it)

by reverse mode through the whole closed loop: networks, impedance law, MJX contact solve with the
implicit derivative of ``hec_jax.mjx_scene.differentiable``, integration. Results:
docs/gradients.md, "Learning with exact gradients".
"""

from __future__ import annotations

import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
import optax

from hec_jax.loop.metrics import force_norm, mean_std
from hec_jax.loop.policy import Loop, switches
from hec_jax.mjx_scene import PendulumConditions, PendulumConfig, differentiable


def training_conditions(n: int, seed: int, pendulum: PendulumConfig, dtype) -> PendulumConditions:
    """``n`` conditions drawn around ``pendulum`` so that every swing reaches a hand waiting at
    X_HOME: rod 0.57-0.63 m, cube 0.5-0.9 kg, release -0.6 to -0.5 rad, from rest; hinge damping
    and position are ``pendulum``'s.
    """
    rng = np.random.default_rng(seed)
    hinge_x = float(pendulum.conditions().hinge_x)
    fields = dict(
        rod_length=rng.uniform(0.57, 0.63, n),
        cube_mass=rng.uniform(0.5, 0.9, n),
        release_angle=rng.uniform(-0.6, -0.5, n),
        release_speed=np.zeros(n),
        hinge_damping=np.full(n, pendulum.hinge_damping),
        arrival_phase=np.zeros(n),
        hinge_x=np.full(n, hinge_x),
    )
    return PendulumConditions(**{k: jnp.asarray(v, dtype) for k, v in fields.items()})


def converged_at(peaks: np.ndarray, tol: float = 0.1) -> int:
    """First swing (1-based) after which ``peaks`` stays within ``tol`` of its last value."""
    ok = np.abs(peaks - peaks[-1]) <= tol * abs(peaks[-1])
    bad = np.flatnonzero(~ok)
    return int(bad[-1] + 2) if bad.size else 1


def make_batch_loss(loop: Loop, conditions: PendulumConditions, ls0):
    """``loss(params) -> (L, (L per condition, peak |F_contact| per condition [N], smallest Eq. 49
    margin))`` of one swing of the batch with the networks ``params`` frozen (pure).
    """
    frozen, n = switches("frozen"), loop.swing_steps
    dt = loop.ids.timestep

    def swing_loss(params, c):
        m = loop.model_for(c)
        d0 = loop.data_for(m, c)
        ps0 = loop.initial_policy_state(m, d0, ls0._replace(params=params), frozen)
        f_ext = jnp.zeros((n, 3), d0.qpos.dtype)
        _, traj = differentiable.rollout(
            m, loop.ids, d0, loop.policy, ps0, f_ext, c, checkpoint=False
        )
        aux = traj.aux
        loss = jnp.sum(jnp.where(aux["inside"], aux["energy"], 0.0)) * dt
        peak = jnp.max(jnp.sqrt(jnp.sum(traj.f_contact**2, axis=-1)))
        return loss, (peak, jnp.min(aux["margins"]))

    def batch_loss(params):
        loss, aux = jax.vmap(swing_loss, in_axes=(None, 0))(params, conditions)
        return jnp.mean(loss), (loss, *aux)

    return batch_loss


def train_bptt(
    loop: Loop,
    conditions: PendulumConditions,
    key,
    dtype,
    lr: float,
    clip: float,
    progress: Callable[[int, dict], None] | None = None,
) -> dict:
    """``loop.config.swings`` Adam steps (gradient clipped to global norm ``clip``) from the
    networks of ``key``; evaluates swings + 1 times (the last: the trained networks). Returns the
    history: per evaluation ``loss`` and ``peak`` (per condition), ``min_margin``, ``grad_norm``,
    ``finite``. ``progress(epoch, row)`` after each evaluation.

    Raises:
        FloatingPointError: a non-finite gradient.
    """
    params0 = loop.learner_init(key, dtype).params
    _, hist = train_bptt_params(loop, conditions, params0, loop.config.swings, lr, clip, progress)
    return hist


def train_bptt_params(
    loop: Loop,
    conditions: PendulumConditions,
    params0: dict,
    epochs: int,
    lr: float,
    clip: float,
    progress: Callable[[int, dict], None] | None = None,
) -> tuple[dict, dict]:
    """:func:`train_bptt` from the networks ``params0`` for ``epochs`` Adam steps; returns (the
    trained networks, the history).

    Raises:
        FloatingPointError: a non-finite gradient.
    """
    dtype = jax.tree_util.tree_leaves(params0)[0].dtype
    ls0 = loop.learner_init(jax.random.PRNGKey(0), dtype)._replace(params=params0)
    opt = optax.chain(optax.clip_by_global_norm(clip), optax.adam(lr))
    grad_fn = jax.jit(jax.value_and_grad(make_batch_loss(loop, conditions, ls0), has_aux=True))

    @jax.jit
    def apply(params, opt_state, grad):
        updates, opt_state = opt.update(grad, opt_state, params)
        return optax.apply_updates(params, updates), opt_state

    params, opt_state = params0, opt.init(params0)
    hist = {"loss": [], "peak": [], "min_margin": [], "grad_norm": [], "finite": []}
    for epoch in range(epochs + 1):
        (loss, (loss_b, peak_b, margin_b)), grad = grad_fn(params)
        finite = all(bool(np.all(np.isfinite(g))) for g in jax.tree_util.tree_leaves(grad))
        row = dict(
            loss=np.asarray(loss_b),
            peak=np.asarray(peak_b),
            min_margin=float(margin_b.min()),
            grad_norm=float(optax.tree.norm(grad)),
            finite=finite,
        )
        for k, v in row.items():
            hist[k].append(v)
        if progress is not None:
            progress(epoch, dict(row, mean_loss=float(loss)))
        if not finite:
            raise FloatingPointError(f"non-finite gradient at epoch {epoch}")
        if epoch < epochs:
            params, opt_state = apply(params, opt_state, grad)
    return params, hist


def online_metrics(logs: dict, peak_plain: np.ndarray, reach: np.ndarray) -> dict:
    """Learning-curve metrics of an online arm (logs (batch, swings, steps)) against the plain
    first-swing peaks ``peak_plain`` (batch,); ``reach``: conditions whose plain swing makes
    contact. With ``de_df_exact`` logged (the exact arm): the median cosine and magnitude ratio of
    the paper's dE/dF_act to the exact one over the learning samples.
    """
    peaks = force_norm(logs).max(-1)
    out = {
        "final_peak_force": mean_std(peaks[:, -1]),
        "final_over_plain": mean_std(peaks[reach, -1] / peak_plain[reach]),
        "swings_to_convergence": converged_at(peaks.mean(0)),
        "peak_force_per_swing_mean": peaks.mean(0).tolist(),
        "stable_every_sample": bool(np.all(logs["margins"] > 0)),
        "finite": bool(all(np.all(np.isfinite(v)) for v in logs.values() if v.dtype.kind == "f")),
    }
    if "de_df_exact" in logs:
        learning = logs["learning"]
        ex, pa = logs["de_df_exact"][learning], logs["de_df_paper"][learning]
        ne, npa = np.linalg.norm(ex, axis=-1), np.linalg.norm(pa, axis=-1)
        ok = (ne > 0) & (npa > 0)
        cos = np.sum(ex * pa, axis=-1)[ok] / (ne * npa)[ok]
        out["de_df_cosine_paper_vs_exact_median"] = float(np.median(cos))
        out["de_df_magnitude_paper_over_exact_median"] = float(np.median(npa[ok] / ne[ok]))
    return out


def bptt_metrics(hist: dict, peak_plain: np.ndarray, reach: np.ndarray) -> dict:
    """The same learning-curve metrics for :func:`train_bptt`'s history: swing k is run with the
    networks after k - 1 updates (swing 1: the initial networks), the last with the trained ones.
    """
    peak = np.stack(hist["peak"], axis=1)  # (batch, swings + 1)
    final = peak[:, -1]
    return {
        "final_peak_force": mean_std(final),
        "final_over_plain": mean_std(final[reach] / peak_plain[reach]),
        "swings_to_convergence": converged_at(peak.mean(0)),
        "peak_force_per_swing_mean": peak.mean(0).tolist(),
        "loss_per_swing": [float(x.mean()) for x in hist["loss"]],
        "gradients_finite_every_step": bool(all(hist["finite"])),
        "min_stability_margin": float(min(hist["min_margin"])),
    }


def timed_sweep(run, keys, sw, conditions) -> tuple[dict, float]:
    """(logs as NumPy, wall time [s]) of one call of a jitted sweep."""
    t0 = time.perf_counter()
    logs = jax.tree_util.tree_map(np.asarray, run(keys, sw, conditions))
    return logs, time.perf_counter() - t0
