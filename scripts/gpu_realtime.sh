#!/usr/bin/env bash
# The real-time loop on a many-core machine with a GPU renderer (issue 26; docs/realtime.md,
# "Sixteen cores and a GPU renderer"): MuJoCo's renderer through EGL on the GPU, JAX (controller,
# learner, tracker) on the CPU, float64, catching, 60 s per run:
#   1. the renderer alone at 320x240 and 640x480 (fast and full quality);
#   2. three runs with the ground-truth eye (the first with its simulated twin);
#   3. two runs with the camera at 640x480 (the first with both twins), then one without the eye's
#      local re-acquisition search (--eye-local-starts 0; 12 is the default).
# Usage, from the repository root of an installed checkout:
#   scripts/gpu_realtime.sh OUT_DIR [extra flags for every run, e.g. --rt-priority 50]
# (where SCHED_FIFO is refused: e.g. --spin-us 1000 --cpu-latency-us 0 --pool-idle; the pool's
# watchdog bounds the stall --pool-idle risks on a shared CPU: docs/realtime.md, sessions 69
# and 72). The wheels and GL loaders this needs on
# a machine without MuJoCo: scripts/offline_wheels.sh.
# The runs use normal scheduling unless a flag says otherwise (SCHED_FIFO was refused on the
# machines measured). Writes OUT_DIR/render.txt and one complete run folder per run.
set -euo pipefail
out=${1:?usage: scripts/gpu_realtime.sh OUT_DIR [flags]}
shift
mkdir -p "$out"
py=${PYTHON:-python3}
export MUJOCO_GL=egl JAX_PLATFORMS=cpu PYTHONUNBUFFERED=1
$py - <<'PY' | tee "$out/render.txt"
import time

import numpy as np
from OpenGL.GL import GL_RENDERER, glGetString

from hec_jax.loop.config import TaskConfig
from hec_jax.mjx_scene.render import SceneCamera
from hec_jax.realtime.plant import plant_model

m = plant_model(TaskConfig())
for w, h in ((320, 240), (640, 480)):
    for fast in (True, False):
        with SceneCamera(m, "eye", w, h, fast) as cam:
            q, ts = m.qpos0.copy(), []
            for i in range(60):
                q[-1] = 0.01 * i
                t0 = time.perf_counter()
                cam.render(q)
                ts.append(time.perf_counter() - t0)
            if w == 640 and fast:
                print("renderer:", glGetString(GL_RENDERER))
        p50, p99 = 1e3 * np.percentile(ts[10:], [50, 99])
        print(f"{w}x{h} fast={fast}: p50 {p50:.2f} ms p99 {p99:.2f} ms")
PY
rt="$py experiments/realtime.py --preset catching --duration-s 60"
$rt --eye truth --twin truth --out "$out/truth-1" "$@"
$rt --eye truth --twin none --out "$out/truth-2" "$@"
$rt --eye truth --twin none --out "$out/truth-3" "$@"
cam="--eye camera --width 640 --height 480 --child-nice -10"
$rt $cam --twin auto --out "$out/camera640-1" "$@"
$rt $cam --twin none --out "$out/camera640-2" "$@"
$rt $cam --twin none --eye-local-starts 0 --out "$out/camera640-local0" "$@"
