"""Exact reverse-mode gradients through closed-loop MJX rollouts with contact
(``hec_jax.mjx_scene.differentiable``): float64 against central differences, float32 finite.

The loop is ``contact_probe``'s (PD-held hand struck by the pendulum; no learner, so that the
compiles stay short); the gradient is with respect to its 3 gains over a rollout whose last ~45
samples are in contact. The jitted functions are built once per module.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hec_jax.mjx_scene import PendulumConditions, default_conditions, differentiable, rollout
from hec_jax.mjx_scene.contact_probe import make_probe

STEPS = 620  # the default swing reaches the hand at step ~576
NO_REMAT = functools.partial(differentiable.rollout, checkpoint=False)


@pytest.fixture(scope="module")
def f64():
    probe = make_probe()
    c = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float64), default_conditions())
    forward = jax.jit(lambda g: probe.loss(g, c, STEPS, rollout))  # MJX's own solve
    value_and_grad = jax.jit(
        jax.value_and_grad(lambda g: probe.loss(g, c, STEPS, NO_REMAT), has_aux=True)
    )
    g0 = jnp.array([0.1, -0.2, 0.3])
    return forward, value_and_grad, g0


def test_value_is_mjx_solution(f64):
    forward, value_and_grad, g0 = f64
    (v, f_contact), _ = value_and_grad(g0)
    v_ref, f_ref = forward(g0)
    assert int(np.sum(np.linalg.norm(np.asarray(f_ref), axis=1) > 1e-6)) > 20  # in contact
    np.testing.assert_allclose(np.asarray(f_contact), np.asarray(f_ref), rtol=1e-7, atol=1e-7)
    assert abs(float(v) - float(v_ref)) <= 1e-9 * abs(float(v_ref))


def test_gradient_matches_central_differences_float64(f64):
    forward, value_and_grad, g0 = f64
    _, grad = value_and_grad(g0)
    grad = np.asarray(grad)
    assert np.all(np.isfinite(grad))
    h = 1e-6
    fd = np.array(
        [
            (float(forward(g0 + h * e)[0]) - float(forward(g0 - h * e)[0])) / (2 * h)
            for e in np.eye(3)
        ]
    )
    np.testing.assert_allclose(grad, fd, rtol=1e-3, atol=1e-6 * np.max(np.abs(fd)))


def _float32_grads(conds, batched):
    """Gradients (and contact forces) of the probe loss in float32 (x64 off while tracing)."""
    with jax.enable_x64(False):
        probe = make_probe()
        conds = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float32), conds)
        vg = jax.value_and_grad(lambda g, c: probe.loss(g, c, 660, NO_REMAT), has_aux=True)
        vg = jax.jit(jax.vmap(vg, in_axes=(None, 0)) if batched else vg)
        (_, f_contact), grad = vg(jnp.zeros(3, jnp.float32), conds)
        grad = np.asarray(grad)
        assert grad.dtype == np.float32
    return grad, np.asarray(f_contact)


@pytest.mark.slow  # a second compile of the whole differentiable rollout (float32)
def test_gradient_finite_float32():
    grad, f_contact = _float32_grads(default_conditions(), batched=False)
    assert np.all(np.isfinite(grad))
    assert np.sum(np.linalg.norm(f_contact, axis=-1) > 1e-6) > 10  # through contact


@pytest.mark.slow
def test_gradient_finite_float32_batch():
    """float32: finite for every member of a vmapped batch of conditions, all in contact."""
    conds = PendulumConditions(  # four swings that all reach the hand within 0.66 s
        rod_length=np.array([0.58, 0.6, 0.62, 0.6]),
        cube_mass=np.array([0.5, 0.7, 0.9, 0.6]),
        release_angle=np.array([-0.5, -0.55, -0.52, -0.58]),
        release_speed=np.zeros(4),
        hinge_damping=np.full(4, 0.002),
        arrival_phase=np.zeros(4),
        hinge_x=np.full(4, 0.35),  # scene.xml's hinge
    )
    grad, f_contact = _float32_grads(conds, batched=True)
    assert np.all(np.isfinite(grad))
    contact_steps = np.sum(np.linalg.norm(f_contact, axis=2) > 1e-6, axis=1)
    assert np.all(contact_steps > 10), contact_steps


def test_jacobian_fd_error_sees_each_row():
    """The exact-Jacobian check against central differences scales each row by its own size:
    on an affine step whose Jacobian is the unit-mass one (position rows dt^2, velocity rows dt),
    a wrong position row shows as a relative error of order 1, not 1e-3."""
    from hec_jax.loop.gradients import jacobian_fd_error, unit_mass_jacobian

    true_jac = unit_mass_jacobian(1e-3)  # (4, 2)

    def one_step(f_o, qpos, qvel, f_prev, m):
        return jnp.asarray(true_jac) @ f_o

    log = {
        "f_contact": np.zeros((3, 3)),
        "qpos": np.zeros((3, 1)),
        "qvel": np.zeros((3, 1)),
        "f_o": np.ones((3, 2)),
    }
    assert jacobian_fd_error(one_step, true_jac, log, 1, None) < 1e-6
    doubled, zeroed = true_jac.copy(), true_jac.copy()
    doubled[:2] *= 2.0
    zeroed[:2] = 0.0
    assert jacobian_fd_error(one_step, doubled, log, 1, None) == pytest.approx(0.5, rel=1e-6)
    assert jacobian_fd_error(one_step, zeroed, log, 1, None) == np.inf
    velocity_off = true_jac.copy()
    velocity_off[2:] *= 1.01
    assert jacobian_fd_error(one_step, velocity_off, log, 1, None) == pytest.approx(
        0.01 / 1.01, rel=1e-4
    )


def test_horizons_longer_than_a_swing_are_refused_before_learning():
    from hec_jax.loop import sweep_catching
    from hec_jax.loop.gradients import HorizonProbe

    task = sweep_catching()  # 1.5 s swings: 1500 steps
    with pytest.raises(ValueError, match="horizons up to 1497 samples fit a swing of 1500"):
        HorizonProbe(task, (10, 5000))
