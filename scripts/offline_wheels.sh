#!/usr/bin/env bash
# Wheels (and GL loader packages) for a GPU machine with Python 3.12 and no internet, small
# enough to travel with the working tree (docs/gpu.md, "How a run on those machines was made"):
#   wheels/  mujoco 3.17.0 and mujoco-mjx 3.17.0 without the folders the project never imports
#            (mujoco/experimental: the studio GUI, 15.7 MB; mujoco/mjx/test_data, 6.5 MB), and
#            tyro, typeguard, docstring-parser, trimesh, websockets, glfw, PyOpenGL;
#   .gl/     Debian's GL loaders (libegl1, libglvnd0, libopengl0, libgl1, libglx0, libgles2,
#            libvulkan1) for MuJoCo's EGL renderer where the image has the driver but not them.
# Usage, from the repository root of a machine with pip and apt-get:  scripts/offline_wheels.sh
# On the GPU machine, in the copy of the tree:
#   for f in .gl/*.deb; do dpkg -x $f /; done; ldconfig
#   python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site wheels/*.whl
#   export PYTHONPATH=/tmp/site:$PWD MUJOCO_GL=egl
set -euo pipefail
py=${PYTHON:-python3}
full=$(mktemp -d)
trap 'rm -rf "$full"' EXIT
mkdir -p wheels .gl
$py -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 \
  --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 --platform manylinux1_x86_64 \
  -d "$full" mujoco==3.17.0 mujoco-mjx==3.17.0 tyro==1.0.17 typeguard==4.6.1 \
  docstring-parser==0.18.0 trimesh==5.2.0 websockets==17.4 glfw==2.11.0 pyopengl==3.1.10
$py - "$full" <<'PY'
import pathlib
import shutil
import sys
import zipfile

drop = {"mujoco-": ("mujoco/experimental/",), "mujoco_mjx-": ("mujoco/mjx/test_data/",)}
for whl in sorted(pathlib.Path(sys.argv[1]).glob("*.whl")):
    skip = next((d for p, d in drop.items() if whl.name.startswith(p)), ())
    out = pathlib.Path("wheels") / whl.name
    if not skip:
        shutil.copy(whl, out)
        continue
    with zipfile.ZipFile(whl) as src, zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as dst:
        for info in src.infolist():
            if not info.filename.startswith(skip):
                dst.writestr(info, src.read(info.filename))
PY
o='-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/amd64'
mkdir -p /tmp/amd64/partial
apt-get $o update >/dev/null
(cd .gl && apt-get $o download libvulkan1 libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2)
for d in wheels .gl; do
  git check-ignore -q "$d" || echo "warning: $d/ is not ignored by git (.git/info/exclude)" >&2
done
du -sh wheels .gl
