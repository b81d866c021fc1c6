"""Episodic training of the virtual-impedance networks with exact gradients (BPTT + optax) across a
batch of pendulum conditions, against the paper's online rule (Eqs. 52-58).

    python experiments/train_bptt.py --out runs/train_bptt --seed 0 [--batch 6] [--epochs 15]

Both start from the same initial networks (``--seed``) and see the same catching swings (release
from rest, ``--swing-s`` of 1 ms samples) of the same ``--batch`` pendulum conditions (rod length,
cube mass, release angle drawn around the default so that every swing reaches the waiting hand):

* **paper**: the online learner of ``hec_jax.nets`` (dE/dF_act of Eqs. 55-58, one weight update per
  sample inside the sphere), one run per condition (each condition learns its own networks), the
  weights carried over ``--epochs`` swings (``task_loop.make_sweep``);
* **exact**: the same online learner with the exact one-step dE/dF_act through an MJX step
  (``experiments/exact_online.py``) instead of Eqs. 55-58;
* **bptt**: one set of networks for all conditions, frozen within a swing; after each swing of the
  whole batch one Adam step on the gradient of the swing's task energy
  L = mean_conditions sum_t [inside] E(t) dt (E of Eqs. 59-62 as the learner computes it), taken by
  reverse mode through the whole closed loop (networks, impedance law, MJX contact solve with the
  implicit derivative of ``hec_jax.mjx_scene.differentiable``, integration).

Reports per swing the batch-mean peak contact force, swings to convergence (first swing after
which the batch-mean peak stays within 10% of its final value) and the final peak force against
plain impedance control (F_o = 0). Writes ``config.json``, ``metrics.json``, ``history.npz`` and
``peak_force_per_swing.png``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import jax  # noqa: E402

if "--float32" not in sys.argv:
    jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import optax  # noqa: E402

from experiments import task_loop as tl  # noqa: E402
from experiments.exact_online import make_exact_sweep  # noqa: E402
from hec_jax.mjx_scene import PendulumConditions, default_conditions, differentiable  # noqa: E402
from hec_jax.runs import enable_compile_cache, save_figure, start_run, write_json, write_npz  # noqa: E402


def parse(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    tl.add_common_args(p, "runs/train_bptt")
    p.add_argument("--float32", action="store_true")
    p.add_argument("--batch", type=int, default=6, help="pendulum conditions")
    p.add_argument("--epochs", type=int, default=10, help="swings (paper) = Adam steps (bptt)")
    p.add_argument("--swing-s", type=float, default=1.0, help="duration of one swing [s]")
    p.add_argument("--lr", type=float, default=3e-3, help="Adam learning rate")
    p.add_argument("--clip", type=float, default=1.0, help="global gradient-norm clip")
    p.add_argument("--mu", type=float, default=1e-3, help="weight of E_cf (Eq. 59)")
    p.add_argument("--f-cd", type=float, default=1.0, help="desired contact force F_cd [N]")
    p.add_argument(
        "--arms",
        nargs="+",
        default=["paper", "exact", "bptt"],
        choices=["paper", "exact", "bptt"],
        help="learning methods to run (plain impedance always runs)",
    )
    return p.parse_args(argv)


def conditions(n: int, seed: int, dtype) -> PendulumConditions:
    rng = np.random.default_rng(seed)
    base = default_conditions()
    fields = dict(
        rod_length=rng.uniform(0.57, 0.63, n),
        cube_mass=rng.uniform(0.5, 0.9, n),
        release_angle=rng.uniform(-0.6, -0.5, n),  # swings that reach the waiting hand
        release_speed=np.zeros(n),
        hinge_damping=np.full(n, float(base.hinge_damping)),
        arrival_phase=np.zeros(n),
    )
    return PendulumConditions(**{k: jnp.asarray(v, dtype) for k, v in fields.items()})


def converged_at(peaks: np.ndarray, tol: float = 0.1) -> int:
    """First swing (1-based) after which ``peaks`` stays within ``tol`` of its last value."""
    ok = np.abs(peaks - peaks[-1]) <= tol * abs(peaks[-1])
    bad = np.flatnonzero(~ok)
    return int(bad[-1] + 2) if bad.size else 1


def main(argv=None):
    args = parse(argv)
    enable_compile_cache()
    dtype = jnp.float32 if args.float32 else jnp.float64
    learner = tl.learner_from_args(args, "catching", args.f_cd)
    config = tl.config_from_args(args, learner, args.swing_s, args.epochs)
    settings = tl.run_settings(args, "catching", default_conditions(), learner, config)
    folder = start_run(args.out, args.seed, settings)
    conds = conditions(args.batch, args.seed, dtype)
    steps = config.swing_steps
    dt = config.controller.dt
    key = jax.random.PRNGKey(args.seed)
    keys = jnp.broadcast_to(key, (args.batch, 2))
    t_start = time.perf_counter()

    # --- online rules (paper's and exact one-step), one run per condition; plain baseline ---------
    sweep = jax.jit(tl.make_sweep(config))
    timing, online = {}, {}
    t0 = time.perf_counter()
    logs_plain = jax.tree_util.tree_map(np.asarray, sweep(keys, tl.switches("plain"), conds))
    peak_plain = tl.force_norm(logs_plain).max(-1)[:, 0]  # (batch,)
    if not np.all(peak_plain > 0):
        print(f"warning: {int(np.sum(peak_plain <= 0))} swing(s) never reach the hand", flush=True)
    reach = peak_plain > 0  # ratios over plain only where the swing reaches the hand
    timing["plain"] = time.perf_counter() - t0
    for arm in ("paper", "exact"):
        if arm not in args.arms:
            continue
        fn = sweep if arm == "paper" else jax.jit(make_exact_sweep(config))
        t0 = time.perf_counter()
        logs = jax.tree_util.tree_map(np.asarray, fn(keys, tl.switches("learned"), conds))
        timing[arm] = time.perf_counter() - t0
        online[arm] = logs
        peaks = tl.force_norm(logs).max(-1)  # (batch, swings)
        print(f"{arm}: batch-mean peak per swing {np.round(peaks.mean(0), 1).tolist()}", flush=True)

    # --- BPTT: one set of networks for the batch ------------------------------------------------
    loop = tl.build_loop(config, default_conditions())
    ls0 = loop.learner_init(key, dtype)
    frozen = tl.switches("frozen")

    def swing_loss(params, c):
        m = loop.model_for(c)
        d0 = loop.data_for(m, c)
        ps0 = loop.initial_policy_state(d0, ls0._replace(params=params), frozen)
        f_ext = jnp.zeros((steps, 3), dtype)
        _, traj = differentiable.rollout(
            m, loop.ids, d0, loop.policy, ps0, f_ext, c, checkpoint=False
        )
        aux = traj.aux
        loss = jnp.sum(jnp.where(aux["inside"], aux["energy"], 0.0)) * dt
        peak = jnp.max(jnp.sqrt(jnp.sum(traj.f_contact**2, axis=-1)))
        return loss, (peak, jnp.min(aux["margins"]))

    def batch_loss(params):
        loss, aux = jax.vmap(swing_loss, in_axes=(None, 0))(params, conds)
        return jnp.mean(loss), (loss, *aux)

    opt = optax.chain(optax.clip_by_global_norm(args.clip), optax.adam(args.lr))
    grad_fn = jax.jit(jax.value_and_grad(batch_loss, has_aux=True))

    @jax.jit
    def apply(params, opt_state, grad):
        updates, opt_state = opt.update(grad, opt_state, params)
        return optax.apply_updates(params, updates), opt_state

    params, opt_state = ls0.params, opt.init(ls0.params)
    hist = {"loss": [], "peak": [], "min_margin": [], "grad_norm": [], "finite": []}
    t0 = time.perf_counter()
    n_eval = args.epochs + 1 if "bptt" in args.arms else 0  # the last: the trained networks
    for epoch in range(n_eval):
        (loss, (loss_b, peak_b, margin_b)), grad = grad_fn(params)
        finite = all(bool(np.all(np.isfinite(g))) for g in jax.tree_util.tree_leaves(grad))
        hist["loss"].append(np.asarray(loss_b))
        hist["peak"].append(np.asarray(peak_b))
        hist["min_margin"].append(float(margin_b.min()))
        hist["grad_norm"].append(float(optax.global_norm(grad)))
        hist["finite"].append(finite)
        print(
            f"epoch {epoch:3d} loss {float(loss):.5f} peak {float(np.mean(peak_b)):7.2f} N "
            f"|grad| {hist['grad_norm'][-1]:.3g} finite {finite}",
            flush=True,
        )
        if not finite:
            raise FloatingPointError(f"non-finite gradient at epoch {epoch}")
        if epoch < args.epochs:
            params, opt_state = apply(params, opt_state, grad)
    timing["bptt"] = time.perf_counter() - t0

    metrics = {
        "batch": args.batch,
        "swings": config.swings,
        "plain_peak_force": tl.mean_std(peak_plain),
        "conditions_reaching_hand": int(np.sum(peak_plain > 0)),
        "timing_s": {**timing, "total": time.perf_counter() - t_start},
    }
    for arm, logs in online.items():
        peaks = tl.force_norm(logs).max(-1)
        learning = logs["learning"]
        metrics[arm] = {
            "final_peak_force": tl.mean_std(peaks[:, -1]),
            "final_over_plain": tl.mean_std(peaks[reach, -1] / peak_plain[reach]),
            "swings_to_convergence": converged_at(peaks.mean(0)),
            "peak_force_per_swing_mean": peaks.mean(0).tolist(),
            "stable_every_sample": bool(np.all(logs["margins"] > 0)),
            "finite": bool(
                all(np.all(np.isfinite(v)) for v in logs.values() if v.dtype.kind == "f")
            ),
        }
        if arm == "exact":
            ex, pa = logs["de_df_exact"][learning], logs["de_df_paper"][learning]
            ne, npa = np.linalg.norm(ex, axis=-1), np.linalg.norm(pa, axis=-1)
            ok = (ne > 0) & (npa > 0)
            cos = np.sum(ex * pa, axis=-1)[ok] / (ne * npa)[ok]
            metrics[arm]["de_df_cosine_paper_vs_exact_median"] = float(np.median(cos))
            metrics[arm]["de_df_magnitude_paper_over_exact_median"] = float(
                np.median(npa[ok] / ne[ok])
            )
    if "bptt" in args.arms:
        # swing k of bptt = the networks after k - 1 updates (swing 1: the initial networks)
        peak_bptt = np.stack(hist["peak"][: args.epochs], axis=1)  # (batch, swings)
        final_bptt = hist["peak"][args.epochs]
        mean_bptt = peak_bptt.mean(0)
        metrics["bptt"] = {
            "final_peak_force": tl.mean_std(final_bptt),
            "final_over_plain": tl.mean_std(final_bptt[reach] / peak_plain[reach]),
            "swings_to_convergence": converged_at(np.append(mean_bptt, final_bptt.mean())),
            "peak_force_per_swing_mean": mean_bptt.tolist() + [float(final_bptt.mean())],
            "loss_per_swing": [float(x.mean()) for x in hist["loss"]],
            "gradients_finite_every_step": bool(all(hist["finite"])),
            "min_stability_margin": float(min(hist["min_margin"])),
        }
    write_json(folder / "metrics.json", metrics)
    curves = {f"peak_{a}": tl.force_norm(lg).max(-1) for a, lg in online.items()}
    if "bptt" in args.arms:
        curves["peak_bptt"] = np.stack(hist["peak"], axis=1)
        curves["loss_bptt"] = np.stack(hist["loss"], axis=1)
    write_npz(folder / "history.npz", peak_plain=peak_plain, **curves)
    plot(folder, curves, peak_plain)
    print(f"run folder: {folder}")
    for name in ("paper", "exact", "bptt"):
        if name not in metrics:
            continue
        mm = metrics[name]
        print(
            f"{name:6s} final peak {mm['final_peak_force']['mean']:6.1f} N "
            f"({mm['final_over_plain']['mean']:.2f} of plain), "
            f"swings to convergence {mm['swings_to_convergence']}"
        )
    return metrics


def plot(folder, curves, peak_plain):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = {
        "peak_paper": ("o-", "paper's rule (online, Eqs. 55-58)"),
        "peak_exact": ("^-", "online, exact one-step dE/dF_act"),
        "peak_bptt": ("s-", "BPTT + Adam, one set of nets"),
    }
    fig, ax = plt.subplots(figsize=(7, 4))
    for name, (fmt, label) in labels.items():
        if name in curves:
            c = curves[name]
            k = np.arange(1, c.shape[1] + 1)
            ax.errorbar(k, c.mean(0), c.std(0), fmt=fmt, label=label)
    ax.axhline(peak_plain.mean(), color="k", ls=":", label="plain impedance")
    ax.set(xlabel="swing", ylabel="peak |F_int| [N] (mean +- std over conditions)")
    ax.legend()
    fig.tight_layout()
    save_figure(fig, folder / "peak_force_per_swing.png")
    plt.close(fig)


if __name__ == "__main__":
    main()
