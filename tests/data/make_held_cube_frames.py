"""Writes the real-time eye's invalid frames for ``tests/test_eye_tracker.py``:
``held_cube_failed_frames.npz``, frames that no hypothesis of the tracker recovered before
``TrackConfig.min_segments_hidden`` (session 23's runs ``rt-save-8`` and ``rt-save-10``), and
``held_cube_runaway_frames.npz``, frames whose accurate fits the innovation gate rejected after
the filter ran away in depth, before ``TrackConfig.depth_gate`` (session 23's ``rt-fix-6`` and
``rt-three-5``), and, with ``--source local_turned``, ``held_cube_turned_frames.npz``: the frames
that the local search's turned starts recovered (sessions 24-25: ``rt-np-5``, ``rt-df-5``,
``rt-df-8``; not ``rt-final-2``'s two, whose run restarted its filter in float32, a form since
replaced), with the fit each run logged (``logged_camera``, camera frame [m]).

From run folders of ``experiments/realtime.py ... --eye-save-failed 64`` (the catching preset,
the void scene at 640x480 without multisampling, seed 0), the invalid frames' records (``realtime.workers.failed_frame_record``: the
masked image and the mask's pixels as the tracker got them, the tracker's snapshot before the
frame), the tracker's settings and background, and the cube's true centre (world x, z [m]) with
the camera's pose to compare::

    MUJOCO_GL=egl python tests/data/make_held_cube_frames.py OUT.npz RUN_FOLDER [RUN_FOLDER ...]
    MUJOCO_GL=egl python tests/data/make_held_cube_frames.py --source local_turned OUT.npz RUN ...

The snapshots and the tracker's config are stored pickled (uint8 arrays), the rest as arrays.
"""

import pickle
import sys
from pathlib import Path

import numpy as np

from hec_jax.loop.config import PRESETS, CameraConfig
from hec_jax.realtime.plant import camera_model
from hec_jax.realtime.workers import _MaskCamera


def main(out: str, *runs: str, source: str = "") -> None:
    """``source``: the frames of that ``fit_source``; "" the invalid ones."""
    cam = CameraConfig.void_perfect(width=640, height=480)
    m, _ = camera_model(PRESETS["catching"](camera=cam).task, cam)
    r_wc, t_wc = _MaskCamera(m, cam.width, cam.height).world_from_camera
    images, occluded, snaps, truth, names, logged = [], [], [], [], [], []
    tracker = None
    for run in runs:
        saved = pickle.loads((Path(run) / "eye_failed_frames.pkl").read_bytes())
        frames = np.load(Path(run) / "eye_frames.npz")
        tracker = saved["tracker"]
        for r in saved["frames"]:
            if r["fit_source"] != source:
                continue
            row = r["row"]
            i = int(np.flatnonzero(frames["camera_index"] == row["index"])[0])
            images.append(r["image"])
            occluded.append(r["occluded"])
            snaps.append(np.frombuffer(pickle.dumps(r["snapshot"]), np.uint8))
            truth.append(frames["camera_x_true"][i])
            logged.append(np.asarray(r["measured_position"], float))
            names.append(f"{Path(run).name} episode {row['episode']} frame {row['number']}")
    np.savez_compressed(
        out,
        images=np.stack(images),
        occluded=np.stack(occluded),
        truth_world_xz=np.stack(truth),
        logged_camera=np.stack(logged),
        names=np.array(names),
        snapshot_lengths=np.array([len(s) for s in snaps]),
        snapshots=np.concatenate(snaps),
        config=np.frombuffer(pickle.dumps(tracker["config"]), np.uint8),
        intrinsics=tracker["intrinsics"],
        size=tracker["size"],
        fps=tracker["fps"],
        background=tracker["background"],
        world_from_camera_r=r_wc,
        world_from_camera_t=t_wc,
    )


if __name__ == "__main__":
    args = sys.argv[1:]
    chosen = ""
    if args and args[0] == "--source":
        chosen, args = args[1], args[2:]
    main(*args, source=chosen)
