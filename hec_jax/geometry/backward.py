"""Offline tracking backward in time from each re-acquisition, guarded by the whole-track
fixed-axis model (issue 24; docs/eye_randomized.md, "Tracking backward from each
re-acquisition").

A causal tracker that loses the box and finds it again leaves the frames between the loss and the
re-acquisition invalid, although the box is often visible in them: the search from scratch is
slower to find it than a tracker that knows where it is. Offline, the track after the
re-acquisition knows where it was: a tracker started at the re-acquired frame with the
time-reversed state (velocity negated) tracks the frames before it, in reverse order, until its
first failed frame. Such an extension carries whatever the segment is, a wrong lock included
(development seeds 46 and 112 of the randomized benchmark, session 70), so it is guarded by the
pendulum model the smoother fits over the whole track (``SmootherConfig.hinge_whole_track``):

1. a segment is extended only if the first smoothing accepted the whole-track model and the
   segment took the model's state (``SmoothedTrack.hinge_modelled`` at its first frame);
2. the track is smoothed again with the frames found; a found frame is kept only if that
   smoothing accepted the model again and counts the frame as an inlier
   (``hinge_modelled``, and neither ``hinge_outlier`` nor ``jump_rejected``); if any is
   dropped, the track is smoothed once more without them.

The frames a causal tracker found are never changed or dropped: the pass adds frames, and only in
the gaps before a valid segment. It is offline: a found frame is no online acquisition.

NumPy at the boundary; the tracker is any callable (:func:`guarded_backward_fill`), so the pass
is tested on synthetic fits without images. :func:`hec_jax.geometry.track.track_box` runs it
with a :class:`~hec_jax.geometry.track.BoxTracker` where ``SmootherConfig.extend_backward``.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import NamedTuple

import numpy as np

from hec_jax.geometry.smooth import SmoothedTrack, SmootherConfig, smooth_track


class Fits(NamedTuple):
    """Per-frame fits, as :func:`smooth_track` takes them (NumPy).

    Attributes:
        valid: (T,) bool, the frame's fit passed the tracker's checks.
        pose_rotation: (T, 3, 3) R_cam_box of the fit (any rotation where not valid).
        position: (T, 3) the fit's centre [m] (any value, NaN included, where not valid).
        information: (T, 6, 6) information of the fit over (dw, dt) [1/rad^2, 1/m^2].
        restarted: (T,) bool, the frames where a new filter started (``TrackStep.restarted``).
    """

    valid: np.ndarray
    pose_rotation: np.ndarray
    position: np.ndarray
    information: np.ndarray
    restarted: np.ndarray


class BackwardFit(NamedTuple):
    """One frame's fit from a tracker run backward in time (the fields of :class:`Fits`)."""

    valid: bool
    pose_rotation: np.ndarray
    position: np.ndarray
    information: np.ndarray


# track_backward(start, end, state) -> the fits of frames start - 1, start - 2, ... in that
# order; ``start`` is a segment's first valid frame, ``end`` its last, ``state`` the first
# smoothing's (position [m], velocity [m/s], acceleration [m/s^2]) at ``start`` in forward time.
# The pass stops reading at the first invalid fit, at frame 0 or at a frame already valid.
TrackBackward = Callable[[int, int, tuple], Iterable[BackwardFit]]


class BackwardFill(NamedTuple):
    """Result of :func:`guarded_backward_fill`.

    Attributes:
        fits: the merged fits (the forward ones, plus the kept backward ones where ``filled``).
        filled: (T,) bool, frames invalid forward that a kept backward fit made valid.
        smoothed: the smoothing of ``fits`` (:func:`smooth_track`, the same settings): the
            first smoothing where nothing was kept.
        first: the first smoothing (of the forward fits alone).
        tried: backward tracker updates run (the pass's cost, in tracked frames).
        dropped: backward fits found but dropped by the guard's second part.
    """

    fits: Fits
    filled: np.ndarray
    smoothed: SmoothedTrack
    first: SmoothedTrack
    tried: int
    dropped: int


def _starts(valid: np.ndarray) -> list[tuple[int, int]]:
    """(first, last) frame of every run of valid frames that has an invalid frame before it."""
    out = []
    t_n = len(valid)
    for s in range(1, t_n):
        if valid[s] and not valid[s - 1]:
            e = s
            while e + 1 < t_n and valid[e + 1]:
                e += 1
            out.append((s, e))
    return out


def _restarts(forward: np.ndarray, filled: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Restart flags for merged fits: the forward ones, moved from the first frame of each
    segment an extension reaches to the extension's first frame.
    """
    out = forward.copy()
    for t in range(len(out)):
        if filled[t] and (t == 0 or not filled[t - 1]):
            out[t] = True
        if t > 0 and valid[t] and not filled[t] and filled[t - 1]:
            out[t] = False
    return out


def guarded_backward_fill(
    fits: Fits,
    dt: float,
    cfg: SmootherConfig,
    track_backward: TrackBackward,
    first: SmoothedTrack | None = None,
    gravity_cam=None,
) -> BackwardFill:
    """The guarded backward extension (module docstring), NumPy in and out.

    Args:
        fits: the forward (causal) per-frame fits.
        dt: frame interval [s].
        cfg: the smoother's settings (every smoothing of the pass uses them; the model guard
            needs ``cfg.hinge_whole_track``, without which nothing is extended).
        track_backward: runs a tracker backward from a segment's first frame (:data:`TrackBackward`).
        first: the smoothing of ``fits`` with ``cfg`` if already computed (else computed here).
        gravity_cam: gravity in the camera frame for every smoothing (:func:`smooth_track`).

    Returns:
        :class:`BackwardFill`. Where no frame is kept, ``fits`` and ``first`` come back as they
        were (bit for bit).

    Raises:
        ValueError: fits of mismatched lengths.
    """
    valid = np.asarray(fits.valid, bool)
    t_n = len(valid)
    shapes = {
        "pose_rotation": (t_n, 3, 3),
        "position": (t_n, 3),
        "information": (t_n, 6, 6),
        "restarted": (t_n,),
    }
    for name, shape in shapes.items():
        if np.shape(getattr(fits, name)) != shape:
            raise ValueError(f"fits.{name} has shape {np.shape(getattr(fits, name))}, not {shape}")

    given = fits
    fits = fits._replace(valid=valid, restarted=np.asarray(fits.restarted, bool))

    def smooth(f: Fits) -> SmoothedTrack:
        rot = np.array(f.pose_rotation, np.float64)
        if f.valid.any():  # before the first valid frame, its rotation (track_box's convention)
            first_valid = int(np.argmax(f.valid))
            rot[:first_valid] = rot[first_valid]
        return smooth_track(
            rot, f.position, f.information, f.valid, dt, cfg, f.restarted, gravity_cam
        )

    if first is None:
        first = smooth(fits)
    modelled = first.hinge_modelled if first.hinge_modelled is not None else np.zeros(t_n, bool)
    rot = np.array(fits.pose_rotation, np.float64)
    pos = np.array(fits.position, np.float64)
    info = np.array(fits.information, np.float64)
    filled = np.zeros(t_n, bool)
    tried = 0
    for start, end in _starts(valid):
        if not modelled[start]:
            continue  # guard 1: only segments the accepted whole-track model explains
        state = (first.position[start], first.velocity[start], first.acceleration[start])
        t = start - 1
        for fit in track_backward(start, end, state):
            tried += 1
            if not fit.valid:
                break
            rot[t], pos[t], info[t] = fit.pose_rotation, fit.position, fit.information
            filled[t] = True
            t -= 1
            if t < 0 or valid[t]:
                break
    if not filled.any():
        return BackwardFill(given, filled, first, first, tried, 0)

    def merged(keep: np.ndarray) -> Fits:
        return Fits(
            valid | keep,
            np.where(keep[:, None, None], rot, fits.pose_rotation),
            np.where(keep[:, None], pos, fits.position),
            np.where(keep[:, None, None], info, fits.information),
            _restarts(np.asarray(fits.restarted, bool), keep, valid | keep),
        )

    out = merged(filled)
    second = smooth(out)
    inlier = np.zeros(t_n, bool)
    if second.hinge_modelled is not None:
        # the model's inliers among the fits the smoother used (the jump test's rejected fits
        # left out of it: SmootherConfig.max_speed_m_s)
        inlier = second.hinge_modelled & ~second.hinge_outlier & ~second.jump_rejected
    # guard 2: the model, fitted again, agrees with each kept frame (judged frame by frame: a
    # frame kept beyond a dropped one in the same extension is an inlier of the model too)
    keep = filled & inlier
    dropped = int(np.sum(filled & ~keep))
    if dropped == 0:
        return BackwardFill(out, filled, second, first, tried, 0)
    if not keep.any():
        return BackwardFill(given, keep, first, first, tried, dropped)
    out = merged(keep)
    return BackwardFill(out, keep, smooth(out), first, tried, dropped)
