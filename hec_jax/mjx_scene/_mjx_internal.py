"""The one module that touches MJX internals (``mujoco.mjx._src`` and ``Data._impl``).

MJX 3.17 keeps contacts, the constraint Jacobian, the solver's context and a few support
functions out of its public API. Everything the project needs of them goes through the small
functions here, so that an MJX upgrade is checked in one place (the tests against MuJoCo C cover
each of them).
"""

from __future__ import annotations

import jax
from mujoco import mjx
from mujoco.mjx._src import solver as _solver
from mujoco.mjx._src import support as _support
from mujoco.mjx._src.types import SolverType

__all__ = [
    "SolverType",
    "contact_force_world",
    "contact_geoms",
    "contact_count",
    "has_constraints",
    "inertia_storage",
    "jac_dot",
    "solver_context",
    "with_constraint_solution",
]


def contact_count(d: mjx.Data) -> int:
    """Number of contact slots MJX allocates (static: one per possible contact of the pairs)."""
    return int(d._impl.contact.dist.shape[0])


def contact_geoms(d: mjx.Data) -> jax.Array:
    """(ncon, 2) geom ids of each contact slot (geom1, geom2)."""
    return d._impl.contact.geom


def contact_force_world(m: mjx.Model, d: mjx.Data, i: int) -> jax.Array:
    """(6,) force/torque of contact slot ``i`` in the world frame: geom1 on geom2 (0 if inactive)."""
    return _support.contact_force(m, d, i, to_world_frame=True)


def has_constraints(d: mjx.Data) -> bool:
    """Whether the model has any constraint rows (static)."""
    return d._impl.efc_J.size != 0


def jac_dot(m: mjx.Model, d: mjx.Data, point: jax.Array, body_id: int):
    """Time derivative of the (translational, rotational) Jacobians at ``point`` on ``body_id``."""
    return _support.jac_dot(m, d, point, body_id)


def solver_context(m: mjx.Model, d: mjx.Data, grad: bool):
    """MJX's constraint-solver context at ``d.qacc`` (cost gradient, Newton step ``Mgrad``)."""
    return _solver.Context.create(m, d, grad=grad)


def with_constraint_solution(d: mjx.Data, qacc, qfrc_constraint, efc_force) -> mjx.Data:
    """``d`` with a constraint solution written where ``mjx.solve`` writes it."""
    return d.tree_replace(
        {"qfrc_constraint": qfrc_constraint, "qacc": qacc, "_impl.efc_force": efc_force}
    )


def inertia_storage(d: mjx.Data) -> jax.Array:
    """MJX's stored joint-space inertia (sparse ``(nC,)`` or dense ``(nv, nv)`` by ``opt.jacobian``)."""
    return d._impl.M
