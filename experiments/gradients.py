"""The paper's dE/dF_act (Eqs. 54-58) against the exact one-step sensitivity through an MJX step.

    python experiments/gradients.py --out runs/gradients --seed 0

Eqs. 55-58 treat the hand as a unit mass over one sample: dX_e/dF_act = dt^2 I and
dX_e'/dF_act = dt I. Here the exact one-step Jacobian d(X_e, X_e')(t + dt) / dF_act(t) is computed
by forward-mode autodiff (``jax.jacfwd``, 2 columns) through one full simulated control step:
observation, impedance law (Eqs. 41-44, F_act = F_o entering as in Eq. 48), torque saturation,
actuation, MJX constraint solve (contact) and semi-implicit Euler, at states sampled along a
learned catching trajectory (float64). Forward mode works through MJX's solver ``while_loop``.

For each sampled state inside the virtual sphere the script reports the relative error of the
Jacobian and, with the catching energy's gradient (dE/dX_e, dE/dX_e') at that state, the cosine
similarity and magnitude ratio of the paper's dE/dF_act to the exact one-step one, split into the
approach (before contact), contact and after-contact phases. Writes ``config.json``,
``metrics.json``, ``samples.npz`` and ``one_step_gradients.png``.

Scope: one-step sensitivities along catching only; the hitting trajectory, the sweep of pendulum
conditions and the multi-step horizons (exact dE/dw through rollouts) are in
``experiments/gradients_horizon.py``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from mujoco import mjx  # noqa: E402

from experiments import task_loop as tl  # noqa: E402
from hec_jax.control import ImpedanceParams, impedance_torque, observe, task_jacobians  # noqa: E402
from hec_jax.mjx_scene import (  # noqa: E402
    TASK_AXES,
    SimStep,
    default_conditions,
    dynamics_stages,
    load_mj_model,
    observe_stages,
    scene_ids,
    solve_posture,
)
from hec_jax.nets import LearnerConfig, LearnerInputs, task_energy  # noqa: E402
from hec_jax.runs import save_figure, start_run, write_json, write_npz  # noqa: E402

PHASES = ("approach", "contact", "after_contact")


def make_one_step(loop: tl.Loop, config: tl.TaskConfig):
    """(f_o (2,), qpos, qvel, f_int_world (3,)[, m]) -> (X_e, X_e')(t + dt) (4,): one control step.

    ``m``: the MJX model to step (default ``loop.mx``); pass it as an argument to reuse one compiled
    function across pendulum conditions (``loop.model_for``)."""
    lc, cc = config.learner, config.controller
    params = ImpedanceParams(jnp.asarray(lc.m_e), jnp.asarray(lc.b_e), jnp.asarray(lc.k_e))
    target = tl.Target(jnp.asarray(config.x_home), jnp.zeros(2), jnp.zeros(2))
    m_c = load_mj_model()
    q_home = jnp.asarray(solve_posture(m_c, scene_ids(m_c), config.x_home))
    limit = jnp.asarray(cc.torque_limit)
    axes = np.array(TASK_AXES)
    dof = np.array(loop.ids.arm_dof)
    d_template = loop.initial_data()

    def one_step(f_o, qpos, qvel, f_int_world, m=None):
        m = loop.mx if m is None else m
        d = observe_stages(m, d_template.replace(qpos=qpos, qvel=qvel))
        obs = observe(m, loop.ids, SimStep(d=d, f_int=f_int_world, t=d.time))
        tau, _ = impedance_torque(obs, params, target, f_o, q_home, cc)
        d_acc, _ = dynamics_stages(m, loop.ids, d, jnp.clip(tau, -limit, limit))
        with jax.numpy_rank_promotion("allow"):
            d1 = observe_stages(m, mjx.euler(m, d_acc))
        J, _ = task_jacobians(m, d1, loop.ids)
        return jnp.concatenate([d1.site_xpos[loop.ids.hand_site][axes], J @ d1.qvel[dof]])

    return one_step


def energy_gradients(lc: LearnerConfig, logs: dict, idx: np.ndarray, v_tc, touched):
    """(dE/dX_e, dE/dX_e') (n, 2) each of the catching energy at the sampled states."""

    def grad_at(x_e, xd_e, x_o, xd_o, f_int, contact, v, t):
        inputs = LearnerInputs(x_e, xd_e, jnp.zeros(2), x_o, xd_o, jnp.zeros(2), f_int, contact)
        return jax.grad(lambda a, b: task_energy(lc, a, b, inputs, v, t), argnums=(0, 1))(x_e, xd_e)

    fields = [jnp.asarray(logs[k][idx]) for k in ("x_e", "xd_e", "x_o", "xd_o", "f_int")]
    contact = jnp.asarray(logs["in_contact"][idx])
    return jax.vmap(grad_at)(*fields, contact, jnp.asarray(v_tc), jnp.asarray(touched))


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=Path("runs/gradients"))
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--swings", type=int, default=10, help="learning swings before the sampled one")
    p.add_argument("--stride", type=int, default=2, help="sample every n-th step inside the sphere")
    args = p.parse_args(argv)
    folder = start_run(args.out, args.seed, {k: v for k, v in vars(args).items() if k != "seed"})
    lc = LearnerConfig(task="catching", r_b=0.085, eta=(0.3,) * 3, contact_stiffness=1e5)
    config = tl.TaskConfig(learner=lc, swing_steps=1500, swings=args.swings)
    pendulum = default_conditions()
    t0 = time.perf_counter()
    run = tl.make_experiment(config, pendulum)
    keys = jax.random.split(jax.random.PRNGKey(args.seed), 1)
    logs = jax.tree_util.tree_map(np.asarray, run(keys, tl.switches("learned")))
    last = {k: v[0, -1] for k, v in logs.items()}  # seed 0, last swing
    dt = config.controller.dt

    inside = last["inside"]
    steps = np.flatnonzero(inside)
    entry = steps[0]
    first_contact = np.flatnonzero(last["in_contact"] & inside)
    t_contact = first_contact[0] if first_contact.size else len(inside)
    idx = steps[:: args.stride]
    phase = np.where(idx < t_contact, 0, np.where(last["in_contact"][idx], 1, 2))
    xd_r = last["xd_o"] - last["xd_e"]
    v_tc = np.broadcast_to(xd_r[entry], (len(idx), 2))
    touched = idx >= t_contact

    one_step = make_one_step(tl.build_loop(config, pendulum), config)
    jac = jax.jit(jax.vmap(jax.jacfwd(one_step)))
    # The force measured at step k is the contact force solved at step k - 1 (as in the rollout).
    f_prev = np.concatenate([np.zeros((1, 3)), last["f_contact"][:-1]])
    exact = np.asarray(
        jac(
            jnp.asarray(last["f_o"][idx]),
            jnp.asarray(last["qpos"][idx]),
            jnp.asarray(last["qvel"][idx]),
            jnp.asarray(f_prev[idx]),
        )
    )  # (n, 4, 2)
    # Check the autodiff Jacobian against central differences (float64) at a few samples.
    fd_err = []
    step_jit = jax.jit(one_step)
    for i in np.linspace(0, len(idx) - 1, 4).astype(int):
        k = idx[i]
        args_k = (
            jnp.asarray(last["qpos"][k]),
            jnp.asarray(last["qvel"][k]),
            jnp.asarray(f_prev[k]),
        )
        h = 1e-3  # [N]; one_step is affine in F_o away from saturation and contact onset
        cols = [
            (
                step_jit(jnp.asarray(last["f_o"][k]) + h * e, *args_k)
                - step_jit(jnp.asarray(last["f_o"][k]) - h * e, *args_k)
            )
            / (2 * h)
            for e in np.eye(2)
        ]
        fd = np.stack([np.asarray(c) for c in cols], axis=1)
        fd_err.append(float(np.max(np.abs(fd - exact[i])) / np.max(np.abs(exact[i]))))
    paper = np.concatenate([dt**2 * np.eye(2), dt * np.eye(2)])[None]
    jac_rel_err = np.linalg.norm(exact - paper, axis=(1, 2)) / np.linalg.norm(paper)
    g_x, g_v = (np.asarray(g) for g in energy_gradients(lc, last, idx, v_tc, touched))
    g = np.concatenate([g_x, g_v], axis=1)  # (n, 4)
    de_exact = np.einsum("ni,nij->nj", g, exact)
    de_paper = np.einsum("ni,nij->nj", g, np.broadcast_to(paper, exact.shape))
    norm_e, norm_p = np.linalg.norm(de_exact, axis=1), np.linalg.norm(de_paper, axis=1)
    ok = (norm_e > 0) & (norm_p > 0)
    cosine = np.where(ok, np.sum(de_exact * de_paper, 1) / np.where(ok, norm_e * norm_p, 1), np.nan)
    ratio = np.where(ok, norm_p / np.where(ok, norm_e, 1), np.nan)
    wall = time.perf_counter() - t0

    metrics = {
        "samples": int(len(idx)),
        "wall_s": wall,
        "finite": bool(np.all(np.isfinite(exact))),
        "autodiff_vs_central_differences_max_rel_err": max(fd_err),
    }
    for k, name in enumerate(PHASES):
        sel = (phase == k) & ok
        if sel.any():
            metrics[name] = {
                "n": int(sel.sum()),
                "jacobian_rel_error_median": float(np.median(jac_rel_err[phase == k])),
                "cosine_median": float(np.nanmedian(cosine[sel])),
                "cosine_min": float(np.nanmin(cosine[sel])),
                "magnitude_ratio_paper_over_exact_median": float(np.nanmedian(ratio[sel])),
            }
    write_json(folder / "metrics.json", metrics)
    write_npz(
        folder / "samples.npz",
        step=idx,
        phase=phase,
        exact=exact,
        paper=paper[0],
        cosine=cosine,
        ratio=ratio,
        jac_rel_err=jac_rel_err,
    )
    plot(folder, idx * dt, phase, cosine, ratio, jac_rel_err, exact, dt)
    print(f"run folder: {folder}")
    for name in PHASES:
        if name in metrics:
            print(name, metrics[name])
    return metrics


def plot(folder, t, phase, cosine, ratio, jac_rel_err, exact, dt):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(3, 1, figsize=(8, 8), sharex=True)
    colors = np.array(["C0", "C3", "C2"])[phase]
    ax[0].scatter(t, cosine, c=colors, s=6)
    ax[0].set(
        ylabel="cosine(paper, exact)", title="dE/dF_act: paper (Eqs. 55-58) vs exact one step"
    )
    ax[1].scatter(t, ratio, c=colors, s=6)
    ax[1].set(ylabel="|paper| / |exact|", yscale="log")
    ax[2].plot(t, exact[:, 2, 0] / dt, ".", ms=3, label="dX_e'/dF_x (x) / dt")
    ax[2].plot(t, exact[:, 3, 1] / dt, ".", ms=3, label="dX_e'/dF_z (z) / dt")
    ax[2].axhline(1.0, color="k", lw=0.8, ls=":", label="paper: 1 (unit mass)")
    ax[2].set(xlabel="t [s] (blue: approach, red: contact, green: after contact)", ylabel="[1/kg]")
    ax[2].legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, folder / "one_step_gradients.png")
    plt.close(fig)


if __name__ == "__main__":
    main()
