"""The paper's dE/dw against the exact one: one step and H-step horizons, catching and hitting,
over a few pendulum conditions (issue 6, item 2).

    python experiments/gradients_horizon.py --out runs/gradients_horizon --seed 0

Per task (catching as ``experiments/gradients.py``; hitting with ``experiments/hitting.py``'s
defaults: the bouncy pad, mu = 1e-5, F_hd = 5 N) the networks learn online for ``--swings`` swings
(the paper's rule), then one more swing is run with the weights w frozen: the *sampled swing*.

**One step** (every ``--stride``-th sample inside the sphere of the sampled swing, for each of the
``--conditions``): the paper's dE/dF_act = dE/dX_e dt^2 + dE/dX_e' dt (Eqs. 55-58) against the exact
dE/dX (t) . d(X_e, X_e')(t + dt)/dF_act(t) through one MJX control step
(``gradients.make_one_step``, forward mode), compared in F_act (2 components; both reach the
weights through the same dF_o/dw). Both use the energy gradient at t, so this isolates the
unit-mass Jacobian of Eqs. 55-58.

**Horizons** (default conditions, ``--per-phase`` states per phase of the sampled swing): from the
state (MJX data, policy state, last contact force) reached at sample k,

    exact:  d/dw  sum_{j=1..H} [learning(k+j)] E(k+j)       (weights w frozen over the horizon)
    paper:  sum_{j=0..H-1} g_paper(k+j),  g_paper = (dE/dF_act)_paper^T dF_o/dw (Eqs. 52-53)

for H in ``--horizons``. The exact one is reverse mode through the closed loop (networks, impedance
law, MJX with the implicitly differentiated contact solve of ``hec_jax.mjx_scene.differentiable``,
float64), all network weights (3 networks x 2 axes, 3246 weights). ``g_paper`` is the online
learner's own weight step at each sample (its update run with eta = 1, the weights then reset to w),
i.e. what the learner would apply over the H samples, with the state it would see if its weights
did not move. The exact gradient is checked against float64 central differences along a random
direction at one state per task. Phases: approach (inside the sphere, no contact yet in this
encounter), contact, after contact (touched in this encounter, no contact now).

Writes ``config.json``, ``metrics.json``, ``samples.npz``, ``table.md``, ``one_step_sweep.png``
and ``horizons.png``.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from experiments import gradients as gr  # noqa: E402
from experiments import task_loop as tl  # noqa: E402
from hec_jax.mjx_scene import default_conditions, differentiable, observe_stages  # noqa: E402
from hec_jax.mjx_scene import rollout as mjx_rollout  # noqa: E402
from hec_jax.nets import LearnerConfig  # noqa: E402
from hec_jax.runs import enable_compile_cache, save_figure, start_run, write_json, write_npz  # noqa: E402

PHASES = ("approach", "contact", "after_contact")
CONDITIONS = {  # name -> overrides of default_conditions (each reaches the waiting hand)
    "default": {},
    "rod_0.57": {"rod_length": 0.57},
    "cube_0.9kg": {"cube_mass": 0.9},
    "release_-0.6": {"release_angle": -0.6},
}


def task_config(task: str, swings: int) -> tl.TaskConfig:
    if task == "catching":  # as experiments/gradients.py
        lc = LearnerConfig(task="catching", r_b=0.085, eta=(0.3,) * 3, contact_stiffness=1e5)
        return tl.TaskConfig(learner=lc, swing_steps=1500, swings=swings)
    from experiments import hitting

    args = hitting.parse([])
    lc = tl.learner_from_args(args, "hitting", args.f_hd)
    return tl.config_from_args(args, lc, args.train_swing_s, swings)


def paper_rule_policy(loop: tl.Loop):
    """``loop.policy`` (switches "learned") with the weights held fixed; logs the learner's own weight
    step (eta = 1) as ``g_paper`` and its latched X_r'(t_c) and contact flag."""

    def policy(ps, m, step):
        w = ps.learner.params
        tau, ps_new, aux = loop.policy(ps, m, step)
        g = jax.tree_util.tree_map(lambda a, b: a - b, w, ps_new.learner.params)
        ps_new = ps_new._replace(learner=ps_new.learner._replace(params=w))
        aux = dict(aux, g_paper=g, xd_r_tc=ps_new.learner.xd_r_tc, touched=ps_new.learner.touched)
        return tau, ps_new, aux

    return policy


def flat(tree, lead: int = 0) -> np.ndarray:
    leaves = [np.asarray(x) for x in jax.tree_util.tree_leaves(tree)]
    return np.concatenate([x.reshape(x.shape[:lead] + (-1,)) for x in leaves], axis=-1)


def cos_ratio(paper: np.ndarray, exact: np.ndarray):
    """Cosine and |paper| / |exact| along the last axis (NaN where either is 0)."""
    n_p, n_e = np.linalg.norm(paper, axis=-1), np.linalg.norm(exact, axis=-1)
    ok = (n_p > 0) & (n_e > 0)
    den = np.where(ok, n_p * n_e, 1.0)
    cos = np.where(ok, np.sum(paper * exact, -1) / den, np.nan)
    return cos, np.where(ok, n_p / np.where(ok, n_e, 1.0), np.nan)


def phases_of(log: dict) -> np.ndarray:
    """-1 outside the sphere, else 0 approach, 1 contact, 2 after contact."""
    ph = np.where(log["in_contact"], 1, np.where(log["touched"], 2, 0))
    return np.where(log["inside"], ph, -1)


def stats(x: np.ndarray) -> dict:
    x = x[np.isfinite(x)]
    if not x.size:
        return {"n": 0}
    q = np.percentile(x, [0, 10, 50, 90, 100])
    return {
        "n": int(x.size),
        **dict(zip(("min", "p10", "median", "p90", "max"), map(float, q), strict=True)),
    }


class Task:
    """Compiled pieces of one task (one compile serves every pendulum condition)."""

    def __init__(self, name: str, swings: int, horizons: tuple[int, ...]):
        self.name = name
        self.config = task_config(name, swings)
        self.loop = tl.build_loop(self.config, default_conditions())
        # the frozen loop's learner steps with eta = 1, so that its weight step is its gradient
        unit = dataclasses.replace(self.config.learner, eta=(1.0, 1.0, 1.0))
        self.policy = paper_rule_policy(
            tl.build_loop(dataclasses.replace(self.config, learner=unit), default_conditions())
        )
        self.steps = self.config.swing_steps
        self.horizons = horizons
        loop, ids = self.loop, self.loop.ids

        def swing(ls, sw, c):
            m = loop.model_for(c)
            d0 = loop.data_for(m, c)
            ps0 = loop.initial_policy_state(d0, ls, sw)
            (_, ps), traj = mjx_rollout(m, ids, d0, loop.policy, ps0, jnp.zeros((self.steps, 3)), c)
            aux = {k: v for k, v in traj.aux.items()}
            log = dict(aux, f_contact=traj.f_contact, qpos=traj.qpos, qvel=traj.qvel)
            return ps.learner._replace(was_inside=jnp.asarray(False)), log

        def frozen_swing(ls, c):
            m = loop.model_for(c)
            d0 = loop.data_for(m, c)
            ps0 = loop.initial_policy_state(d0, ls, tl.switches("learned"))
            _, traj = mjx_rollout(m, ids, d0, self.policy, ps0, jnp.zeros((self.steps, 3)), c)
            aux = {k: v for k, v in traj.aux.items() if k != "g_paper"}
            return dict(aux, f_contact=traj.f_contact, qpos=traj.qpos, qvel=traj.qvel)

        def segment(d, ps, f0, c, n):
            """Advance the frozen loop by n (< swing_steps) steps from (d, ps, f0)."""
            m = loop.model_for(c)
            active = jnp.arange(self.steps) < n
            (d, ps), traj = mjx_rollout(
                m, ids, d, self.policy, ps, jnp.zeros((self.steps, 3)), c, f0, active
            )
            return d, ps, traj.f_contact[jnp.maximum(n - 1, 0)]

        def start(ls, c):
            m = loop.model_for(c)
            d0 = loop.data_for(m, c)
            return d0, loop.initial_policy_state(d0, ls, tl.switches("learned"))

        h_max = max(horizons)

        def horizon_losses(w, d, ps, f0, c):
            m = loop.model_for(c)
            ps = ps._replace(learner=ps.learner._replace(params=w))
            _, traj = mjx_rollout(
                m,
                ids,
                d,
                self.policy,
                ps,
                jnp.zeros((h_max + 1, 3)),
                c,
                f0,
                observe=observe_stages,
                dynamics=differentiable.dynamics_stages,
                checkpoint=True,
            )
            e = jnp.where(traj.aux["learning"], traj.aux["energy"], 0.0)
            cum = jnp.cumsum(e[1:])
            losses = jnp.stack([cum[h - 1] for h in horizons])
            g_paper = jax.tree_util.tree_map(
                lambda g: jnp.stack([jnp.sum(g[:h], 0) for h in horizons]), traj.aux["g_paper"]
            )
            return losses, g_paper

        self.swing = jax.jit(swing)
        self.frozen_swing = jax.jit(frozen_swing)
        self.segment = jax.jit(segment)
        self.start = jax.jit(start)
        self.losses = jax.jit(lambda w, d, ps, f0, c: horizon_losses(w, d, ps, f0, c)[0])
        self.horizon_grads = jax.jit(jax.jacrev(horizon_losses, has_aux=True))
        one_step = gr.make_one_step(self.loop, self.config)
        self.jac = jax.jit(jax.vmap(jax.jacfwd(one_step), in_axes=(0, 0, 0, 0, None)))

    def sampled_swing(self, key, c):
        ls = self.loop.learner_init(key, jnp.float64)
        peaks = []
        for _ in range(self.config.swings):
            ls, log = self.swing(ls, tl.switches("learned"), c)
            peaks.append(float(np.max(np.linalg.norm(np.asarray(log["f_contact"]), axis=-1))))
        log = jax.tree_util.tree_map(np.asarray, self.frozen_swing(ls, c))
        log["touched"] = np.asarray(log["touched"])
        return ls, log, peaks

    def one_step(self, log: dict, c, stride: int) -> dict:
        """Paper's vs exact one-step dE/dF_act at every ``stride``-th sample inside the sphere."""
        idx = np.flatnonzero(log["inside"])[::stride]
        f_prev = np.concatenate([np.zeros((1, 3)), log["f_contact"][:-1]])
        m = self.loop.model_for(c)
        exact = np.asarray(
            self.jac(
                *(jnp.asarray(a[idx]) for a in (log["f_o"], log["qpos"], log["qvel"], f_prev)), m
            )
        )
        g_x, g_v = gr.energy_gradients(
            self.config.learner, log, idx, log["xd_r_tc"][idx], log["touched"][idx]
        )
        g = np.concatenate([np.asarray(g_x), np.asarray(g_v)], axis=1)
        dt = self.config.controller.dt
        paper_jac = np.concatenate([dt**2 * np.eye(2), dt * np.eye(2)])
        cos, ratio = cos_ratio(g @ paper_jac, np.einsum("ni,nij->nj", g, exact))
        return dict(step=idx, phase=phases_of(log)[idx], cosine=cos, ratio=ratio, exact_jac=exact)

    def horizon_samples(self, ls, log, c, per_phase: int) -> list[dict]:
        """Exact vs paper dE/dw over each horizon from ``per_phase`` states of each phase."""
        ph = phases_of(log)
        last = self.steps - max(self.horizons) - 2
        picks = []
        for k in range(3):
            cand = np.flatnonzero((ph == k) & (np.arange(self.steps) <= last))
            if cand.size:
                sel = np.linspace(0, cand.size - 1, min(per_phase, cand.size)).round().astype(int)
                picks += list(cand[np.unique(sel)])
        picks = sorted(picks)
        d, ps = self.start(ls, c)
        f0, at = jnp.zeros(3), 0
        rows = []
        for k in picks:
            d, ps, f0 = self.segment(d, ps, f0, c, k - at)
            at = k
            drift = float(np.max(np.abs(np.asarray(d.qpos) - log["qpos"][k])))
            w = ps.learner.params
            g_ex, g_pa = self.horizon_grads(w, d, ps, f0, c)
            g_ex, g_pa = flat(g_ex, 1), flat(g_pa, 1)
            cos, ratio = cos_ratio(g_pa, g_ex)
            rows.append(
                dict(
                    step=int(k),
                    phase=int(ph[k]),
                    cosine=cos,
                    ratio=ratio,
                    exact_norm=np.linalg.norm(g_ex, axis=-1),
                    paper_norm=np.linalg.norm(g_pa, axis=-1),
                    finite=bool(np.all(np.isfinite(g_ex))),
                    replay_qpos_drift=drift,
                    state=(w, d, ps, f0),
                    g_exact=g_ex,
                )
            )
        return rows

    def fd_check(self, row, c, rng, h: float = 1e-6) -> dict:
        """Exact H-step gradients along a random weight direction vs float64 central differences."""
        w, d, ps, f0 = row["state"]
        leaves, treedef = jax.tree_util.tree_flatten(w)
        v = [rng.standard_normal(np.shape(x)) for x in leaves]
        v = [x / np.sqrt(sum(np.sum(y**2) for y in v)) for x in v]
        shift = lambda s: jax.tree_util.tree_unflatten(  # noqa: E731
            treedef, [x + s * y for x, y in zip(leaves, v, strict=True)]
        )
        lp = np.asarray(self.losses(shift(h), d, ps, f0, c))
        lm = np.asarray(self.losses(shift(-h), d, ps, f0, c))
        fd = (lp - lm) / (2 * h)
        ad = row["g_exact"] @ np.concatenate([x.ravel() for x in v])
        rel = np.abs(ad - fd) / np.maximum(np.abs(fd), 1e-300)
        return {
            "step": row["step"],
            "phase": PHASES[row["phase"]],
            "h": h,
            "horizons": list(self.horizons),
            "autodiff": ad.tolist(),
            "central_differences": fd.tolist(),
            "rel_error": rel.tolist(),
        }


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=Path("runs/gradients_horizon"))
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--tasks", nargs="+", default=["catching", "hitting"])
    p.add_argument("--swings", type=int, default=5, help="learning swings before the sampled one")
    p.add_argument("--stride", type=int, default=2, help="one-step: every n-th sample inside")
    p.add_argument("--horizons", type=int, nargs="+", default=[1, 10, 50, 200])
    p.add_argument("--per-phase", type=int, default=3, help="horizon states per phase")
    p.add_argument("--conditions", nargs="+", default=list(CONDITIONS), choices=list(CONDITIONS))
    args = p.parse_args(argv)
    enable_compile_cache()
    folder = start_run(args.out, args.seed, {k: v for k, v in vars(args).items() if k != "seed"})
    rng = np.random.default_rng(args.seed)
    key = jax.random.PRNGKey(args.seed)
    horizons = tuple(sorted(args.horizons))
    metrics, npz, one_step_all, horizon_all = {"timing_s": {}}, {}, {}, {}
    for name in args.tasks:
        t0 = time.perf_counter()
        task = Task(name, args.swings, horizons)
        mt = metrics[name] = {"one_step": {}, "horizons": {}}
        for cname in args.conditions:
            c = default_conditions(**CONDITIONS[cname])
            ls, log, peaks = task.sampled_swing(key, c)
            res = task.one_step(log, c, args.stride)
            one_step_all[(name, cname)] = res
            entry = {
                "peak_force_per_learning_swing": peaks,
                "sampled_swing_peak_force": float(np.linalg.norm(log["f_contact"], axis=-1).max()),
                "samples_inside": int(len(res["step"])),
                "finite": bool(np.all(np.isfinite(res["exact_jac"]))),
            }
            for k, ph in enumerate(PHASES):
                sel = res["phase"] == k
                entry[ph] = {"cosine": stats(res["cosine"][sel]), "ratio": stats(res["ratio"][sel])}
            mt["one_step"][cname] = entry
            for f in ("step", "phase", "cosine", "ratio"):
                npz[f"{name}/one_step/{cname}/{f}"] = res[f]
            print(f"{name} {cname}: one step, {len(res['step'])} samples", flush=True)
            if cname != "default":
                continue
            rows = task.horizon_samples(ls, log, c, args.per_phase)
            horizon_all[name] = rows
            mt["horizons"]["samples"] = [
                {
                    "step": r["step"],
                    "phase": PHASES[r["phase"]],
                    "cosine": r["cosine"].tolist(),
                    "ratio_paper_over_exact": r["ratio"].tolist(),
                    "exact_norm": r["exact_norm"].tolist(),
                    "paper_norm": r["paper_norm"].tolist(),
                    "finite": r["finite"],
                    "replay_qpos_drift": r["replay_qpos_drift"],
                }
                for r in rows
            ]
            for f in ("step", "phase", "cosine", "ratio", "exact_norm", "paper_norm"):
                npz[f"{name}/horizons/{f}"] = np.array([r[f] for r in rows])
            smooth = [r for r in rows if r["phase"] == 0] or rows
            mt["horizons"]["fd_check"] = task.fd_check(smooth[0], c, rng)
            print(f"{name}: horizons, {len(rows)} states; fd {mt['horizons']['fd_check']}")
        metrics["timing_s"][name] = time.perf_counter() - t0
    metrics["horizons"] = list(horizons)
    table = make_table(metrics, args, horizons, one_step_all, horizon_all)
    (folder / "table.md").write_text(table)
    write_json(folder / "metrics.json", metrics)
    write_npz(folder / "samples.npz", **{k.replace("/", "__"): v for k, v in npz.items()})
    plot(folder, one_step_all, horizon_all, horizons)
    print(table)
    print(f"run folder: {folder}")
    return metrics


def _fmt(s: dict, key: str = "median") -> str:
    if not s.get("n"):
        return "-"
    return f"{s[key]:.4g} [{s['min']:.3g}, {s['max']:.3g}]"


def make_table(metrics, args, horizons, one_step_all, horizon_all) -> str:
    out = [
        "One step (paper's dE/dF_act vs exact through one MJX step), every "
        f"{args.stride}nd sample inside the sphere of the sampled swing; median [min, max]:",
        "",
        "| task | condition | phase | n | cosine | |paper| / |exact| |",
        "|---|---|---|---:|---|---|",
    ]
    for (name, cname), res in one_step_all.items():
        for k, ph in enumerate(PHASES):
            sel = res["phase"] == k
            if not sel.any():
                out.append(f"| {name} | {cname} | {ph} | 0 | - | - |")
                continue
            cs, rs = stats(res["cosine"][sel]), stats(res["ratio"][sel])
            out.append(f"| {name} | {cname} | {ph} | {int(sel.sum())} | {_fmt(cs)} | {_fmt(rs)} |")
    out += [
        "",
        "Horizons (default conditions): exact d/dw sum_{j=1..H} E vs the paper's rule summed over "
        "the same H samples, all 3246 weights; every sampled state (cosine / |paper| / |exact|; "
        "where either is 0, the two norms):",
        "",
        "| task | step | phase | " + " | ".join(f"H={h}" for h in horizons) + " |",
        "|---|---:|---|" + "---|" * len(horizons),
    ]
    for name, rows in horizon_all.items():
        for r in rows:
            cells = [
                f"{c:+.3f} / {q:.3g}" if np.isfinite(c) else f"(paper {pn:.2g}, exact {en:.2g})"
                for c, q, pn, en in zip(
                    r["cosine"], r["ratio"], r["paper_norm"], r["exact_norm"], strict=True
                )
            ]
            out.append(
                f"| {name} | {r['step']} | {PHASES[r['phase']]} | " + " | ".join(cells) + " |"
            )
    out.append("")
    for name in horizon_all:
        fd = metrics[name]["horizons"]["fd_check"]
        errs = ", ".join(
            f"H={h}: {e:.1e}" for h, e in zip(fd["horizons"], fd["rel_error"], strict=True)
        )
        out.append(
            f"{name}: exact H-step gradient vs central differences (h = {fd['h']}) along a random "
            f"direction at step {fd['step']} ({fd['phase']}): rel. error {errs}"
        )
    return "\n".join(out) + "\n"


def plot(folder, one_step_all, horizon_all, horizons):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colors = np.array(["C0", "C3", "C2"])
    names = sorted({n for n, _ in one_step_all})
    fig, ax = plt.subplots(2, len(names), figsize=(6 * len(names), 6), squeeze=False)
    markers = dict(zip(CONDITIONS, "o^sd", strict=True))
    for j, name in enumerate(names):
        for (n, cname), res in one_step_all.items():
            if n != name:
                continue
            ok = res["phase"] >= 0
            t = res["step"][ok] * 1e-3
            c = colors[res["phase"][ok]]
            ax[0, j].scatter(t, res["cosine"][ok], c=c, s=8, marker=markers[cname], label=cname)
            ax[1, j].scatter(t, res["ratio"][ok], c=c, s=8, marker=markers[cname])
        ax[0, j].set(title=f"{name}: one step, paper vs exact", ylabel="cosine")
        ax[1, j].set(xlabel="t [s] (blue approach, red contact, green after)", yscale="log")
        ax[1, j].set(ylabel="|paper| / |exact|")
        ax[0, j].legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, folder / "one_step_sweep.png")
    plt.close(fig)

    fig, ax = plt.subplots(2, len(horizon_all), figsize=(6 * len(horizon_all), 6), squeeze=False)
    for j, (name, rows) in enumerate(horizon_all.items()):
        for r in rows:
            kw = dict(color=colors[r["phase"]], marker="o", ms=3, lw=0.8)
            ax[0, j].plot(horizons, r["cosine"], **kw)
            ax[1, j].plot(horizons, r["ratio"], **kw)
        ax[0, j].set(title=f"{name}: dE/dw over H steps", ylabel="cosine", xscale="log")
        ax[1, j].set(xlabel="horizon H [samples]", ylabel="|paper| / |exact|", xscale="log")
        ax[1, j].set(yscale="log")
    fig.tight_layout()
    save_figure(fig, folder / "horizons.png")
    plt.close(fig)


if __name__ == "__main__":
    main()
