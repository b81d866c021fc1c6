"""Virtual sphere of the non-contact impedance control (Eqs. 45-47) and the stability set (Eq. 49).

Readings (docs/paper_readings.md, Sec. 2):
* X_r = X_o - X_e, n = X_r / |X_r| points from the hand to the object (n = 0 at X_r = 0, Eq. 46);
* dX_o = X_r - r n (Eq. 45) = -(r - |X_r|) n inside the sphere; with K_o > 0, F_o = K_o dX_o pushes
  the hand away from the object;
* n varies with X_r in 2-D, so dX_o' = X_r' - r n' and dX_o'' = X_r'' - r n'' with
  n' = P X_r' / rho, P = I - n n^T, rho = |X_r| (derived in :func:`sphere_kinematics`);
* F_o (Eq. 47) acts for |X_r| <= r and is zero outside and at the centre (as the paper states);
  it jumps at the boundary through its B_o and M_o terms.
* Eq. 49 per axis with frozen parameters and constant n: the characteristic polynomial is
  (M_o + M_e) s^2 + (B_o + B_e) s + (K_o + K_e); the printed ">=" condition is not sufficient, the
  strict one (each sum > 0) is used.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np


class VirtualParams(NamedTuple):
    """Virtual impedance of Eq. 47, diagonal per task axis (pytree leaves).

    Attributes:
        m_o: [kg] (2,) virtual inertia M_o.
        b_o: [N s/m] (2,) virtual viscosity B_o.
        k_o: [N/m] (2,) virtual stiffness K_o.
        r: [m] () radius of the virtual sphere.
    """

    m_o: jax.Array
    b_o: jax.Array
    k_o: jax.Array
    r: jax.Array


def virtual_params(m_o, b_o, k_o, r) -> VirtualParams:
    """Validated VirtualParams (host side): diagonals of shape (2,) or scalars, r > 0."""
    out = []
    for name, v in (("m_o", m_o), ("b_o", b_o), ("k_o", k_o)):
        a = np.broadcast_to(np.asarray(v, dtype=float), (2,)).copy()
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name} must be finite, got {a}")
        out.append(jnp.asarray(a))
    r = float(r)
    if not (np.isfinite(r) and r > 0):
        raise ValueError(f"virtual sphere radius r must be > 0, got {r}")
    return VirtualParams(*out, r=jnp.asarray(r))


class SphereKinematics(NamedTuple):
    """Geometry of Eqs. 45-46 and its time derivatives (task coordinates).

    Attributes:
        x_r: [m] (2,) X_r = X_o - X_e.
        rho: [m] () |X_r|.
        n: (2,) unit vector from hand to object (0 at X_r = 0).
        dx_o, dxd_o, dxdd_o: [m], [m/s], [m/s^2] (2,) dX_o and its first two time derivatives.
        inside: () bool, 0 < |X_r| <= r.
    """

    x_r: jax.Array
    rho: jax.Array
    n: jax.Array
    dx_o: jax.Array
    dxd_o: jax.Array
    dxdd_o: jax.Array
    inside: jax.Array


def sphere_kinematics(x_r, xd_r, xdd_r, r) -> SphereKinematics:
    """Eqs. 45-46 with derivatives (pure, NaN-safe at X_r = 0).

    rho = |X_r|, n = X_r / rho, P = I - n n^T,
    n'  = P X_r' / rho,
    n'' = (P' X_r' + P X_r'') / rho - P X_r' rho' / rho^2,
    P' = -(n' n^T + n n'^T), rho' = n . X_r'.
    dX_o = X_r - r n, dX_o' = X_r' - r n', dX_o'' = X_r'' - r n''.
    """
    rho2 = jnp.dot(x_r, x_r)
    nonzero = rho2 > 0.0
    rho = jnp.sqrt(jnp.where(nonzero, rho2, 1.0))
    inv_rho = jnp.where(nonzero, 1.0 / rho, 0.0)
    rho = jnp.where(nonzero, rho, 0.0)
    n = x_r * inv_rho
    P = jnp.eye(2) - jnp.outer(n, n)
    n_d = P @ xd_r * inv_rho
    rho_d = jnp.dot(n, xd_r)
    P_d = -(jnp.outer(n_d, n) + jnp.outer(n, n_d))
    n_dd = (P_d @ xd_r + P @ xdd_r) * inv_rho - P @ xd_r * (rho_d * inv_rho**2)
    return SphereKinematics(
        x_r=x_r,
        rho=rho,
        n=n,
        dx_o=x_r - r * n,
        dxd_o=xd_r - r * n_d,
        dxdd_o=xdd_r - r * n_dd,
        inside=nonzero & (rho <= r),
    )


def virtual_force(vp: VirtualParams, sk: SphereKinematics) -> jax.Array:
    """F_o [N] (2,) of Eq. 47.

    M_o dX_o'' + B_o dX_o' + K_o dX_o inside the sphere, 0 outside and at the centre (n = 0).
    """
    f = vp.m_o * sk.dxdd_o + vp.b_o * sk.dxd_o + vp.k_o * sk.dx_o
    return jnp.where(sk.inside, f, jnp.zeros(2))


def is_stable(m_e, b_e, k_e, m_o, b_o, k_o) -> jax.Array:
    """Eq. 49, strict per-axis form: all of M_o + M_e, B_o + B_e, K_o + K_e > 0 (bool array)."""
    return (m_o + m_e > 0) & (b_o + b_e > 0) & (k_o + k_e > 0)


def project_stable(vp: VirtualParams, m_e, b_e, k_e, margin: float = 1e-3) -> VirtualParams:
    """Projects (M_o, B_o, K_o) onto the strict stable set of Eq. 49 (per axis, pure).

    Each virtual parameter is raised to at least -(1 - margin) times its target counterpart, i.e.
    M_o >= -(1 - margin) M_e etc., so M_o + M_e >= margin M_e > 0 (requires M_e, B_e, K_e > 0;
    with K_e = 0 the stiffness bound is K_o >= 0, which keeps only K_o + K_e >= 0).
    """
    s = 1.0 - margin
    return vp._replace(
        m_o=jnp.maximum(vp.m_o, -s * m_e),
        b_o=jnp.maximum(vp.b_o, -s * b_e),
        k_o=jnp.maximum(vp.k_o, -s * k_e),
    )
