"""The hand-eye loop in real time, with a seam for a robot driver.

* :mod:`.plant`: the :class:`Plant` and :class:`Camera` interfaces a robot driver implements,
  the controller's :class:`ArmModel` (Eqs. 39-44's M, h, J, J' theta' by MuJoCo C from the joint
  state), and :class:`MujocoPlant`, MuJoCo C physics stepping on the wall clock at 1 kHz with a
  camera rendering in its own process.
* :mod:`.clock`: the wall clock (sleep, then spin) and a free clock (un-timed runs).
* :mod:`.runner`: the jitted controller + learner every 1 ms (:func:`run_loop`), the eye in its
  own process, and :func:`run_realtime`: an experiment in real time beside the same run in
  simulated time.
* :mod:`.report`: the deadline report (tick latency percentiles and histogram, missed deadlines,
  the eye's latency and dropped frames) and the run folder's files.
* :mod:`.workers`: the camera's and the eye's processes; :mod:`.shared`: their shared memory.
* :mod:`.profile`: where a control tick's time goes, per stage, without deadlines
  (``python benchmarks/realtime_profile.py``).

    from hec_jax import loop, realtime
    result = realtime.run_realtime(loop.catching(eye="truth"), realtime.RealtimeConfig(duration_s=6))
    result.report["control"]["latency_us"], result.comparison
"""

from hec_jax.realtime.clock import FreeClock, WallClock
from hec_jax.realtime.config import RealtimeConfig
from hec_jax.realtime.plant import (
    ArmModel,
    Camera,
    Frame,
    MujocoPlant,
    Plant,
    PlantSample,
    plant_model,
)
from hec_jax.realtime.report import deadline_report, print_report, write_report
from hec_jax.realtime.runner import (
    RealtimeResult,
    make_step_fns,
    ready_step_fns,
    run_loop,
    run_realtime,
)

__all__ = [
    "ArmModel",
    "Camera",
    "Frame",
    "FreeClock",
    "MujocoPlant",
    "Plant",
    "PlantSample",
    "RealtimeConfig",
    "RealtimeResult",
    "WallClock",
    "deadline_report",
    "make_step_fns",
    "plant_model",
    "print_report",
    "ready_step_fns",
    "run_loop",
    "run_realtime",
    "write_report",
]
