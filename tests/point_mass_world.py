"""A 1-D test world for the learner: an ideal impedance-controlled hand (the closed loop of Eq. 48)
and an object on a linear spring (a small-angle pendulum) swinging into it, penalty contact.

Semi-implicit Euler at the learner's dt; everything in one ``lax.scan`` per episode and one over
episodes, with the learner's weights carried across episodes (each episode restarts the world).
"""

import jax
import jax.numpy as jnp

from hec_jax.nets import LearnerInputs, SphereGeometry, make_online_learner

M_E, B_E, K_E = 1.0, 40.0, 400.0  # target impedance [kg], [N s/m], [N/m]
K_C = 2e4  # contact stiffness [N/m]
CONTACT = 0.07  # contact distance: hand radius + half cube [m]
M_O, OMEGA, X_REST, AMP = 0.7, 4.0, 0.35, 0.45  # object [kg], [rad/s], rest [m], release offset [m]


def sphere_1d(x_r, xd_r, xdd_r, radius):
    """Eqs. 45-46 in 1-D: n = sign(X_r) is constant away from 0, so dX_o' = X_r', dX_o'' = X_r''."""
    return SphereGeometry(x_r - radius * jnp.sign(x_r), xd_r, xdd_r)


DT = 1e-3  # [s] sampling interval of the world and the learner


def make_episodes(config, steps, learn=True, use_fo=True):
    """(key, n_episodes) -> per-sample logs (episodes, steps) of the hand-object world."""
    init, update = make_online_learner(config, DT, (M_E,), (B_E,), (K_E,))
    dt = DT

    def step(carry, _):
        ls, xe, ve, ae, xo, vo, ao = carry
        pen = CONTACT - (xo - xe)
        in_contact = pen > 0
        f_contact = jnp.where(in_contact, K_C * pen, 0.0)
        f_int = -f_contact  # force on the hand (Eq. 39), pushing it away from the object
        x = [jnp.reshape(v, (1,)) for v in (xe, ve, ae, xo, vo, ao, f_int)]
        sphere = sphere_1d(x[3] - x[0], x[4] - x[1], x[5] - x[2], config.radius)
        inputs = LearnerInputs(*x, in_contact, sphere)
        ls_new, out = update(ls, inputs)
        if not learn:
            ls_new = ls_new._replace(params=ls.params)
        f_o = out.f_o[0] if use_fo else 0.0
        ae_new = (f_o + f_int - B_E * ve - K_E * xe) / M_E  # Eq. 48, X_d = 0
        ao_new = -(OMEGA**2) * (xo - X_REST) + f_contact / M_O
        ve_new = ve + dt * ae_new
        vo_new = vo + dt * ao_new
        carry = (ls_new, xe + dt * ve_new, ve_new, ae_new, xo + dt * vo_new, vo_new, ao_new)
        log = dict(
            x_e=xe,
            x_o=xo,
            f_int=f_int,
            energy=out.energy,
            inside=out.inside,
            impedance=out.impedance[0],
            margins=out.margins[0],
            learning=out.learning,
        )
        return carry, log

    def episode(ls, _):
        z = jnp.zeros((), jnp.float64)
        carry = (ls, z, z, z, z + X_REST + AMP, z, z)
        carry, log = jax.lax.scan(step, carry, None, length=steps)
        return carry[0]._replace(was_inside=jnp.asarray(False)), log

    def run(key, n_episodes):
        ls, logs = jax.lax.scan(episode, init(key, jnp.float64), None, length=n_episodes)
        return ls, logs

    return jax.jit(run, static_argnums=1)
