r"""The box tracker's depth and tilt on the real-time camera's frames, against the simulator.

Runs the simulated camera loop of the real-time preset once (``realtime_experiment``: one seed,
the swings of ``--duration-s``, the real-time eye's tracker; the void scene without
multisampling, as the real-time camera renders it), records every frame as the eye got it (the
masked image and the occluded pixels it was told, ``run_camera``'s ``observe``) with the
simulator's cube pose at mid-exposure, then replays the recorded frames through each variant of
the tracker (``VARIANTS``: fields of the tracker replaced), a fresh track per swing.

The replay is open loop: each variant sees the frames the loop's own tracker produced (the arm
moves on that tracker's estimates before contact; in contact the controller does not use the
eye). The first variant, "tracker as configured", reproduces the loop's fits.

Tabulated per variant, in contact and out of it (the hand's contact at the frame's step): the
error of the fitted centre along the camera's axis (depth) and across it (the image plane),
the filtered centre's, the fitted rotation's tilt out of the image plane (the rotation error's
component about the camera's x and y axes; the hinge axis is the optical axis in the void
scene, so the true cube never tilts), invalid frames, which hypothesis gave each fit, and a
least-squares fit of the depth error on the two tilt magnitudes (mm per degree, R^2).

Deterministic: same seed, same frames, same numbers (CPU). The frames are held in memory
(about 0.9 MB each at 640x480: 1.7 GB for 60 s).

    MUJOCO_GL=egl python benchmarks/eye_depth.py --out runs/eye_depth
    MUJOCO_GL=egl python benchmarks/eye_depth.py --seed 1 --out runs/eye_depth_seed1 \
        --variants "tracker as configured" "rotation prior 2 deg"
"""

from __future__ import annotations

import dataclasses
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import jax
import numpy as np

from hec_jax.cli import command, parse, require
from hec_jax.geometry.track import BoxTracker, _log, snap_to_symmetry
from hec_jax.loop.camera_loop import frame_steps, run_camera
from hec_jax.loop.policy import build_loop
from hec_jax.realtime.config import RealtimeConfig
from hec_jax.realtime.runner import void_camera_experiment
from hec_jax.runs import run_folder, write_json, write_text

# name: fields of the real-time eye's tracker replaced
VARIANTS = {
    "tracker as configured": {},
    "no depth gate": {"depth_gate": None},
    "rotation prior 0.2 deg": {"rotation_prior_deg": 0.2},
    "rotation prior 2 deg": {"rotation_prior_deg": 2.0},
}


@dataclass(frozen=True)
class EyeDepth:
    """How long, how the frames are rendered, which variants, and where to write."""

    out: Path = Path("runs/eye_depth")  # run folder
    overwrite: bool = False  # replace an existing non-empty out
    duration_s: float = 60.0  # [s] as the real-time run (its number of swings)
    msaa: int = 0  # multisample anti-aliasing of the frames (0: as the real-time camera)
    width: int = 640  # [px]
    height: int = 480  # [px]
    variants: tuple[str, ...] = tuple(VARIANTS)  # names of VARIANTS to replay
    seed: int = 0  # the networks' initialisation (the preset's, 0, is the real-time runs')

    def __post_init__(self):
        require(self, "seed", "seed")
        unknown = [v for v in self.variants if v not in VARIANTS]
        if unknown:
            raise ValueError(f"--variants: unknown {unknown}; known: {list(VARIANTS)}")


@dataclass
class Recording:
    """The frames as the eye got them, with the simulator's cube pose in the camera frame."""

    images: list
    occluded: list
    swing: list
    frame: list
    position: list  # (3,) [m] cube centre, camera frame
    rotation: list  # (3, 3) R_cam_box
    eye: dict | None = None  # the eye's background, intrinsics, size [m] and fps [1/s]


def record(a: EyeDepth, exp, loop) -> tuple[Recording, np.ndarray, object]:
    """Runs the simulated camera loop once; (recording, in_contact (swings, steps), the
    tracker's config).
    """
    rec = Recording([], [], [], [], [], [])
    cube = loop.ids.cube_body

    def observe(seed, swing, frame, image, occluded, camera, eye):
        if swing == "final":
            return
        if rec.eye is None:
            rec.eye = {
                "background": eye.given_background,
                "intrinsics": eye.intrinsics,
                "size": eye.size,
                "fps": eye.fps,
            }
        r_wc, t_wc = camera.world_from_camera
        rec.images.append(image.copy())
        rec.occluded.append(None if occluded is None else np.packbits(occluded, axis=-1))
        rec.swing.append(int(swing))
        rec.frame.append(int(frame))
        rec.position.append(r_wc.T @ (camera.data.xpos[cube] - t_wc))
        rec.rotation.append(r_wc.T @ camera.data.xmat[cube].reshape(3, 3))

    conditions = exp.task.pendulum.conditions()
    keys = jax.random.split(jax.random.PRNGKey(exp.seed), 1)
    logs, _, _ = run_camera(
        loop, conditions, keys, "learned", exp.camera, progress=False, observe=observe
    )
    return rec, np.asarray(logs["in_contact"])[0], exp.camera.tracker


def replay(rec: Recording, in_contact, track, steps) -> dict:
    """One tracker over the recorded frames (a fresh track per swing): the summarised errors."""
    e = rec.eye
    tracker = BoxTracker(e["intrinsics"], e["size"], e["fps"], track, e["background"])
    width = rec.images[0].shape[1]
    rows = []
    last = None
    for k, image in enumerate(rec.images):
        if rec.swing[k] != last:
            tracker.reset()
            last = rec.swing[k]
        occ = rec.occluded[k]
        occ = None if occ is None else np.unpackbits(occ, axis=-1)[:, :width].astype(bool)
        st = tracker.update(image, occ) if occ is not None else tracker.update(image)
        truth_p, truth_r = rec.position[k], rec.rotation[k]
        row = {
            "contact": bool(in_contact[rec.swing[k], steps[rec.frame[k]]]),
            "valid": bool(st.valid),
            "source": st.fit_source,
            "eye_ms": float(st.timing_ms["total_ms"]),
            "filtered": np.asarray(st.position) - truth_p if st.initialised else None,
        }
        if st.valid:
            row["measured"] = np.asarray(st.measured_position) - truth_p
            rot = snap_to_symmetry(np.asarray(st.pose_rotation), truth_r)
            row["tilt_deg"] = np.degrees(_log(rot @ truth_r.T))[:2]
        rows.append(row)
    return summarise(rows)


def _stats(x) -> dict | None:
    """p50 / p99 / max of ``x`` [mm] (None if empty)."""
    x = np.asarray(x, np.float64)
    if not x.size:
        return None
    p50, p99 = np.percentile(x, [50, 99])
    return {"p50": float(p50), "p99": float(p99), "max": float(x.max())}


def summarise(rows: list[dict]) -> dict:
    """The tabulated errors [mm, deg] of one variant's rows."""
    out = {}
    for part, in_contact in (("contact", True), ("free", False)):
        sel = [r for r in rows if r["contact"] == in_contact]
        meas = np.array([r["measured"] for r in sel if "measured" in r]).reshape(-1, 3)
        filt = np.array([r["filtered"] for r in sel if r["filtered"] is not None]).reshape(-1, 3)
        tilt = np.array([r["tilt_deg"] for r in sel if "tilt_deg" in r]).reshape(-1, 2)
        out[part] = {
            "frames": len(sel),
            "invalid": sum(not r["valid"] for r in sel),
            "fit_depth_mm": _stats(1e3 * np.abs(meas[:, 2])),
            "fit_image_plane_mm": _stats(1e3 * np.linalg.norm(meas[:, :2], axis=1)),
            "filtered_depth_mm": _stats(1e3 * np.abs(filt[:, 2])),
            "filtered_image_plane_mm": _stats(1e3 * np.linalg.norm(filt[:, :2], axis=1)),
            "tilt_deg": _stats(np.linalg.norm(tilt, axis=1)),
        }
    fits = [r for r in rows if "measured" in r]
    depth = 1e3 * np.array([r["measured"][2] for r in fits])
    tilt = np.abs(np.array([r["tilt_deg"] for r in fits]))
    a = np.c_[tilt, np.ones(len(depth))]
    coef, *_ = np.linalg.lstsq(a, depth, rcond=None)
    resid = depth - a @ coef
    out["depth_on_tilt"] = {
        "mm_per_deg_about_x": float(coef[0]),
        "mm_per_deg_about_y": float(coef[1]),
        "r2": float(1.0 - resid.var() / depth.var()) if depth.var() > 0 else None,
    }
    out["fits_by_source"] = dict(Counter(r["source"] or "invalid" for r in rows))
    out["eye_ms_p50"] = float(np.median([r["eye_ms"] for r in rows]))
    return out


def table(results: dict) -> list[str]:
    """Markdown rows: one per variant and part."""

    def cell(s):
        return "-" if s is None else f"{s['p50']:.1f} / {s['p99']:.1f} / {s['max']:.1f}"

    rows = [
        "| variant | part | frames (invalid) | fit depth [mm] | fit image plane [mm] "
        "| filtered depth [mm] | filtered image plane [mm] | tilt [deg] |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, r in results.items():
        for part in ("contact", "free"):
            p = r[part]
            rows.append(
                f"| {name} | {part} | {p['frames']} ({p['invalid']}) | {cell(p['fit_depth_mm'])} "
                f"| {cell(p['fit_image_plane_mm'])} | {cell(p['filtered_depth_mm'])} "
                f"| {cell(p['filtered_image_plane_mm'])} | {cell(p['tilt_deg'])} |"
            )
    rows += ["", "p50 / p99 / max.", ""]
    rows += ["| variant | depth on tilt (mm/deg about x, y; R^2) | fits by source | eye ms p50 |"]
    rows += ["|---|---|---|---|"]
    for name, r in results.items():
        d = r["depth_on_tilt"]
        r2 = "-" if d["r2"] is None else f"{d['r2']:.2f}"
        fits = ", ".join(f"{k} {v}" for k, v in sorted(r["fits_by_source"].items()))
        rows.append(
            f"| {name} | {d['mm_per_deg_about_x']:.2f}, {d['mm_per_deg_about_y']:.2f}; {r2} "
            f"| {fits} | {r['eye_ms_p50']:.1f} |"
        )
    return rows


@command
def main(argv=None) -> dict:
    """Records the frames, replays the variants (flags: ``--help``); returns the results."""
    a = parse(EyeDepth(), argv, __doc__)
    jax.config.update("jax_enable_x64", True)
    exp = void_camera_experiment(
        "catching", a.seed, a.width, a.height, a.msaa, RealtimeConfig(duration_s=a.duration_s)
    )
    loop = build_loop(exp.task)
    settings = {k: v for k, v in dataclasses.asdict(a).items() if k != "seed"}
    settings |= {"variants_fields": {v: VARIANTS[v] for v in a.variants}}
    with run_folder(a.out, exp.seed, settings, a.overwrite) as folder:
        t0 = time.perf_counter()
        rec, in_contact, track = record(a, exp, loop)
        print(f"recorded {len(rec.images)} frames in {time.perf_counter() - t0:.0f} s")
        steps = frame_steps(exp.camera, loop.ids.timestep, in_contact.shape[1])
        results = {}
        for name in a.variants:
            t0 = time.perf_counter()
            variant = dataclasses.replace(track, **VARIANTS[name])
            results[name] = replay(rec, in_contact, variant, steps)
            print(f"{name}: replayed in {time.perf_counter() - t0:.0f} s", flush=True)
        write_json(folder / "results.json", results)
        rows = table(results)
        write_text(folder / "table.md", "\n".join(rows) + "\n")
        print("\n".join(rows))
    return results


if __name__ == "__main__":
    main()
