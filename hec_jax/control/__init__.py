"""The hand: impedance control without Jacobian inverse and the virtual sphere (Eqs. 39-49).

Pure functions on arrays; imports jax and numpy only (no other part of ``hec_jax``, no MuJoCo).
The observation of the plant (``TaskObs``) is computed by the caller, e.g.
``hec_jax.loop.observation`` from MJX or MuJoCo C.
"""

from hec_jax.control.impedance import (
    ControlInfo,
    ControllerConfig,
    ControllerState,
    ImpedanceParams,
    Target,
    TaskObs,
    difference_over_elapsed,
    fixed_target,
    impedance_params,
    impedance_torque,
    make_impedance_controller,
    operational_inertia,
    solve_spd,
)
from hec_jax.control.virtual import (
    SphereKinematics,
    VirtualParams,
    is_stable,
    project_stable,
    sphere_kinematics,
    virtual_force,
    virtual_params,
)

__all__ = [
    "ControlInfo",
    "ControllerConfig",
    "ControllerState",
    "ImpedanceParams",
    "SphereKinematics",
    "Target",
    "TaskObs",
    "VirtualParams",
    "difference_over_elapsed",
    "fixed_target",
    "impedance_params",
    "impedance_torque",
    "is_stable",
    "make_impedance_controller",
    "operational_inertia",
    "project_stable",
    "solve_spd",
    "sphere_kinematics",
    "virtual_force",
    "virtual_params",
]
