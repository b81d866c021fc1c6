"""The object's state as the policy uses it: the eye's estimates and the hand's sense of touch.

Pure functions on pytrees, evaluated every control step inside the jitted rollout. The eye
(camera frames at 30 fps through ``hec_jax.geometry.BoxTracker``, at the NumPy boundary in
:mod:`hec_jax.loop.camera_loop`) reports an estimate per frame; between frames the state is
predicted with the filter's constant-acceleration model (:func:`eye_object_state`). The force
sensor takes over from the eye in contact and just after it (:class:`TouchMemory`,
:func:`touch_object_state`). With ``EyeInput.use == 0`` the simulator's ground truth is used.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from hec_jax.loop.config import TOUCH_MEMORY_ACROSS
from hec_jax.mjx_scene import CUBE_EDGE, HAND_RADIUS

# [m] hand centre to object centre while they touch: the hand sphere's radius plus half the cube's
# edge (a face on the hand; a corner would be 0.037 m further out)
TOUCH_DISTANCE = HAND_RADIUS + CUBE_EDGE / 2


class EyeInput(NamedTuple):
    """The object's state as the eye reports it (task plane (x, z), world frame), for camera runs.

    Two estimates: ``old`` (index 0) is used until ``t_switch``, ``new`` (index 1) from then on (the
    camera's latency decides when a frame's estimate arrives). Between frames the state is
    predicted from the estimate with the filter's constant-acceleration model:
    X_o(t) = x + xd tau + xdd tau^2 / 2, tau = t - t_stamp.

    Attributes:
        use: () 1.0: take X_o, X_o', X_o'' from here; 0.0: from the simulator (ground truth).
        seen: () 1.0 once the eye has an estimate; before that F_o = 0 and no learning.
        t_stamp: [s] (2,) time of each estimate's state (mid-exposure of its frame).
        t_switch: [s] () from this time on the new estimate is used.
        x: [m] (2, 2), xd: [m/s] (2, 2), xdd: [m/s^2] (2, 2): (estimate, axis).
        touch_guard: [s] () an estimate whose frame was exposed less than this after the hand last
            felt the object is not used (see :class:`TouchMemory`); 0: no guard.
        touch_memory: [s] () how long after the last touch its extrapolation may stand in for
            the eye (an old or lost estimate); later the object counts as unseen.
    """

    use: jax.Array
    seen: jax.Array
    t_stamp: jax.Array
    t_switch: jax.Array
    x: jax.Array
    xd: jax.Array
    xdd: jax.Array
    touch_guard: jax.Array = 0.0
    touch_memory: jax.Array = 0.0


def truth_eye() -> EyeInput:
    """The object state comes from the simulator (``--eye truth``)."""
    z = jnp.zeros((2, 2))
    one, zero = jnp.asarray(1.0), jnp.asarray(0.0)
    return EyeInput(zero, one, jnp.zeros(2), jnp.asarray(jnp.inf), z, z, z, zero, zero)


class TouchMemory(NamedTuple):
    """What the hand's force sensor last said about the object (camera runs; part of the policy
    state, carried across steps and frames).

    While the sensor feels the object (|F_int| above the contact threshold) the object's centre is
    taken to be ``TOUCH_DISTANCE`` from the hand's centre against the measured force (F_int acts ON
    the hand, so the object lies along -F_int), moving with the hand along that normal (the eye
    gives the motion across it: :func:`touch_object_state`). After the contact ends, the
    object is extrapolated from that last touch until the eye delivers an estimate from a frame
    exposed at least ``EyeInput.touch_guard`` after it: a 30 fps eye with 33 ms latency still
    reports the pre-impact motion (into the hand) for several frames after an impact, and its
    filter needs a few post-impact frames for the new velocity. Along the last contact normal the
    extrapolation is at the hand's velocity at the last touch (a frictionless contact sets the
    object's velocity along the normal only); across it, as ``across`` in
    :func:`touch_object_state` says.

    Attributes:
        t: [s] () time of the last sample in contact (-inf: never).
        x: [m] (2,) object centre at that sample (world task plane).
        xd: [m/s] (2,) object velocity at that sample (the hand's).
        normal: (2,) unit contact normal at that sample, hand -> object.
        x_hand: [m] (2,) the hand's centre at that sample.
    """

    t: jax.Array
    x: jax.Array
    xd: jax.Array
    normal: jax.Array
    x_hand: jax.Array


def no_touch(dtype=None) -> TouchMemory:
    """The memory before any contact."""
    z = jnp.zeros(2, dtype)
    return TouchMemory(jnp.asarray(-jnp.inf, dtype), z, z, z, z)


def touch_object_state(
    eye: EyeInput,
    touch: TouchMemory,
    t,
    x_e,
    xd_e,
    xdd_e,
    f_int,
    in_contact,
    distance: float,
    across: str = "follow_hand",
):
    """(X_o, X_o', X_o'', known, memory) of a camera run at time ``t``: touch in contact, the last
    touch extrapolated while the eye's estimate predates it (+ guard) or is lost, the eye
    otherwise; out of contact the estimate is kept out of the hand. Pure.

    ``known`` (bool): the object is in contact, or within ``eye.touch_memory`` of the last touch
    while the eye has nothing newer, or the eye sees it (``eye.seen``); otherwise it counts as
    unseen (the caller then drops the virtual force and learning).

    * In contact: the force on the (spherical, frictionless) hand is along the contact normal n,
      so touch fixes the centre along n only: at ``distance`` from the hand's centre; across n
      (where on its face the cube is held) the position is the eye's prediction (measured, main
      catching run: taking the centre on the hand's normal line instead gave 44-50 mm errors
      while a cube was held off-centre, and the hand pushed it out). Velocity and acceleration
      are the hand's (the eye's across n made the hold chatter, measured: 8-18 contacts a swing).
      While the eye has nothing (``eye.seen`` 0, e.g. the paper's eye with the hand hiding a
      side of the face) the position across n is the last touch's, or on the hand's normal line
      before any touch (the eye's zeros would put the object metres away).
    * After a contact, while the eye's estimate predates the last touch (+ guard) or is lost:
      along the last touch's normal n the object moves on at the hand's velocity then. Across n,
      with ``across`` (static) "follow_hand" it keeps its offset from the hand as at the last
      touch (position, velocity and acceleration follow the hand's, as in contact: the contact
      says nothing more across n; along n the acceleration is zero), so the relative state
      across n that the virtual force of Eqs. 45-47 sees stays that of the last touch; with
      "hand_velocity" it moves on at the hand's velocity then, with zero acceleration, which can
      feed the hand's sideways motion back through the virtual force and lose a held cube
      (``docs/realtime.md``: the held cube's sideways runaway).
    * Out of contact the force sensor says the object does not touch the hand, so an estimate
      closer than ``distance`` contradicts it: the position is moved out to ``distance`` along the
      same direction (projected onto what the sensor allows). Near X_r = 0 the sphere geometry of
      Eqs. 45-47 is singular (its n' and n'' grow as 1 / |X_r|), so an estimate inside the hand
      would otherwise turn eye errors into arbitrarily large virtual forces. The velocity is
      kept: an estimate just ahead of a real impact is still approaching (removing the approach
      velocity there was tried: learned camera peaks 10-23% above ground truth on the short test
      run, against 4-9% below with the velocity kept).

    Args: ``x_e``, ``xd_e``, ``xdd_e`` [m, m/s, m/s^2] (2,) the hand; ``f_int`` [N] (2,) force on
    the hand; ``in_contact`` () bool; ``distance`` [m] hand centre to object centre in contact;
    ``across`` "follow_hand" or "hand_velocity" (``TaskConfig.touch_memory_across``).
    """
    if across not in TOUCH_MEMORY_ACROSS:
        raise ValueError(f"across must be one of {TOUCH_MEMORY_ACROSS}, got {across!r}")
    f_sq = jnp.sum(f_int**2)
    pos = f_sq > 0.0
    inv = jnp.where(pos, 1.0 / jnp.sqrt(jnp.where(pos, f_sq, 1.0)), 0.0)
    n = -f_int * inv  # unit contact normal, hand -> object (F_int acts ON the hand)
    x_eye, xd_eye, xdd_eye = eye_object_state(eye, t)
    # touch along n, the eye's position across it (where on the face the hand holds the cube);
    # with the eye blind (it carries zeros then), the last touch's across it, or the hand's
    # normal line if there was none
    touched = jnp.isfinite(touch.t)
    x_across = jnp.where(touched, touch.x, x_e + distance * n)
    x_across = jnp.where(eye.seen > 0, x_eye, x_across)
    x_touch = x_across + n * jnp.dot(n, x_e + distance * n - x_across)
    touch = jax.tree_util.tree_map(
        lambda new, old: jnp.where(in_contact, new, old),
        TouchMemory(jnp.asarray(t, touch.t.dtype), x_touch, xd_e, n, x_e),
        touch,
    )
    i = (t >= eye.t_switch).astype(jnp.int32)
    stale = eye.t_stamp[i] < touch.t + eye.touch_guard  # the frame predates the last touch
    since = t - jnp.where(jnp.isfinite(touch.t), touch.t, t)
    stale = stale | ((eye.seen <= 0) & jnp.isfinite(touch.t))  # the eye lost it: touch if recent
    known = in_contact | jnp.where(stale, since <= eye.touch_memory, eye.seen > 0)
    if across == "follow_hand":  # along n the last touch's velocity, across n the hand's offset
        n_last = touch.normal
        xd_along = n_last * jnp.dot(n_last, touch.xd)
        moved = x_e - touch.x_hand  # the hand since the last touch
        x_mem = touch.x + xd_along * since + moved - n_last * jnp.dot(n_last, moved)
        xd_mem = xd_along + xd_e - n_last * jnp.dot(n_last, xd_e)
        xdd_mem = xdd_e - n_last * jnp.dot(n_last, xdd_e)
    else:
        x_mem, xd_mem, xdd_mem = touch.x + touch.xd * since, touch.xd, jnp.zeros(2)
    x_free = jnp.where(stale, x_mem, x_eye)
    xd_free = jnp.where(stale, xd_mem, xd_eye)
    xdd_free = jnp.where(stale, xdd_mem, xdd_eye)
    # out of contact: not inside the hand (the position projected onto what the sensor allows)
    r = x_free - x_e
    rho_sq = jnp.sum(r**2)
    inside = (rho_sq < distance**2) & (rho_sq > 0.0)
    rho = jnp.sqrt(jnp.where(inside, rho_sq, 1.0))
    u = jnp.where(inside, r / rho, jnp.zeros(2))  # unit, hand -> estimate (0: nothing to do)
    x_free = jnp.where(inside, x_e + distance * u, x_free)
    x = jnp.where(in_contact, x_touch, x_free)
    xd = jnp.where(in_contact, xd_e, xd_free)
    xdd = jnp.where(in_contact, xdd_e, xdd_free)
    return x, xd, xdd, known, touch


def eye_object_state(eye: EyeInput, t: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """(X_o, X_o', X_o'') at time ``t`` predicted from the estimate in force at ``t``."""
    i = (t >= eye.t_switch).astype(jnp.int32)
    tau = t - eye.t_stamp[i]
    x, xd, xdd = eye.x[i], eye.xd[i], eye.xdd[i]
    return x + xd * tau + 0.5 * xdd * tau**2, xd + xdd * tau, xdd
