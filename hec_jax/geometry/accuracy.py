"""Error statistics of the eye against ground truth (NumPy boundary).

* :func:`motion_errors`: the paper's two-segment estimate (``estimate_motion``, Eqs. 7-38, on one
  pair of parallel cube edges, metric via |AB|) and the OpenCV baselines of :mod:`.baselines` on
  the same synthetic two-frame scenes.
* :func:`track_errors`: a tracked sequence (``track_box``) against the true state of the box.

Rotation error: the angle of R_est^T R_true [deg]. Translation error: |Gamma_est - Gamma_true|
(Gamma of Eq. 1, camera frame).
"""

from __future__ import annotations

import numpy as np

from hec_jax.geometry.baselines import BASELINES, run_baselines
from hec_jax.geometry.parallel_motion import estimate_motion
from hec_jax.geometry.synthetic import CubeMotionScenes, SceneConfig, rotation_error_deg

METHODS = ("paper", *BASELINES)


def error_summary(rotation_deg: np.ndarray, translation_m: np.ndarray, ok: np.ndarray) -> dict:
    """Median and 90th percentile of the errors over the problems where ``ok``, and the failure
    rate.

    Args:
        rotation_deg: (n,) rotation errors [deg].
        translation_m: (n,) translation errors [m], NaN where the method gives none.
        ok: (n,) bool, the method returned a solution.

    Returns:
        ``rotation_median_deg``, ``rotation_p90_deg``, ``translation_median_mm``,
        ``translation_p90_mm`` (None where there is nothing to summarise) and ``failure_rate``.
    """
    ok = np.asarray(ok, bool)
    r, t = np.asarray(rotation_deg)[ok], np.asarray(translation_m)[ok]
    has_t = bool(np.any(np.isfinite(t)))
    return {
        "rotation_median_deg": float(np.median(r)) if r.size else None,
        "rotation_p90_deg": float(np.percentile(r, 90)) if r.size else None,
        "translation_median_mm": float(np.median(t) * 1e3) if has_t else None,
        "translation_p90_mm": float(np.percentile(t, 90) * 1e3) if has_t else None,
        "failure_rate": float(1.0 - ok.mean()),
    }


def motion_errors(scenes: CubeMotionScenes, config: SceneConfig) -> dict[str, dict]:
    """:func:`error_summary` of every method in :data:`METHODS` on one batch of scenes.

    A failure is a method reporting no valid solution (``valid == False`` for the paper's method,
    no solution from OpenCV); errors are over the problems that did not fail.
    """
    n = len(scenes.pair)
    est = estimate_motion(scenes.points_before, scenes.points_after, config.edge)
    rot = {"paper": rotation_error_deg(np.asarray(est.rotation), scenes.rotation)}
    tr = {"paper": np.linalg.norm(np.asarray(est.translation) - scenes.translation, axis=-1)}
    ok = {"paper": np.asarray(est.valid)}
    for name in BASELINES:
        rot[name], tr[name], ok[name] = np.full(n, np.nan), np.full(n, np.nan), np.zeros(n, bool)
    for i in range(n):
        for name, res in run_baselines(scenes, config.intrinsics, config.edge, i).items():
            if res is None:
                continue
            ok[name][i] = True
            rot[name][i] = rotation_error_deg(res[0], scenes.rotation[i])
            if res[1] is not None:
                tr[name][i] = np.linalg.norm(res[1] - scenes.translation[i])
    return {name: error_summary(rot[name], tr[name], ok[name]) for name in METHODS}


def track_errors(track, truth) -> dict:
    """A tracked sequence against the true state, over the frames whose own fit was valid.

    Args:
        track: a :class:`hec_jax.geometry.BoxTrack` (smoothed and ``causal_*`` fields).
        truth: the true state in the same camera frame, with fields ``position``, ``velocity``,
            ``acceleration`` (T, 3) [m, m/s, m/s^2] and ``rotation`` (T, 3, 3) R_cam_box (e.g. a
            ``hec_jax.mjx_scene.RenderedSequence``); the true Phi is R_t R_0^T.

    Returns:
        ``frames``, ``valid_rate``, RMS errors of the smoothed, measured and causal centre
        (``*_rms_mm``), velocity (``*_rms_m_s``) and acceleration (``*_rms_m_s2``), the median and
        90th percentile of the smoothed rotation error and the causal median [deg], and
        ``latency_ms`` (the tracker's ``timing_ms``).
    """
    v = np.asarray(track.valid, bool)

    def rms(a, b):
        return float(np.sqrt(np.mean(np.sum((a - b) ** 2, -1)[v])))

    phi = truth.rotation @ truth.rotation[0].T
    rot = rotation_error_deg(track.rotation, phi)[v]
    return {
        "frames": int(len(v)),
        "valid_rate": float(v.mean()),
        "position_rms_mm": 1e3 * rms(track.position, truth.position),
        "measured_position_rms_mm": 1e3 * rms(track.measured_position, truth.position),
        "velocity_rms_m_s": rms(track.velocity, truth.velocity),
        "acceleration_rms_m_s2": rms(track.acceleration, truth.acceleration),
        "rotation_median_deg": float(np.median(rot)),
        "rotation_p90_deg": float(np.percentile(rot, 90)),
        "causal_position_rms_mm": 1e3 * rms(track.causal_position, truth.position),
        "causal_velocity_rms_m_s": rms(track.causal_velocity, truth.velocity),
        "causal_acceleration_rms_m_s2": rms(track.causal_acceleration, truth.acceleration),
        "causal_rotation_median_deg": float(
            np.median(rotation_error_deg(track.causal_rotation, phi)[v])
        ),
        "latency_ms": track.timing_ms,
    }
