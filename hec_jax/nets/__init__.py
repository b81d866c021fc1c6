"""Learning: the VSN/VVN/VIN networks (Eqs. 50-51) and the online learner (Eqs. 52-66)."""

from hec_jax.nets.impedance_nets import (
    KINDS,
    NetConfig,
    apply,
    init_params,
    normalise_inputs,
    output_unit,
    output_unit_derivative,
    stability_margins,
    u_max,
)
from hec_jax.nets.learner import (
    LearnerConfig,
    LearnerInputs,
    LearnerOutput,
    LearnerState,
    SphereGeometry,
    gain_alpha,
    gain_beta,
    make_online_learner,
    task_energy,
)

__all__ = [
    "KINDS",
    "LearnerConfig",
    "LearnerInputs",
    "LearnerOutput",
    "LearnerState",
    "NetConfig",
    "SphereGeometry",
    "apply",
    "gain_alpha",
    "gain_beta",
    "init_params",
    "make_online_learner",
    "normalise_inputs",
    "output_unit",
    "output_unit_derivative",
    "stability_margins",
    "task_energy",
    "u_max",
]
