#!/usr/bin/env bash
# README row 90's real-time catching run on a GPU machine without MuJoCo or internet (the
# lent H200 machines), with the GPU renderer (EGL): how docs/realtime.md's session-69 runs were
# made. Needs the folders scripts/offline_wheels.sh makes (wheels/, .gl/) in the copy of the
# tree, and root there (the GL loaders are unpacked into /).
# Usage, from the repository root on that machine:
#   OUT=/some/dir scripts/gpu_realtime_offline.sh TAG [RUNS] [extra flags, e.g. --no-pool-idle]
# Writes $OUT/TAG.log (the machine, the renderer, each run's console) and $OUT/TAG-k.tar.gz
# (each run folder without its trajectories). Uses SCHED_FIFO where permitted, else spins
# through the period (--spin-us 1000) with XLA's pool under SCHED_IDLE (--pool-idle; since
# session 72, with its watchdog; before, sessions 69-71 gave it as an extra flag); asks idle
# CPUs to poll where /dev/cpu_dma_latency is writable. Later flags win (--no-pool-idle).
set -uo pipefail
tag=${1:?usage: scripts/gpu_realtime_offline.sh TAG [RUNS] [flags]}
n=${2:-1}
shift $(($# < 2 ? $# : 2))
out=${OUT:?set OUT to the output folder}
# the loaders go into /: only on the GPU machine it is meant for
command -v nvidia-smi >/dev/null || { echo "nvidia-smi not found: this is for a GPU machine" >&2; exit 1; }
[ "$(id -u)" = 0 ] || { echo "needs root (the GL loaders are unpacked into /)" >&2; exit 1; }
mkdir -p "$out"
for f in .gl/*.deb; do dpkg -x "$f" /; done
ldconfig
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
  --target /tmp/site wheels/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD MUJOCO_GL=egl JAX_PLATFORMS=cpu PYTHONUNBUFFERED=1
vendor=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
[ -e $vendor ] && export __EGL_VENDOR_LIBRARY_FILENAMES=$vendor
{
  nproc
  grep -m1 "model name" /proc/cpuinfo
  uptime
  nvidia-smi -L
  chrt -f 50 true && echo "SCHED_FIFO permitted" || echo "SCHED_FIFO refused"
  ls -la /dev/cpu_dma_latency
  python3 -c "import jax, mujoco; print('jax', jax.__version__, 'mujoco', mujoco.__version__)"
  python3 - <<'PY'
import time

import mujoco
from OpenGL.GL import GL_RENDERER, glGetString

m = mujoco.MjModel.from_xml_string('<mujoco><worldbody><geom size="1"/></worldbody></mujoco>')
with mujoco.Renderer(m, 480, 640) as r:
    r.update_scene(mujoco.MjData(m))
    t = time.perf_counter()
    for _ in range(30):
        r.render()
    print("renderer:", glGetString(GL_RENDERER), f"{(time.perf_counter() - t) / 30 * 1e3:.2f} ms")
PY
} 2>&1 | tee "$out/$tag.log"
if chrt -f 50 true 2>/dev/null; then
  flags="--rt-priority 50 --camera-priority 40"
else
  # XLA's pool under SCHED_IDLE, with its watchdog (RealtimeConfig.pool_rescue_us) bounding
  # the stall another process's burst on the loop's CPU would otherwise cause (session 72)
  flags="--spin-us 1000 --pool-idle"
fi
flags="$flags --child-nice -10"
[ -w /dev/cpu_dma_latency ] && flags="$flags --cpu-latency-us 0"
echo "flags: $flags $*" | tee -a "$out/$tag.log"
for k in $(seq 1 "$n"); do
  d=/tmp/runs/$tag-$k
  python3 experiments/realtime.py --preset catching --eye camera --width 640 --height 480 \
    --camera-msaa 0 --duration-s 60 --camera-plane-grid-m 0.05 $flags "$@" --out "$d" 2>&1 |
    tee -a "$out/$tag.log" | tail -40
  tar czf "$out/$tag-$k.tar.gz" --exclude="trajectory_*" -C /tmp/runs "$tag-$k"
done
