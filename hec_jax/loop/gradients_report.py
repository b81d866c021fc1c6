"""Tables, arrays and figures of the gradient comparisons (:mod:`hec_jax.loop.gradients`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hec_jax.loop.gradients import CONDITIONS, PHASES, stats
from hec_jax.runs import save_figure

_COLORS = np.array(["C0", "C3", "C2"])  # approach, contact, after contact


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def one_step_figure(folder: Path, res: dict, dt: float) -> None:
    """``one_step_gradients.png``: cosine and magnitude ratio of the paper's dE/dF_act to the
    exact one-step one, and the exact dX_e'/dF_act per axis against the unit mass.
    """
    plt = _pyplot()
    t, exact, colors = res["step"] * dt, res["exact"], _COLORS[res["phase"]]
    fig, ax = plt.subplots(3, 1, figsize=(8, 8), sharex=True)
    ax[0].scatter(t, res["cosine"], c=colors, s=6)
    ax[0].set(
        ylabel="cosine(paper, exact)", title="dE/dF_act: paper (Eqs. 55-58) vs exact one step"
    )
    ax[1].scatter(t, res["ratio"], c=colors, s=6)
    ax[1].set(ylabel="|paper| / |exact|", yscale="log")
    ax[2].plot(t, exact[:, 2, 0] / dt, ".", ms=3, label="dX_e'/dF_x (x) / dt")
    ax[2].plot(t, exact[:, 3, 1] / dt, ".", ms=3, label="dX_e'/dF_z (z) / dt")
    ax[2].axhline(1.0, color="k", lw=0.8, ls=":", label="paper: 1 (unit mass)")
    ax[2].set(xlabel="t [s] (blue: approach, red: contact, green: after contact)", ylabel="[1/kg]")
    ax[2].legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, folder / "one_step_gradients.png")
    plt.close(fig)


def horizon_arrays(one_step_all: dict, horizon_all: dict) -> dict:
    """The per-sample arrays of :func:`hec_jax.loop.gradients.horizon_comparison` by name
    (``<task>__one_step__<condition>__<field>``, ``<task>__horizons__<field>``).
    """
    out = {}
    for (name, cname), res in one_step_all.items():
        for f in ("step", "phase", "cosine", "ratio"):
            out[f"{name}__one_step__{cname}__{f}"] = res[f]
    for name, rows in horizon_all.items():
        for f in ("step", "phase", "cosine", "ratio", "exact_norm", "paper_norm"):
            out[f"{name}__horizons__{f}"] = np.array([r[f] for r in rows])
    return out


def _fmt(s: dict, key: str = "median") -> str:
    if not s.get("n"):
        return "-"
    return f"{s[key]:.4g} [{s['min']:.3g}, {s['max']:.3g}]"


def horizon_table(metrics: dict, stride: int, one_step_all: dict, horizon_all: dict) -> str:
    """Markdown tables of the one-step sweep and the horizons (as in docs/gradients.md)."""
    horizons = metrics["horizons"]
    out = [
        "One step (paper's dE/dF_act vs exact through one MJX step), every "
        f"{stride}nd sample inside the sphere of the sampled swing; median [min, max]:",
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
        "the same H samples, all network weights; every sampled state (cosine / |paper| / "
        "|exact|; where either is 0, the two norms):",
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
            row = f"| {name} | {r['step']} | {PHASES[r['phase']]} | " + " | ".join(cells) + " |"
            out.append(row)
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


def horizon_figures(
    folder: Path, one_step_all: dict, horizon_all: dict, horizons, dt: float
) -> None:
    """``one_step_sweep.png`` (one-step cosine and ratio along the sampled swings, every
    condition) and ``horizons.png`` (cosine and ratio against H per state).
    """
    plt = _pyplot()
    names = sorted({n for n, _ in one_step_all})
    fig, ax = plt.subplots(2, len(names), figsize=(6 * len(names), 6), squeeze=False)
    markers = dict(zip(CONDITIONS, "o^sd", strict=True))
    for j, name in enumerate(names):
        for (n, cname), res in one_step_all.items():
            if n != name:
                continue
            ok = res["phase"] >= 0
            t, c = res["step"][ok] * dt, _COLORS[res["phase"][ok]]
            ax[0, j].scatter(t, res["cosine"][ok], c=c, s=8, marker=markers[cname], label=cname)
            ax[1, j].scatter(t, res["ratio"][ok], c=c, s=8, marker=markers[cname])
        ax[0, j].set(title=f"{name}: one step, paper vs exact", ylabel="cosine")
        ax[1, j].set(xlabel="t [s] (blue approach, red contact, green after)", yscale="log")
        ax[1, j].set(ylabel="|paper| / |exact|")
        ax[0, j].legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, folder / "one_step_sweep.png")
    plt.close(fig)
    if not horizon_all:
        return
    fig, ax = plt.subplots(2, len(horizon_all), figsize=(6 * len(horizon_all), 6), squeeze=False)
    for j, (name, rows) in enumerate(horizon_all.items()):
        for r in rows:
            kw = dict(color=_COLORS[r["phase"]], marker="o", ms=3, lw=0.8)
            ax[0, j].plot(horizons, r["cosine"], **kw)
            ax[1, j].plot(horizons, r["ratio"], **kw)
        ax[0, j].set(title=f"{name}: dE/dw over H steps", ylabel="cosine", xscale="log")
        ax[1, j].set(xlabel="horizon H [samples]", ylabel="|paper| / |exact|", xscale="log")
        ax[1, j].set(yscale="log")
    fig.tight_layout()
    save_figure(fig, folder / "horizons.png")
    plt.close(fig)
