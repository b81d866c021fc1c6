"""Non-contact impedance control of Sec. 4 (Eqs. 39-49) as pure JAX functions.

Imports only jax, numpy and ``hec_jax.mjx_scene``.
"""

from hec_jax.control.closed_loop import make_c_policy, make_mjx_policy
from hec_jax.control.impedance import (
    ControlInfo,
    ControllerConfig,
    ControllerState,
    ImpedanceParams,
    Target,
    fixed_target,
    impedance_params,
    impedance_torque,
    make_impedance_controller,
    operational_inertia,
    solve_spd,
)
from hec_jax.control.kinematics import (
    TaskObs,
    hand_position,
    object_state,
    observe,
    observe_c,
    task_jacobians,
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
    "fixed_target",
    "hand_position",
    "impedance_params",
    "impedance_torque",
    "is_stable",
    "make_c_policy",
    "make_impedance_controller",
    "make_mjx_policy",
    "object_state",
    "observe",
    "observe_c",
    "operational_inertia",
    "solve_spd",
    "project_stable",
    "sphere_kinematics",
    "task_jacobians",
    "virtual_force",
    "virtual_params",
]
