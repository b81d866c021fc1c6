"""The closed task loop: world (``mjx_scene``) + hand (``control``) + learner (``nets``) + eye
(``geometry``), as library code that experiments, benchmarks and tests import.

    from hec_jax import loop
    exp = loop.replace(loop.catching(eye="truth", seeds=3), swings=3, mu=2e-3)
    result = loop.run_experiment(exp)
    result.metrics["learned"]["peak_force"], result.logs["learned"]["x_e"].shape

Modules: ``config`` (configs and named presets), ``observation`` (simulator -> task observation),
``object_state`` (eye + touch), ``policy`` (one control step; :func:`build_loop`), ``episodes``
(swings in ``lax.scan``, seeds and conditions ``vmap``-ed), ``camera_loop`` (render -> mask ->
tracker or the paper's eye -> jitted segment, at the NumPy boundary), ``metrics``, ``experiment``
(:func:`run_experiment`), ``report`` (run folders), ``sweep``, ``devices`` (several GPUs),
``cli`` (the task scripts' command line), ``plain`` (plain impedance rollouts, MJX and C),
``exact`` (exact one-step gradients and the learner that uses them), ``gradients`` and
``gradients_report`` (the paper's dE/dF against exact sensitivities), ``bptt`` (offline training
through the rollout).
"""

from hec_jax.loop.camera_loop import run_camera, run_conditions_camera
from hec_jax.loop.config import (
    PRESETS,
    CameraConfig,
    CameraDefects,
    ExperimentConfig,
    TargetImpedance,
    TaskConfig,
    catching,
    catching_paper,
    hitting,
    hitting_paper,
    replace,
    sweep_catching,
)
from hec_jax.loop.devices import OnDevices, Sharded
from hec_jax.loop.episodes import make_episodes, make_seed_run, make_sweep, run_conditions
from hec_jax.loop.exact import build_exact_loop
from hec_jax.loop.experiment import ExperimentResult, run_experiment, task_metrics
from hec_jax.loop.object_state import (
    TOUCH_DISTANCE,
    EyeInput,
    TouchMemory,
    eye_object_state,
    no_touch,
    touch_object_state,
    truth_eye,
)
from hec_jax.loop.observation import observe, observe_c
from hec_jax.loop.plain import make_plain_run, plain_scene
from hec_jax.loop.policy import (
    CONDITIONS,
    Loop,
    PolicyState,
    Switches,
    build_loop,
    hold_point,
    make_c_policy,
    make_mjx_policy,
    switches,
)
from hec_jax.loop.report import print_summary, write_experiment
from hec_jax.loop.sweep import SweepConfig, SweepGrid, merge, run_sweep

__all__ = [
    "CONDITIONS",
    "PRESETS",
    "TOUCH_DISTANCE",
    "CameraConfig",
    "CameraDefects",
    "ExperimentConfig",
    "ExperimentResult",
    "EyeInput",
    "Loop",
    "OnDevices",
    "PolicyState",
    "Sharded",
    "SweepConfig",
    "SweepGrid",
    "Switches",
    "TargetImpedance",
    "TaskConfig",
    "TouchMemory",
    "build_exact_loop",
    "build_loop",
    "catching",
    "catching_paper",
    "eye_object_state",
    "hitting",
    "hitting_paper",
    "hold_point",
    "make_c_policy",
    "make_episodes",
    "make_mjx_policy",
    "make_plain_run",
    "make_seed_run",
    "make_sweep",
    "merge",
    "no_touch",
    "observe",
    "observe_c",
    "plain_scene",
    "print_summary",
    "replace",
    "run_camera",
    "run_conditions",
    "run_conditions_camera",
    "run_experiment",
    "run_sweep",
    "sweep_catching",
    "switches",
    "task_metrics",
    "touch_object_state",
    "truth_eye",
    "write_experiment",
]
