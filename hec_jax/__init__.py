"""hec_jax: hand-eye coordination for flexible impedance control, in JAX/MJX.

Importing the package makes headless rendering (EGL) MuJoCo's default backend unless the user
chose one (``MUJOCO_GL``): MuJoCo reads it when it is first imported, and this library runs
mostly without a display (CI, GPU hosts); import ``hec_jax`` before ``mujoco`` for it to apply.
"""

import os

os.environ.setdefault("MUJOCO_GL", "egl")
