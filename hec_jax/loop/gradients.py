"""The paper's dE/dF_act and dE/dw (Eqs. 52-58) against exact ones, along the closed loop.

Two comparisons (``experiments/gradients.py``; results and their reading in docs/gradients.md):

* **One step** (:func:`one_step_comparison`): at samples inside the virtual sphere, the paper's
  dE/dF_act = dE/dX_e dt^2 + dE/dX_e' dt against dE/dX (t) . d(X_e, X_e')(t + dt)/dF_act(t)
  through one MJX control step (``hec_jax.loop.exact.make_one_step``, forward mode). Both use the
  energy gradient at t, so this isolates the unit-mass Jacobian of Eqs. 55-58.
* **Horizons** (:class:`HorizonProbe`): from the full state at sample k (MJX data, policy state,
  last contact force) of a swing with the weights w frozen,

      exact:  d/dw  sum_{j=1..H} [learning(k+j)] E(k+j)
      paper:  sum_{j=0..H-1} g_paper(k+j),  g_paper = (dE/dF_act)_paper^T dF_o/dw  (Eqs. 52-53)

  The exact one is reverse mode through the closed loop (networks, impedance law, MJX with the
  implicitly differentiated contact solve of ``hec_jax.mjx_scene.differentiable``), all network
  weights; ``g_paper`` is the online learner's own weight step (its update run with eta = 1, the
  weights then reset to w).

Phases of a sample inside the sphere: approach (no contact yet in this encounter), contact, after
contact (touched in this encounter, no contact now).
"""

from __future__ import annotations

import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np

from hec_jax.loop.config import TaskConfig
from hec_jax.loop.episodes import make_episodes
from hec_jax.loop.exact import make_one_step
from hec_jax.loop.policy import Loop, build_loop, switches
from hec_jax.mjx_scene import PendulumConditions, differentiable, observe_stages, rollout
from hec_jax.nets import LearnerConfig, LearnerInputs, SphereGeometry, task_energy

PHASES = ("approach", "contact", "after_contact")


def unit_mass_jacobian(dt: float) -> np.ndarray:
    """The paper's d(X_e, X_e')(t + dt) / dF_act (4, 2): dt^2 I over dt I (Eqs. 55-58)."""
    return np.concatenate([dt**2 * np.eye(2), dt * np.eye(2)])


def energy_gradients(lc: LearnerConfig, log: dict, idx: np.ndarray, v_tc, touched):
    """(dE/dX_e, dE/dX_e') (n, 2) each of the task energy at the samples ``idx`` of one swing's
    ``log`` (x_e, xd_e, x_o, xd_o, f_int, in_contact), with X_r'(t_c) ``v_tc`` (n, 2) and the
    touched flags (n,).
    """

    def grad_at(x_e, xd_e, x_o, xd_o, f_int, contact, v, t):
        z = jnp.zeros(2)
        sphere = SphereGeometry(z, z, z)  # not used by the energy
        inputs = LearnerInputs(x_e, xd_e, z, x_o, xd_o, z, f_int, contact, sphere)
        return jax.grad(lambda a, b: task_energy(lc, a, b, inputs, v, t), argnums=(0, 1))(x_e, xd_e)

    fields = [jnp.asarray(log[k][idx]) for k in ("x_e", "xd_e", "x_o", "xd_o", "f_int")]
    contact = jnp.asarray(log["in_contact"][idx])
    return jax.vmap(grad_at)(*fields, contact, jnp.asarray(v_tc), jnp.asarray(touched))


def cos_ratio(paper: np.ndarray, exact: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cosine and |paper| / |exact| along the last axis (NaN where either is 0)."""
    n_p, n_e = np.linalg.norm(paper, axis=-1), np.linalg.norm(exact, axis=-1)
    ok = (n_p > 0) & (n_e > 0)
    cos = np.where(ok, np.sum(paper * exact, -1) / np.where(ok, n_p * n_e, 1.0), np.nan)
    return cos, np.where(ok, n_p / np.where(ok, n_e, 1.0), np.nan)


def stats(x: np.ndarray) -> dict:
    """n, min, p10, median, p90, max of the finite values of ``x``."""
    x = x[np.isfinite(x)]
    if not x.size:
        return {"n": 0}
    q = np.percentile(x, [0, 10, 50, 90, 100])
    names = ("min", "p10", "median", "p90", "max")
    return {"n": int(x.size), **dict(zip(names, map(float, q), strict=True))}


def phases_of(log: dict) -> np.ndarray:
    """-1 outside the sphere, else 0 approach, 1 contact, 2 after contact (logs of
    :class:`HorizonProbe` swings, which carry the learner's ``touched`` flag).
    """
    ph = np.where(log["in_contact"], 1, np.where(log["touched"], 2, 0))
    return np.where(log["inside"], ph, -1)


def make_jacobian(loop: Loop):
    """Jitted ``jac(f_o (n, 2), qpos (n, nq), qvel (n, nv), f_prev (n, 3), m) -> (n, 4, 2)``: the
    exact one-step Jacobians at n logged states (forward mode), and the jitted one step itself.
    """
    one_step = make_one_step(loop)
    jac = jax.jit(jax.vmap(jax.jacfwd(one_step), in_axes=(0, 0, 0, 0, None)))
    return jac, jax.jit(one_step)


def one_step_comparison(loop: Loop, jac, log: dict, idx, v_tc, touched, m) -> dict:
    """Paper's vs exact one-step dE/dF_act at samples ``idx`` of one swing's ``log``.

    Returns a dict of arrays over the samples: ``exact`` (n, 4, 2) Jacobians, ``jac_rel_err``
    (Frobenius error of the unit-mass Jacobian relative to it), ``cosine`` and ``ratio``
    (|paper| / |exact| of dE/dF_act, NaN where either is 0).
    """
    f_prev = np.concatenate([np.zeros((1, 3)), log["f_contact"][:-1]])  # measured at step k
    args = (jnp.asarray(a[idx]) for a in (log["f_o"], log["qpos"], log["qvel"], f_prev))
    exact = np.asarray(jac(*args, m))
    paper = unit_mass_jacobian(loop.ids.timestep)
    jac_rel_err = np.linalg.norm(exact - paper, axis=(1, 2)) / np.linalg.norm(paper)
    g_x, g_v = energy_gradients(loop.config.learner, log, idx, v_tc, touched)
    g = np.concatenate([np.asarray(g_x), np.asarray(g_v)], axis=1)  # (n, 4)
    cosine, ratio = cos_ratio(g @ paper, np.einsum("ni,nij->nj", g, exact))
    return dict(exact=exact, jac_rel_err=jac_rel_err, cosine=cosine, ratio=ratio)


def jacobian_fd_error(one_step, jac_exact: np.ndarray, log: dict, k: int, m, h=1e-3) -> float:
    """Max relative error of one exact Jacobian (4, 2) at step ``k`` against central differences
    in F_o with step ``h`` [N] (one step is affine in F_o away from saturation and contact onset),
    row by row: each row's largest error over that row's largest entry. The position rows
    (about dt^2) are some 1000 times smaller than the velocity rows (about dt); one scale for the
    whole matrix would hide their errors.
    """
    f_prev = np.concatenate([np.zeros((1, 3)), log["f_contact"][:-1]])
    rest = (jnp.asarray(log["qpos"][k]), jnp.asarray(log["qvel"][k]), jnp.asarray(f_prev[k]), m)
    f_o = jnp.asarray(log["f_o"][k])
    cols = [
        (one_step(f_o + h * e, *rest) - one_step(f_o - h * e, *rest)) / (2 * h) for e in np.eye(2)
    ]
    fd = np.stack([np.asarray(c) for c in cols], axis=1)
    scale = np.max(np.abs(jac_exact), axis=1)
    err = np.max(np.abs(fd - jac_exact), axis=1)
    # a zero row of the exact Jacobian: exact if the differences give zero too, else inf
    rel = np.where(scale > 0, err / np.where(scale > 0, scale, 1.0), np.where(err > 0, np.inf, 0.0))
    return float(np.max(rel))


def _paper_rule_policy(loop: Loop):
    """``loop.policy`` with the weights held fixed; logs the learner's own weight step as
    ``g_paper`` (the loop's eta: build it with eta = 1) and its X_r'(t_c) and touched flag.
    """

    def policy(ps, m, step):
        w = ps.learner.params
        tau, ps_new, aux = loop.policy(ps, m, step)
        g = jax.tree_util.tree_map(lambda a, b: a - b, w, ps_new.learner.params)
        ps_new = ps_new._replace(learner=ps_new.learner._replace(params=w))
        aux = dict(aux, g_paper=g, xd_r_tc=ps_new.learner.xd_r_tc, touched=ps_new.learner.touched)
        return tau, ps_new, aux

    return policy


def _flat(tree, lead: int = 0) -> np.ndarray:
    leaves = [np.asarray(x) for x in jax.tree_util.tree_leaves(tree)]
    return np.concatenate([x.reshape(x.shape[:lead] + (-1,)) for x in leaves], axis=-1)


class HorizonProbe:
    """Compiled pieces of the comparison for one task (one compile serves every condition).

    ``sampled_swing``: the task's swings of online learning (the paper's rule), then one swing
    with the weights frozen; ``one_step``: the one-step comparison along it;
    ``horizon_samples``: exact vs paper dE/dw over each horizon from states of each phase;
    ``fd_check``: an exact H-step gradient against float64 central differences.
    """

    def __init__(self, config: TaskConfig, horizons: tuple[int, ...]):
        self.config, self.horizons = config, tuple(sorted(horizons))
        self.loop = loop = build_loop(config)
        ids = loop.ids
        unit = dataclasses.replace(config.learner, eta=(1.0, 1.0, 1.0))  # weight step = gradient
        self.policy = _paper_rule_policy(build_loop(dataclasses.replace(config, learner=unit)))
        self.steps = n = loop.swing_steps
        h_max, learned = max(self.horizons), switches("learned")
        if h_max > n - 3:  # a sample needs its H steps and two more inside the swing
            raise ValueError(
                f"horizons up to {n - 3} samples fit a swing of {n} steps, got {h_max}"
            )

        def start(ls, c):
            m = loop.model_for(c)
            d0 = loop.data_for(m, c)
            return m, d0, loop.initial_policy_state(m, d0, ls, learned)

        def swing(ls, c):
            m, d0, ps0 = start(ls, c)
            (_, ps), traj = rollout(m, ids, d0, loop.policy, ps0, jnp.zeros((n, 3)), c)
            ls = ps.learner._replace(was_inside=jnp.asarray(False))
            return ls, jnp.max(jnp.linalg.norm(traj.f_contact, axis=-1))

        def frozen_swing(ls, c):
            m, d0, ps0 = start(ls, c)
            _, traj = rollout(m, ids, d0, self.policy, ps0, jnp.zeros((n, 3)), c)
            aux = {k: v for k, v in traj.aux.items() if k != "g_paper"}
            return dict(aux, f_contact=traj.f_contact, qpos=traj.qpos, qvel=traj.qvel)

        def segment(d, ps, f0, c, k):
            """Advance the frozen loop by k (< swing_steps) steps from (d, ps, f0)."""
            m = loop.model_for(c)
            active = jnp.arange(n) < k
            z = jnp.zeros((n, 3))
            (d, ps), traj = rollout(m, ids, d, self.policy, ps, z, c, f0, active)
            return d, ps, traj.f_contact[jnp.maximum(k - 1, 0)]

        def horizon_losses(w, d, ps, f0, c):
            m = loop.model_for(c)
            ps = ps._replace(learner=ps.learner._replace(params=w))
            _, traj = rollout(
                m, ids, d, self.policy, ps, jnp.zeros((h_max + 1, 3)), c, f0,
                observe=observe_stages, dynamics=differentiable.dynamics_stages, checkpoint=True,
            )  # fmt: skip
            cum = jnp.cumsum(jnp.where(traj.aux["learning"], traj.aux["energy"], 0.0)[1:])
            g_paper = jax.tree_util.tree_map(
                lambda g: jnp.stack([jnp.sum(g[:h], 0) for h in self.horizons]), traj.aux["g_paper"]
            )
            return jnp.stack([cum[h - 1] for h in self.horizons]), g_paper

        self.swing, self.frozen_swing = jax.jit(swing), jax.jit(frozen_swing)
        self.segment, self.start = jax.jit(segment), jax.jit(lambda ls, c: start(ls, c)[1:])
        self.losses = jax.jit(lambda *a: horizon_losses(*a)[0])
        self.horizon_grads = jax.jit(jax.jacrev(horizon_losses, has_aux=True))
        self.jac, _ = make_jacobian(loop)

    def sampled_swing(self, key, c: PendulumConditions):
        """(learner state, frozen swing's log as NumPy, peak force [N] per learning swing)."""
        ls = self.loop.learner_init(key, jnp.float64)
        peaks = []
        for _ in range(self.config.swings):
            ls, peak = self.swing(ls, c)
            peaks.append(float(peak))
        return ls, jax.tree_util.tree_map(np.asarray, self.frozen_swing(ls, c)), peaks

    def one_step(self, log: dict, c: PendulumConditions, stride: int) -> dict:
        """The one-step comparison at every ``stride``-th sample inside the sphere."""
        idx = np.flatnonzero(log["inside"])[::stride]
        res = one_step_comparison(
            self.loop, self.jac, log, idx, log["xd_r_tc"][idx], log["touched"][idx],
            self.loop.model_for(c),
        )  # fmt: skip
        return dict(res, step=idx, phase=phases_of(log)[idx])

    def horizon_samples(self, ls, log: dict, c: PendulumConditions, per_phase: int) -> list[dict]:
        """Exact vs paper dE/dw over each horizon from ``per_phase`` evenly spaced states of each
        phase of the frozen swing ``log`` (replayed from the release).
        """
        ph = phases_of(log)
        last = self.steps - max(self.horizons) - 2
        picks = []
        for k in range(3):
            cand = np.flatnonzero((ph == k) & (np.arange(self.steps) <= last))
            if cand.size:
                sel = np.linspace(0, cand.size - 1, min(per_phase, cand.size)).round().astype(int)
                picks += list(cand[np.unique(sel)])
        d, ps = self.start(ls, c)
        f0, at, rows = jnp.zeros(3), 0, []
        for k in sorted(picks):
            d, ps, f0 = self.segment(d, ps, f0, c, k - at)
            at = k
            w = ps.learner.params
            g_ex, g_pa = self.horizon_grads(w, d, ps, f0, c)
            g_ex, g_pa = _flat(g_ex, 1), _flat(g_pa, 1)
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
                    replay_qpos_drift=float(np.max(np.abs(np.asarray(d.qpos) - log["qpos"][k]))),
                    state=(w, d, ps, f0),
                    g_exact=g_ex,
                )
            )
        return rows

    def fd_check(self, row: dict, c: PendulumConditions, rng, h: float = 1e-6) -> dict:
        """Exact H-step gradients along a random weight direction vs central differences."""
        w, d, ps, f0 = row["state"]
        leaves, treedef = jax.tree_util.tree_flatten(w)
        v = [rng.standard_normal(np.shape(x)) for x in leaves]
        v = [x / np.sqrt(sum(np.sum(y**2) for y in v)) for x in v]

        def shifted(s):
            return jax.tree_util.tree_unflatten(
                treedef, [x + s * y for x, y in zip(leaves, v, strict=True)]
            )

        lp = np.asarray(self.losses(shifted(h), d, ps, f0, c))
        lm = np.asarray(self.losses(shifted(-h), d, ps, f0, c))
        fd = (lp - lm) / (2 * h)
        ad = row["g_exact"] @ np.concatenate([x.ravel() for x in v])
        return {
            "step": row["step"],
            "phase": PHASES[row["phase"]],
            "h": h,
            "horizons": list(self.horizons),
            "autodiff": ad.tolist(),
            "central_differences": fd.tolist(),
            "rel_error": (np.abs(ad - fd) / np.maximum(np.abs(fd), 1e-300)).tolist(),
        }


def one_step_along_learning(loop: Loop, key, stride: int) -> dict:
    """The one-step comparison along the last of the task's learning swings (one network
    initialisation, ``jax.random.split(key, 1)``, learning on), at every ``stride``-th sample inside the sphere, phases split at the first
    contact; plus ``fd_err``: :func:`jacobian_fd_error` at 4 evenly spaced samples.
    """
    c = loop.config.pendulum.conditions()
    logs = make_episodes(loop)(jax.random.split(key, 1), switches("learned"), c)
    log = {k: np.asarray(v[0, -1]) for k, v in logs.items()}  # the last swing
    inside = np.flatnonzero(log["inside"])
    contact = np.flatnonzero(log["in_contact"] & log["inside"])
    t_contact = contact[0] if contact.size else len(log["inside"])
    idx = inside[::stride]
    phase = np.where(idx < t_contact, 0, np.where(log["in_contact"][idx], 1, 2))
    v_tc = np.broadcast_to(log["xd_o"][inside[0]] - log["xd_e"][inside[0]], (len(idx), 2))
    jac, one_step = make_jacobian(loop)
    m = loop.model_for(c)
    res = one_step_comparison(loop, jac, log, idx, v_tc, idx >= t_contact, m)
    picks = np.linspace(0, len(idx) - 1, 4).astype(int)
    fd_err = [jacobian_fd_error(one_step, res["exact"][i], log, idx[i], m) for i in picks]
    return dict(res, step=idx, phase=phase, fd_err=fd_err)


def phase_summary(res: dict) -> dict:
    """Per phase of :func:`one_step_along_learning`'s samples: count, median Jacobian error,
    median and smallest cosine, median |paper| / |exact| (phases without such samples left out).
    """
    ok = np.isfinite(res["cosine"])
    out = {}
    for k, name in enumerate(PHASES):
        sel = (res["phase"] == k) & ok
        if sel.any():
            out[name] = {
                "n": int(sel.sum()),
                "jacobian_rel_error_median": float(
                    np.median(res["jac_rel_err"][res["phase"] == k])
                ),
                "cosine_median": float(np.nanmedian(res["cosine"][sel])),
                "cosine_min": float(np.nanmin(res["cosine"][sel])),
                "magnitude_ratio_paper_over_exact_median": float(np.nanmedian(res["ratio"][sel])),
            }
    return out


# name -> overrides of the task's pendulum (each swing reaches the waiting hand)
CONDITIONS = {
    "default": {},
    "rod_0.57": {"rod_length": 0.57},
    "cube_0.9kg": {"cube_mass": 0.9},
    "release_-0.6": {"release_angle": -0.6},
}


def horizon_comparison(
    tasks: dict[str, TaskConfig],
    conditions: tuple[str, ...],
    seed: int,
    stride: int,
    horizons: tuple[int, ...],
    per_phase: int,
    progress=print,
) -> tuple[dict, dict, dict]:
    """For each task: the one-step comparison along the frozen sampled swing under each of the
    named ``conditions`` (:data:`CONDITIONS`), and under "default" the horizon comparison from
    ``per_phase`` states per phase, with one float64 central-difference check. Returns
    (metrics, {(task, condition): one-step arrays}, {task: horizon rows}).
    """
    key, rng = jax.random.PRNGKey(seed), np.random.default_rng(seed)
    metrics, one_step_all, horizon_all = {"timing_s": {}}, {}, {}
    for name, config in tasks.items():
        t0 = time.perf_counter()
        probe = HorizonProbe(config, horizons)
        mt = metrics[name] = {"one_step": {}, "horizons": {}}
        for cname in conditions:
            c = dataclasses.replace(config.pendulum, **CONDITIONS[cname]).conditions()
            ls, log, peaks = probe.sampled_swing(key, c)
            res = one_step_all[(name, cname)] = probe.one_step(log, c, stride)
            entry = mt["one_step"][cname] = {
                "peak_force_per_learning_swing": peaks,
                "sampled_swing_peak_force": float(np.linalg.norm(log["f_contact"], axis=-1).max()),
                "samples_inside": int(len(res["step"])),
                "finite": bool(np.all(np.isfinite(res["exact"]))),
            }
            for k, ph in enumerate(PHASES):
                sel = res["phase"] == k
                entry[ph] = {"cosine": stats(res["cosine"][sel]), "ratio": stats(res["ratio"][sel])}
            progress(f"{name} {cname}: one step, {len(res['step'])} samples")
            if cname != "default":
                continue
            rows = horizon_all[name] = probe.horizon_samples(ls, log, c, per_phase)
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
            smooth = [r for r in rows if r["phase"] == 0] or rows
            mt["horizons"]["fd_check"] = probe.fd_check(smooth[0], c, rng)
            progress(f"{name}: horizons, {len(rows)} states; fd {mt['horizons']['fd_check']}")
        metrics["timing_s"][name] = time.perf_counter() - t0
    metrics["horizons"] = list(sorted(horizons))
    return metrics, one_step_all, horizon_all
