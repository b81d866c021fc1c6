"""Metrics the paper cares about, per run (NumPy boundary): catching (relative speed at contact,
peak force, overshoot above F_cd after the impact transient, time to reach and stay within 20%
of F_cd, whether the cube is held) and hitting (periodic hits, the swing sustained, pulse peaks
against F_hd, energy returned per hit).

A run is one trajectory (steps, ...) of the protocol's logs (:mod:`hec_jax.loop.protocol`).
Nothing raises on what a run did: a run without contact gives ``None`` for what needs a contact.
"""

from __future__ import annotations

import numpy as np

from hec_jax.loop.metrics import contact_events, hit_series, mean_std

# [s] the impact transient: force samples within this time of the first contact are excluded from
# the overshoot (Fig. 6's impact spike is the impact, not the force control's overshoot).
IMPACT_TRANSIENT_S = 0.2
# [s] contacts closer than this are one contact episode (one impact may chatter)
CONTACT_MERGE_S = 0.02
# F_cd band for "reached and stays": |F_int| within 20% of F_cd.
FORCE_BAND = 0.2


def _norm(v: np.ndarray) -> np.ndarray:
    return np.linalg.norm(v, axis=-1)


def catching_run_metrics(
    log: dict, dt: float, f_cd: float, threshold: float, settle_s: float
) -> dict:
    """One catching run's metrics.

    Args:
        log: one run's arrays (steps, ...): ``f_contact`` (steps, 6), ``xd_o_true``, ``xd_e``
            (steps, 2).
        dt: [s] control period.
        f_cd: [N] desired holding force.
        threshold: [N] |F_int| above this is contact.
        settle_s: [s] window at the end over which ``settle_force`` is averaged.

    Returns:
        ``contact`` (bool), ``t_c_s`` [s] (first sample inside the virtual sphere, None if
        never; with ``inside`` logged), ``relative_speed_at_contact`` [m/s] (|X_o' - X_e'| one sample before
        the first contact), ``peak_force`` [N], ``overshoot_over_f_cd`` (largest |F_int| after
        the impact transient over F_cd), ``time_to_f_cd_s`` (from the first contact until |F_int|
        enters and stays in the +-20% band to the end; None if it never stays), ``settle_force``
        [N] and ``held`` (in contact over the whole last ``settle_s`` and one contact episode from
        the first contact on, merged over gaps under 20 ms).
    """
    f = _norm(log["f_contact"][:, [0, 2]])
    events = contact_events(f, threshold, min_gap=int(round(CONTACT_MERGE_S / dt)))
    tail = max(int(round(settle_s / dt)), 1)
    inside = np.asarray(log["inside"]) if "inside" in log else np.zeros(0, bool)
    out = {
        "contact": bool(events),
        "t_c_s": float(np.argmax(inside) * dt) if inside.any() else None,
        "peak_force": float(f.max()),
        "settle_force": float(f[-tail:].mean()),
    }
    if not events:
        return dict(
            out,
            relative_speed_at_contact=None,
            overshoot_over_f_cd=None,
            time_to_f_cd_s=None,
            held=False,
        )
    i0 = events[0][0]
    before = max(i0 - 1, 0)
    rel = float(_norm(log["xd_o_true"][before] - log["xd_e"][before]))
    after = f[i0 + int(round(IMPACT_TRANSIENT_S / dt)) :]
    outside = np.flatnonzero(np.abs(f - f_cd) > FORCE_BAND * f_cd)
    outside = outside[outside >= i0]
    last_out = int(outside[-1]) if outside.size else i0 - 1
    stays = last_out < f.shape[0] - 1
    held = bool(len(events) == 1 and events[0][1] == f.shape[0] and np.all(f[-tail:] > threshold))
    return dict(
        out,
        relative_speed_at_contact=rel,
        overshoot_over_f_cd=float(after.max() / f_cd) if after.size else None,
        time_to_f_cd_s=(last_out + 1 - i0) * dt if stays else None,
        held=held,
    )


def hitting_run_metrics(log: dict, dt: float, f_hd: float, threshold: float) -> dict:
    """One hitting run's metrics (a continuous run, several hits).

    Returns :func:`~hec_jax.loop.metrics.hit_series`' ``hits``, ``periodic_hits``,
    ``peak_forces`` and, per hit, ``approach_speeds`` [m/s] (the cube's speed one sample before
    the hit), ``speed_gain`` [m/s] (the cube's speed 10 ms after the hit minus 10 ms before it:
    > 0 the hand added energy; a ratio of energies is meaningless for a cube struck at rest);
    ``sustained`` = last approach speed of the periodic series
    over its first; ``pulse_over_f_hd`` = the largest pulse over F_hd.
    """
    f = _norm(log["f_contact"][:, [0, 2]])
    hs = hit_series(f, dt, threshold)
    events = contact_events(f, threshold, min_gap=int(round(0.05 / dt)))
    v = _norm(log["xd_o_true"])
    k = int(round(0.01 / dt))
    n = f.shape[0]
    approach = [float(v[max(a - 1, 0)]) for a, _ in events]
    gain = [float(v[min(b + k, n - 1)] - v[max(a - k, 0)]) for a, b in events]
    i0, m = hs["series_first_hit"], hs["periodic_hits"]
    series = approach[i0 : i0 + m]
    return {
        "hits": hs["hits"],
        "periodic_hits": hs["periodic_hits"],
        "peak_forces": hs["peak_forces"],
        "max_pulse": hs["max_peak_force"],
        "pulse_over_f_hd": hs["max_peak_force"] / f_hd if events else None,
        "approach_speeds": approach,
        "speed_gain": gain,
        "sustained": series[-1] / series[0] if len(series) >= 2 and series[0] > 0 else None,
    }


def summarize(per_run: list[dict], keys: tuple[str, ...]) -> dict:
    """Mean +- std over runs of each of ``keys`` (runs where it is None are left out and counted
    in ``n``), and the fraction of runs where a boolean key holds.
    """
    out = {}
    for key in keys:
        vals = [r[key] for r in per_run if r.get(key) is not None]
        if vals and isinstance(vals[0], bool):
            out[key] = {"fraction": float(np.mean(vals)), "n": len(vals)}
        elif vals:
            out[key] = dict(mean_std(vals), n=len(vals))
        else:
            out[key] = {"mean": None, "std": None, "n": 0}
    out["runs"] = len(per_run)
    return out


CATCHING_KEYS = (
    "t_c_s",
    "relative_speed_at_contact",
    "peak_force",
    "overshoot_over_f_cd",
    "time_to_f_cd_s",
    "settle_force",
    "held",
    "contact",
)
HITTING_KEYS = (
    "hits",
    "periodic_hits",
    "sustained",
    "max_pulse",
    "pulse_over_f_hd",
    "speed_gain_mean",
)


def runs_of(logs: dict) -> list[dict]:
    """Split logs with leading axes (seeds, runs, steps, ...) into one dict per run."""
    s, r = logs["f_contact"].shape[:2]
    return [{k: v[i, j] for k, v in logs.items()} for i in range(s) for j in range(r)]


def task_run_metrics(task: str, log: dict, dt: float, f_d: float, threshold: float, settle_s):
    """:func:`catching_run_metrics` or :func:`hitting_run_metrics` (with ``speed_gain_mean``, the
    mean speed gained per hit) by ``task``.

    Raises:
        ValueError: ``task`` is neither "catching" nor "hitting".
    """
    if task not in ("catching", "hitting"):
        raise ValueError(f"task must be 'catching' or 'hitting', got {task!r}")
    if task == "catching":
        return catching_run_metrics(log, dt, f_d, threshold, settle_s)
    m = hitting_run_metrics(log, dt, f_d, threshold)
    m["speed_gain_mean"] = float(np.mean(m["speed_gain"])) if m["speed_gain"] else None
    return m
