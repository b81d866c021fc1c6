"""Metrics of the closed loop's logs (NumPy boundary): contact events, settling, hit series,
stability margins, the eye's accuracy, and the per-task summaries of an experiment.

Every function takes logs as :func:`hec_jax.loop.episodes.make_episodes` returns them (converted
to NumPy) and never raises on what a run did: a swing without contact gives ``None`` values with
the reason in the metrics.
"""

from __future__ import annotations

import numpy as np

from hec_jax.geometry.paper_eye import STATUSES


def contact_events(f_norm: np.ndarray, threshold: float, min_gap: int) -> list[tuple[int, int]]:
    """(start, end) sample indices of contact episodes in a force-magnitude series; contacts closer
    than ``min_gap`` samples are merged into one event (one hit may chatter).
    """
    on = np.flatnonzero(f_norm > threshold)
    if on.size == 0:
        return []
    events, start, prev = [], on[0], on[0]
    for i in on[1:]:
        if i - prev > min_gap:
            events.append((int(start), int(prev) + 1))
            start = i
        prev = i
    events.append((int(start), int(prev) + 1))
    return events


def settle_metrics(f_norm: np.ndarray, f_desired: float, threshold: float, tail: int) -> dict:
    """How the contact force of one swing ends, (steps,) force magnitudes [N].

    ``settle_force``: mean |F_int| over the last ``tail`` samples; ``settle_rel_error``:
    |settle_force - f_desired| / f_desired; ``contacts``: contact episodes (gaps of 20 samples merged,
    as for ``contact_events``); ``held``: one episode that lasts to the end of the swing (the object
    never leaves the hand after the first contact: no second impact); ``overshoot_after_settle``:
    the largest |F_int| in the last ``tail`` samples over ``settle_force`` (1: flat).
    """
    events = contact_events(f_norm, threshold, min_gap=20)
    settle = float(np.mean(f_norm[-tail:]))
    return {
        "settle_force": settle,
        "settle_rel_error": abs(settle - f_desired) / f_desired,
        "contacts": len(events),
        "held": bool(len(events) == 1 and events[0][1] == f_norm.shape[-1]),
        "overshoot_after_settle": float(np.max(f_norm[-tail:]) / max(settle, 1e-12)),
    }


def hit_series(f_norm: np.ndarray, dt: float, threshold: float, tolerance: float = 0.2) -> dict:
    """Hits, their force pulses and the longest periodic series in one force series (steps,) [N].

    A hit is a contact episode (episodes less than 50 ms apart merged: one strike may chatter). The
    periodic series is the longest run of consecutive hits whose start-to-start intervals all lie
    within ``tolerance`` of the median interval of that run's hits (``periodic_hits`` counts hits,
    i.e. intervals + 1). Its force pulses are *bounded* when (i) no pulse exceeds the first pulse of
    the series (``pulse_growth`` = max pulse / first pulse <= 1: the strikes do not build up) and
    (ii) every pulse is a short impact (``max_pulse_duration_s`` under 50 ms), not a sustained push.
    """
    events = contact_events(f_norm, threshold, min_gap=int(round(0.05 / dt)))
    starts = np.array([e[0] for e in events], dtype=float) * dt
    peaks = np.array([float(f_norm[a:b].max()) for a, b in events])
    durations = np.array([(b - a) * dt for a, b in events])
    best = (0, min(len(events), 1))  # (first hit, number of hits) of the longest periodic run
    if len(events) >= 2:
        intervals = np.diff(starts)
        for i in range(len(intervals)):
            for j in range(len(intervals), i, -1):  # longest run starting at i first
                if j - i + 1 <= best[1]:
                    break
                seg = intervals[i:j]
                if np.all(np.abs(seg - np.median(seg)) <= tolerance * np.median(seg)):
                    best = (i, j - i + 1)
                    break
    i0, n = best
    series = slice(i0, i0 + n)
    sp, sd = peaks[series], durations[series]
    return {
        "hits": len(events),
        "periodic_hits": int(n),
        "hit_times_s": starts.tolist(),
        "peak_forces": peaks.tolist(),
        "pulse_durations_s": durations.tolist(),
        "max_peak_force": float(peaks.max()) if len(peaks) else 0.0,
        "series_first_hit": int(i0),
        "series_pulse_max": float(sp.max()) if n else 0.0,
        "series_pulse_last": float(sp[-1]) if n else 0.0,
        "pulse_growth": float(sp.max() / sp[0]) if n else 0.0,
        "max_pulse_duration_s": float(sd.max()) if n else 0.0,
        "pulses_bounded": bool(n > 0 and sp.max() <= sp[0] and sd.max() < 0.05),
        "median_interval_s": float(np.median(np.diff(starts[series]))) if n > 1 else None,
    }


def force_norm(logs: dict) -> np.ndarray:
    """|F_int| [N] of the contact solved at each step, (..., steps)."""
    return np.linalg.norm(logs["f_contact"][..., [0, 2]], axis=-1)


def mean_std(x) -> dict:
    """{"mean", "std"} of the values ``x`` (population std)."""
    x = np.asarray(x, dtype=float)
    return {"mean": float(np.mean(x)), "std": float(np.std(x))}


def stability_summary(logs: dict) -> dict:
    """Smallest strict Eq. 49 margins (K_o + K_e, B_o + B_e, M_o + M_e) over every sample."""
    m = logs["margins"].reshape(-1, logs["margins"].shape[-2], 3)
    return {
        "min_k_margin": float(m[..., 0].min()),
        "min_b_margin": float(m[..., 1].min()),
        "min_m_margin": float(m[..., 2].min()),
        "all_strictly_stable": bool(np.all(m > 0)),
    }


def eye_metrics(eye: dict, logs: dict, dt: float) -> dict:
    """Counts and accuracy of the eye in the loop, and the real-time factor, of one set of
    episodes (``eye`` and ``logs`` as returned by :func:`run_camera`, or their ``final`` parts).
    """
    init = eye["initialised"]
    lost = init[..., :-1] & ~init[..., 1:]  # a track held on one frame and gone on the next
    err = eye["x_est"] - eye["x_true"]
    on = logs["object_seen"]  # steps where the controller had an estimate
    used = (logs["x_o"] - logs["x_o_true"])[on]
    used_v = (logs["xd_o"] - logs["xd_o_true"])[on]
    seen = np.isfinite(eye["x_est"][..., 0])
    n_seeds = logs["x_o"].shape[0]
    sim_s = dt * np.prod(logs["x_o"].shape[1:-1])  # simulated time of one world [s]
    walls = np.atleast_1d(eye["wall_s"])
    wall = float(walls.sum())
    per_frame = eye["eye_ms"].ravel()
    out = {
        "frames": int(init.size),
        "frames_valid": int(eye["valid"].sum()),
        "frames_failed": int((~eye["valid"]).sum()),
        "frames_failed_while_tracking": int((~eye["valid"] & init).sum()),
        "tracks_lost": int(lost.sum()),
        "position_rms_at_frames_m": float(np.sqrt(np.mean(err[seen] ** 2))),
        # accuracy where the eye reported a valid fit (false detections show here)
        "position_rms_valid_frames_m": float(np.sqrt(np.mean(err[eye["valid"]] ** 2))),
        "controller_position_rms_m": float(np.sqrt(np.mean(used**2))),
        "controller_velocity_rms_m_s": float(np.sqrt(np.mean(used_v**2))),
        "eye_ms_median": float(np.median(per_frame)),
        "eye_ms_p95": float(np.percentile(per_frame, 95)),
        "render_ms_median": float(np.median(eye["render_ms"])),
        "sim_ms_per_segment_median": float(np.median(eye["sim_ms"])),
        "wall_s": wall,
        "real_time_factor": float(sim_s / wall),  # simulated time of one world / wall time
        "real_time_factor_all_worlds": float(n_seeds * sim_s / wall),
    }
    status = eye.get("status")
    if status is not None and np.any(status >= 0):  # the paper's eye: frames by reason
        out["frames_by_status"] = {n: int(np.sum(status == i)) for i, n in enumerate(STATUSES)}
    if len(walls) > 1:  # without the first episode (compilation)
        out["real_time_factor_warm"] = float(
            sim_s * (len(walls) - 1) / len(walls) / walls[1:].sum()
        )
    return out


def catching_swing_metrics(
    logs: dict, s: int, w: int, f_cd: float, settle_steps: int, dt: float, threshold: float
) -> dict:
    """Metrics of seed ``s``, swing ``w`` of a catching run (settling: :func:`settle_metrics`).

    ``peak_force`` [N], ``t_c`` [s] (first sample inside the sphere), and at the first contact:
    ``t_contact`` [s], ``relative_speed_at_contact`` and ``object_speed_at_contact`` [m/s] one
    sample before it, ``hand_follow_ratio`` (X_e' . X_o' / |X_o'|^2: 0 the hand waits, 1 it moves
    with the object); without contact these are None and ``no_contact`` is True. X_o' is the
    simulator's (``xd_o_true``), not the controller's estimate (``xd_o``: the eye's with a
    camera), so that runs with different eyes are compared on the same physical quantity; logs
    without ``xd_o_true`` use ``xd_o``.
    """
    f = force_norm(logs)[s, w]
    events = contact_events(f, threshold, min_gap=20)
    inside = logs["inside"][s, w]
    t_c = int(np.argmax(inside)) if inside.any() else -1
    out = {"peak_force": float(f.max()), "t_c": t_c * dt if t_c >= 0 else None}
    out["no_contact"] = not events
    if events:
        i = max(events[0][0] - 1, 0)
        xd_o = logs["xd_o_true" if "xd_o_true" in logs else "xd_o"][s, w, i]
        xd_e = logs["xd_e"][s, w, i]
        speed_o = float(np.linalg.norm(xd_o))
        out.update(
            t_contact=events[0][0] * dt,
            relative_speed_at_contact=float(np.linalg.norm(xd_o - xd_e)),
            object_speed_at_contact=speed_o,
            hand_follow_ratio=float(np.dot(xd_e, xd_o) / max(speed_o**2, 1e-12)),
        )
    else:
        out.update(
            t_contact=None,
            relative_speed_at_contact=None,
            object_speed_at_contact=None,
            hand_follow_ratio=None,
        )
    out.update(settle_metrics(f, f_cd, threshold, settle_steps))
    return out


def catching_condition_metrics(
    logs: dict, condition: str, f_cd: float, settle_steps: int, dt: float, threshold: float
) -> dict:
    """Mean +- std over seeds of :func:`catching_swing_metrics` (learned: last swing; plain and
    frozen: swing 1, all swings alike), with the per-seed values; a metric some seed lacks (no
    contact) is averaged over the seeds that have it, and ``seeds_without_contact`` counts them.
    """
    n_seeds, n_swings = logs["inside"].shape[:2]
    w = n_swings - 1 if condition == "learned" else 0
    args = (f_cd, settle_steps, dt, threshold)
    per_seed = [catching_swing_metrics(logs, s, w, *args) for s in range(n_seeds)]
    m = {}
    for key in per_seed[0]:
        values = [p[key] for p in per_seed if p[key] is not None]
        if values and not isinstance(values[0], bool):
            m[key] = mean_std(values)
    m["seeds_without_contact"] = int(sum(p["no_contact"] for p in per_seed))
    m["held_every_seed"] = bool(all(p["held"] for p in per_seed))
    m["max_settle_rel_error_over_seeds"] = max(p["settle_rel_error"] for p in per_seed)
    m["swing_used"] = w
    m["per_seed"] = per_seed
    m["stability"] = stability_summary(logs)
    if condition == "learned":
        peaks = force_norm(logs).max(-1)  # (seeds, swings)
        m["peak_force_per_swing"] = [mean_std(peaks[:, k]) for k in range(n_swings)]
    return m


def hitting_condition_metrics(logs: dict, dt: float, threshold: float) -> dict:
    """Hits of the continuous run (``logs["final"]``) per seed (:func:`hit_series`) and their
    mean +- std; the training swings' peak force per swing.
    """
    f = force_norm(logs["final"])[:, 0]
    per_seed = [hit_series(f[s], dt, threshold) for s in range(f.shape[0])]
    return {
        "hits": mean_std([p["hits"] for p in per_seed]),
        "periodic_hits": mean_std([p["periodic_hits"] for p in per_seed]),
        "min_periodic_hits_over_seeds": int(min(p["periodic_hits"] for p in per_seed)),
        "peak_force": mean_std([p["max_peak_force"] for p in per_seed]),
        "series_pulse_max": mean_std([p["series_pulse_max"] for p in per_seed]),
        "series_pulse_last": mean_std([p["series_pulse_last"] for p in per_seed]),
        "pulse_growth": mean_std([p["pulse_growth"] for p in per_seed]),
        "max_pulse_duration_s": mean_std([p["max_pulse_duration_s"] for p in per_seed]),
        "pulses_bounded_every_seed": bool(all(p["pulses_bounded"] for p in per_seed)),
        "per_seed": per_seed,
        "stability": stability_summary(logs["final"]),
        "training_peak_force_per_swing": force_norm(logs).max(-1).mean(0).tolist(),
    }
