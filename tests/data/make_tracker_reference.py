"""Writes ``tracker_reference.npz``: rendered frames of the project's scene and what the image
tracker made of them before issue 24's checks were merged (``tests/test_eye_track.py``).

Run with the tracker of that time (main at 4416d0b), from a checkout of it, e.g.::

    git worktree add --detach /tmp/eyemain 4416d0b
    cd /tmp/eyemain && PYTHONPATH=/tmp/eyemain MUJOCO_GL=egl \\
        /work/main/.venv/bin/python /work/main/tests/data/make_tracker_reference.py OUT.npz

or, to record what that tracker makes of the stored frames on another CPU type (the search's
choice between near-equal starts follows the last bits of XLA's float arithmetic, which differ
between SIMD instruction sets; ``tests/test_eye_track.py``'s ``REFERENCE_AVX2``)::

    ... make_tracker_reference.py OUT.npz /work/main/tests/data/tracker_reference.npz

which writes the outputs only. With OpenCV 5, that tracker's ``detect.edge_points`` needs its one
``cv2.remap`` call split into blocks of under 32767 map rows (OpenCV 5 refuses larger maps; each
output row depends on its own map row only, so the split changes no value):
``git apply /work/main/tests/data/tracker_reference_opencv5.patch`` in the worktree. So made on
2026-12-03 (session 63): ``tracker_reference_avx2.npz``, on an AMD EPYC Zen 3 (AVX2, no
AVX-512), OpenCV 5.1.0, jax 0.10.2.

The frames: a 32-frame swing (release 0.5 rad, 30 fps, 640x480, ``render_swing``), blacked out
over frames 10-17 (0.27 s: a loss, a re-acquisition and a gap the smoother's ``max_gap_s = 0.2``
would split at) and with a grey bar over the cube's left half in frames 22-25 (a hand in front).
The background: the scene rendered with the cube and rod hidden, in colour (as the hand-eye loop
gives it). Stored per case, with the frames' uint8 arrays compressed:

* ``loop_*``: ``track_box`` with the hand-eye loop's tracker settings (``scene_tracker("void")``)
  and the RGB background (the loop's ``BoxTracker`` path, ``causal_*``);
* ``plain_*``: ``track_box`` with every default and no background (the median of the frames);
* ``ghost_*``: every default on the first 12 frames with frame 3 as the (RGB) background (a
  calibration shot with the cube in view): the case where the foreground checks decide.
"""

import sys

import mujoco
import numpy as np

from hec_jax.geometry import TrackConfig, track_box
from hec_jax.mjx_scene import CUBE_EDGE
from hec_jax.mjx_scene.model import load_mj_model
from hec_jax.mjx_scene.render import SceneCamera, render_swing

FPS = 30.0
FIELDS = (
    "position",
    "rotation",
    "velocity",
    "acceleration",
    "pose_rotation",
    "causal_position",
    "causal_velocity",
    "causal_acceleration",
    "causal_rotation",
    "valid",
    "measured_position",
    "information",
    "coverage",
    "rms_px",
    "segments",
    "edge_ids",
    "hinge",
    "hinge_axis",
)


def frames_and_background():
    """The test's frames (T, H, W, 3), background (H, W, 3) and intrinsics (3, 3)."""
    seq = render_swing(0.5, 32, FPS)
    frames = seq.frames.copy()
    frames[10:18] = 0
    k = seq.intrinsics
    for i in range(22, 26):
        u, v = (k[:2, :2] @ (seq.position[i, :2] / seq.position[i, 2]) + k[:2, 2]).astype(int)
        frames[i, v - 30 : v + 30, u - 30 : u] = 90
    m = load_mj_model()
    hinge = m.jnt_qposadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, "hinge")]
    qpos = m.qpos0.copy()
    qpos[hinge] = 0.5
    with SceneCamera(m, "eye", 640, 480, fast=False, hidden_geoms=("cube", "rod")) as cam:
        background = cam.render(qpos)
    return frames, background, k


def main(out: str, frames_from: str | None = None) -> None:
    """Render the frames and record the tracker's outputs on them, or (``frames_from``, a
    reference written before) record this CPU's outputs on that reference's stored frames."""
    import jax

    jax.config.update("jax_enable_x64", True)
    if frames_from is None:
        frames, background, k = frames_and_background()
    else:
        with np.load(frames_from) as f:
            frames, background, k = f["frames"], f["background"], f["intrinsics"]
    loop_track = TrackConfig(maneuver_nis=16.3, stop_hypothesis=True)  # scene_tracker("void")
    cases = {
        "loop": track_box(frames, k, CUBE_EDGE, FPS, loop_track, background=background),
        "plain": track_box(frames, k, CUBE_EDGE, FPS),
        "ghost": track_box(frames[:12], k, CUBE_EDGE, FPS, background=frames[3]),
    }
    arrays = {} if frames_from else {"frames": frames, "background": background, "intrinsics": k}
    for case, tr in cases.items():
        arrays |= {f"{case}_{name}": np.asarray(getattr(tr, name)) for name in FIELDS}
        print(case, "valid", tr.valid.astype(int), flush=True)
    np.savez_compressed(out, **arrays)


if __name__ == "__main__":
    main(*sys.argv[1:3])
