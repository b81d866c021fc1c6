#!/usr/bin/env bash
# Wheels (and GL loader packages) for a GPU machine with Python 3.12 and no internet, small
# enough to travel with the working tree (docs/gpu.md, "How a run on those machines was made"):
#   wheels/  mujoco 3.17.0 and mujoco-mjx 3.17.0 without the folders the project never imports
#            (mujoco/experimental: the studio GUI, 15.7 MB; mujoco/mjx/test_data, 6.5 MB; their
#            RECORD rewritten to match), and tyro, typeguard, docstring-parser, trimesh,
#            websockets, glfw, PyOpenGL;
#   .gl/     Debian bookworm's GL loaders (libegl1, libglvnd0, libopengl0, libgl1, libglx0,
#            libgles2, libvulkan1; pinned) for MuJoCo's EGL renderer where the image has the
#            NVIDIA driver but not the loaders.
# Both folders are replaced whole. Usage, from the repository root of a machine with pip and
# apt-get (Debian sources):  scripts/offline_wheels.sh
# On the GPU machine (root; unpacking into / overwrites any loaders the image has):
#   for f in .gl/*.deb; do dpkg -x $f /; done; ldconfig
#   python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site wheels/*.whl
#   export PYTHONPATH=/tmp/site:$PWD MUJOCO_GL=egl JAX_PLATFORMS=cpu
#   (and, if EGL finds no device, __EGL_VENDOR_LIBRARY_FILENAMES=
#    /usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json);
# scripts/gpu_realtime_offline.sh does all of it for the real-time runs.
set -euo pipefail
py=${PYTHON:-python3}
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
mkdir -p "$tmp/full" "$tmp/wheels" "$tmp/gl" "$tmp/lists/partial"
"$py" -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 \
  --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 --platform manylinux1_x86_64 \
  -d "$tmp/full" mujoco==3.17.0 mujoco-mjx==3.17.0 tyro==1.0.17 typeguard==4.6.1 \
  docstring-parser==0.18.0 trimesh==5.2.0 websockets==17.4 glfw==2.11.0 pyopengl==3.1.10
"$py" - "$tmp/full" "$tmp/wheels" <<'PY'
import pathlib
import shutil
import sys
import zipfile

src_dir, dst_dir = map(pathlib.Path, sys.argv[1:])
drop = {"mujoco-": "mujoco/experimental/", "mujoco_mjx-": "mujoco/mjx/test_data/"}
for whl in sorted(src_dir.glob("*.whl")):
    prefix = next((d for p, d in drop.items() if whl.name.startswith(p)), None)
    if prefix is None:
        shutil.copy(whl, dst_dir / whl.name)
        continue
    with zipfile.ZipFile(whl) as src, zipfile.ZipFile(dst_dir / whl.name, "w", zipfile.ZIP_DEFLATED) as dst:
        for info in src.infolist():
            name = info.filename
            if name.startswith(prefix):
                continue
            data = src.read(name)
            if name.endswith(".dist-info/RECORD"):  # the dropped files' lines out
                lines = data.decode().splitlines(keepends=True)
                data = "".join(x for x in lines if not x.startswith(prefix)).encode()
            dst.writestr(info, data)
PY
o="-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=$tmp/lists"
# shellcheck disable=SC2086  # $o: several options
apt-get $o update >/dev/null
(
  cd "$tmp/gl"
  # shellcheck disable=SC2086
  apt-get $o download libvulkan1=1.3.239.0-1 libegl1=1.6.0-1 libglvnd0=1.6.0-1 \
    libopengl0=1.6.0-1 libgl1=1.6.0-1 libglx0=1.6.0-1 libgles2=1.6.0-1
)
rm -rf wheels .gl
mv "$tmp/wheels" wheels
mv "$tmp/gl" .gl
if git rev-parse --is-inside-work-tree >/dev/null 2>&1; then
  for d in wheels .gl; do
    git check-ignore -q "$d" || echo "warning: $d/ is not ignored by git" >&2
  done
fi
du -sh wheels .gl
