"""The camera's and the eye's processes of a real-time run (started by ``spawn``).

* :func:`camera_main` renders the plant's state (read from its shared board) whenever the plant
  time reaches the next frame time (a frame's mid-exposure; the exposures end every ``period``
  control steps from each release), into the shared frame ring, stamped with the plant time of
  the state shown, once the plant has reached the exposure's end. If a frame cannot start on
  time (rendering slower than the frame rate) it is exposed late, and frame times that passed
  entirely are skipped; both are counted.
* :func:`eye_main` is the eye: it takes the newest frame (frames that arrived while it was busy
  are dropped and counted), masks the robot out of it from the arm's joint angles at the
  exposure (as :mod:`hec_jax.loop.camera_loop`), runs the :class:`~hec_jax.geometry.BoxTracker`
  and publishes the object's state in the world's task plane with the exposure's time stamp to
  a shared board, which the control loop reads every tick.

Each process keeps a per-frame log and puts it on its queue when told to stop.
"""

from __future__ import annotations

import gc
import os
import time
import traceback

import numpy as np

from hec_jax.realtime.clock import set_scheduling
from hec_jax.report import CompileMeter

ESTIMATE_FIELDS = {
    "frame": (),
    "episode": (),
    "number": (),
    "t_stamp": (),
    "x": (2,),
    "xd": (2,),
    "xdd": (2,),
    "seen": (),
    "valid": (),
    "initialised": (),
    "t_wall_exposure": (),
    "t_wall_done": (),
}

_POLL_S = 2e-4  # [s] how often an idle worker looks for new work


def _stack(rows: list[dict]) -> dict[str, np.ndarray]:
    if not rows:
        return {}
    return {k: np.asarray([r[k] for r in rows]) for k in rows[0]}


def _board_vector(v: np.ndarray, seen: bool) -> np.ndarray:
    """An estimate's vector as the eye publishes it: ``np.nan_to_num(v)`` where ``seen``, else
    zeros (the same values; ``nan_to_num`` only where ``v`` is not all finite, since its
    ~20 us a call delayed the publication).
    """
    if not seen:
        return np.zeros(2)
    return v if np.isfinite(v).all() else np.nan_to_num(v)


def _steal_delta(before: list[float], after: list[float]) -> np.ndarray:
    """[ms] per CPU: the host's steal between two :func:`~.clock.host_steal_ms` readings
    (empty without steal accounting; NaN per CPU where one of the two readings failed, so that
    every frame's row has the same length).
    """
    if len(before) != len(after):
        return np.full(max(len(before), len(after)), np.nan)
    return np.subtract(after, before)


def frame_state_step(number: int, period: int, exposure_back: int) -> int:
    """The plant step whose state frame ``number`` of an episode shows: its mid-exposure,
    ``exposure_back`` steps before the exposure ends at step ``number * period`` (not before the
    release): the simulated camera loop's ``max(s - e, 0)`` for its frame steps ``s``
    (:func:`~hec_jax.loop.camera_loop.frame_steps`) and ``e``
    (:func:`~hec_jax.loop.camera_loop.mid_exposure_steps`), whose frames start at the release
    (``CameraConfig.frame_offset_s`` 0: a trigger phase is refused in real time).
    """
    return max(number * period - exposure_back, 0)


def newest_frame(step: int, period: int, exposure_back: int) -> int:
    """The newest frame of an episode whose state (:func:`frame_state_step`) the plant has
    reached at ``step``.
    """
    return (step + exposure_back) // period


def camera_sleep_s(rec: dict, step_due: int, dt: float, now: float) -> float:
    """[s] the camera sleeps before it looks at the plant's board again, a frame being due at
    ``step_due`` and the board showing ``rec`` (``STATE_FIELDS``) at monotonic time ``now``.

    Until two steps before the frame is due, counted from the step shown: polling every
    ``_POLL_S`` woke this real-time process about once a step, each time preempting the eye on
    its CPU (docs/realtime.md, "The eye's CPU and the held cube"). But when the plant catches up
    after a stall (a burst of steps in microseconds), the step shown is behind the clock, and
    the count from it overslept the frame by up to a frame period; so the sleep also ends two
    steps before the frame's time on the plant's clock (``t_clock`` at the write ``t_wall``;
    NaN: the clock is not running, the count alone). On time the count ends first (the same
    sleep as before). At least ``_POLL_S``.
    """
    by_step = (step_due - int(rec["step"]) - 2) * dt
    t_clock = float(rec["t_clock"])
    if np.isfinite(t_clock):
        by_clock = (step_due - 2) * dt - t_clock - (now - float(rec["t_wall"]))
        by_step = min(by_step, by_clock)
    return max(_POLL_S, by_step)


def camera_main(
    task,
    cam,
    period,
    q0,
    board,
    frames,
    calibration,
    *,
    stop,
    log_queue,
    priority=0,
    nice=0,
    msaa=None,
    shadows=None,
    dt=1e-3,
    exposure_back=0,
):
    """The camera process: calibration shots, then frames on the plant's clock until ``stop``.

    Frame ``n`` of an episode shows the plant's state at step :func:`frame_state_step` (its
    mid-exposure: ``exposure_back`` steps before the exposure ends at step ``n * period``, as in
    the simulated camera loop), stamped with that step's plant time, and is put in the ring no
    earlier than the plant reaches the exposure's end (a camera reads a frame out once exposed);
    one whose exposure would end after its episode is not put, and counted (``not_read_out``).

    Args:
        task: the :class:`~hec_jax.loop.config.TaskConfig` (its world is rendered).
        cam: the :class:`~hec_jax.loop.config.CameraConfig` (resolution, fast rendering).
        period: control steps between frames.
        q0: (nq,) qpos at the release (for the calibration shots).
        board: the plant's state board (t, step, episode, t_wall, t_clock, qpos).
        frames: the :class:`~hec_jax.realtime.shared.FrameRing` to fill.
        calibration: :class:`~hec_jax.realtime.shared.Images`: 0 background (pendulum hidden),
            1 the release frame.
        stop: event ending the loop.
        log_queue: receives the per-frame log (or ``{"error": ...}``).
        priority: SCHED_FIFO priority once the calibration shots are taken (0: none).
        nice: the process's nice value (threads started later inherit it).
        msaa: multisample anti-aliasing samples (None: the model's).
        shadows: the lights cast shadows (None: the scene's, :func:`~.plant.camera_model`).
        dt: [s] the plant's time step (the camera sleeps until two steps before a frame is
            due, then polls every ``_POLL_S``).
        exposure_back: steps from a frame's mid-exposure (the state it shows) to the end of its
            exposure (0: the state at the exposure's end, ``n * period``;
            :func:`~hec_jax.loop.camera_loop.mid_exposure_steps`).
    """
    rows: list[dict] = []
    try:
        os.setpriority(os.PRIO_PROCESS, 0, nice)
        from hec_jax.mjx_scene import scene_ids
        from hec_jax.mjx_scene.render import SceneCamera
        from hec_jax.realtime.clock import host_steal_ms, monotonic_s
        from hec_jax.realtime.plant import camera_model

        m, shadows = camera_model(task, cam, shadows)  # void: the plant's model; lab: around it
        if msaa is not None:
            m.vis.quality.offsamples = msaa
        ids = scene_ids(m)
        arm = np.array(ids.arm_qpos)
        view = (cam.width, cam.height, cam.fast_render)
        with SceneCamera(m, "eye", *view, ("cube", "rod"), shadows) as bg:
            calibration.put(0, bg.render(q0))
        camera = SceneCamera(m, "eye", *view, (), shadows)
        calibration.put(1, camera.render(q0))
        if priority:
            set_scheduling(os.SCHED_FIFO, priority)
        # last_seq 0: the board before the plant first wrote it (zeros) is no state to show
        episode, number, index, last_seq, skipped, not_read_out = -1, 0, 0, 0, 0, 0
        pending = None  # a state read while waiting for an exposure's end, not yet looked at
        while not stop.is_set():
            if pending is None:
                seq = board.seq
                if seq == last_seq:
                    time.sleep(_POLL_S)
                    continue
                last_seq, rec = board.read()
            else:
                rec, pending = pending, None
            if int(rec["episode"]) != episode:
                episode, number = int(rec["episode"]), 0
            step = int(rec["step"])
            state_step = frame_state_step(number, period, exposure_back)
            if step < state_step:
                time.sleep(camera_sleep_s(rec, state_step, dt, monotonic_s()))
                continue
            # held off for a whole period or more (a stall): the newest frame time that has
            # come, not an old one exposed late; the ones passed over are skipped
            due = newest_frame(step, period, exposure_back)
            if due > number:
                skipped += due - number
                number = due
                state_step = frame_state_step(number, period, exposure_back)
            t0, cpu0, steal0 = monotonic_s(), time.process_time(), host_steal_ms()
            image = camera.render(rec["qpos"])
            x_true = camera.data.site_xpos[ids.cube_site].copy()
            t1, cpu1, steal1 = monotonic_s(), time.process_time(), host_steal_ms()
            # not read out before the exposure ends: a renderer faster than half the exposure
            # (the GPU's, 1.5 ms against 2) waits here; a frame whose exposure would end after
            # its episode (or the run) is not put, and counted
            end_step, now = number * period, rec
            if int(now["step"]) < end_step:  # the plant has moved on while this rendered
                last_seq, now = board.read()
            while int(now["step"]) < end_step and int(now["episode"]) == episode:
                if stop.is_set():
                    break
                time.sleep(max(_POLL_S, (end_step - int(now["step"]) - 1) * dt))
                last_seq, now = board.read()
            if int(now["step"]) < end_step or int(now["episode"]) != episode:
                not_read_out += 1
                number += 1
                pending = now  # the next episode's state (or the run's last)
                continue
            t_put = monotonic_s()
            frames.put(
                index,
                image,
                episode=episode,
                number=number,
                t_exposure=rec["t"],
                t_wall_exposure=rec["t_wall"],
                t_wall_done=t1,
                q_arm=rec["qpos"][arm],
            )
            rows.append(
                dict(
                    index=index,
                    episode=episode,
                    number=number,
                    step_due=state_step,
                    step=step,
                    t_exposure=float(rec["t"]),
                    t_wall_exposure=float(rec["t_wall"]),
                    t_wall_start=t0,
                    t_wall_done=t1,
                    t_wall_put=t_put,
                    render_ms=1e3 * (t1 - t0),
                    # the process's CPU time (all threads) and the host's steal per CPU meanwhile
                    render_cpu_ms=1e3 * (cpu1 - cpu0),
                    render_steal_ms=_steal_delta(steal0, steal1),
                    x_true=x_true[[0, 2]],
                )
            )
            index += 1
            # the next frame time; frame times that passed while rendering are skipped
            _, now = board.read()
            behind = (
                newest_frame(int(now["step"]), period, exposure_back)
                if int(now["episode"]) == episode
                else 0
            )
            nxt = max(number + 1, behind)
            skipped += nxt - number - 1
            number = nxt
        camera.close()
        out = _stack(rows)
        out["skipped"] = skipped
        out["not_read_out"] = not_read_out
        log_queue.put(out)
    except Exception:  # noqa: BLE001 - reported to the parent, which raises
        log_queue.put({"error": traceback.format_exc()})


def failed_frame_record(row: dict, image, occluded, snapshot: dict, step) -> dict:
    """A frame the real-time eye failed to track, as saved for an offline replay: the eye's
    log ``row`` of it (index, episode, number, times), the ``image`` and ``occluded`` pixels the
    tracker was given, its ``snapshot`` before the frame (``BoxTracker.snapshot``, after the
    frames it never saw were skipped) and what ``step`` (the ``TrackStep``) gave: its
    ``fit_source`` ("" when invalid), validity and estimated centre [m] (camera frame).

    Replayed (:func:`replay_failed_frames`) on a tracker of the run's settings, the update
    gives the same step: the frame's failure can be studied without the real-time run.
    """
    return {
        "row": dict(row),
        "image": np.asarray(image, np.uint8).copy(),
        "occluded": None if occluded is None else np.asarray(occluded, bool).copy(),
        "snapshot": snapshot,
        "fit_source": str(step.fit_source),
        "valid": bool(step.valid),
        "measured_position": np.asarray(step.measured_position, np.float64).copy(),
    }


def failed_frames_file(tracker, frames: list[dict]) -> dict:
    """What ``eye_failed_frames.pkl`` holds: how to build the eye's ``tracker`` again
    (intrinsics, cube edge [m], fps, config, background) and its saved ``frames``
    (:func:`failed_frame_record`).
    """
    return {
        "tracker": {
            "intrinsics": np.asarray(tracker.intrinsics).copy(),
            "size": float(tracker.size),
            "fps": float(tracker.fps),
            "config": tracker.config,
            "background": tracker.given_background,
        },
        "frames": frames,
    }


def replay_failed_frames(saved: dict) -> list:
    """The ``TrackStep`` of each saved frame (:func:`failed_frames_file`) replayed on a tracker
    built as the run's eye, each from its snapshot: the same fits as in the run.
    """
    from hec_jax.geometry import BoxTracker

    t = saved["tracker"]
    tracker = BoxTracker(t["intrinsics"], t["size"], t["fps"], t["config"], t["background"])
    out = []
    for record in saved["frames"]:
        tracker.restore(record["snapshot"])
        out.append(tracker.update(record["image"], record["occluded"]))
    return out


class _MaskCamera:
    """What :func:`hec_jax.loop.camera_loop.mask_robot_and_replaced` reads of a camera: the calibrated pose
    and intrinsics and a model/data pair with the robot's kinematics (no renderer).
    """

    def __init__(self, m, width: int, height: int):
        import mujoco

        from hec_jax.mjx_scene import camera_intrinsics, camera_pose_world

        self.model, self.data = m, mujoco.MjData(m)
        mujoco.mj_kinematics(m, self.data)
        mujoco.mj_camlight(m, self.data)  # the camera's pose (cam_xpos, cam_xmat)
        self.intrinsics = camera_intrinsics(m, "eye", width, height)
        self.world_from_camera = camera_pose_world(m, self.data, "eye")

    def pose_arm(self, qpos_adr, q_arm) -> None:
        import mujoco

        self.data.qpos[qpos_adr] = q_arm
        mujoco.mj_kinematics(self.model, self.data)


def eye_main(
    task,
    cam,
    fps,
    q0,
    camera,
    estimates,
    x64,
    cache_dir,
    *,
    ready,
    stop,
    log_queue,
    priority=0,
    nice=0,
    skip_unseen=True,
    gc_off=False,
    save_failed=0,
):
    """The eye process: the tracker compiled on the release frame, then the newest frames.

    Args:
        task: the :class:`~hec_jax.loop.config.TaskConfig` (the robot's geometry for its mask).
        cam: the :class:`~hec_jax.loop.config.CameraConfig` (tracker, mask, coasting).
        fps: [1/s] the camera's frame rate (the tracker's filter step is 1 / fps).
        q0: (nq,) qpos at the release (the warm-up frame's arm posture).
        camera: a :class:`~hec_jax.realtime.plant.Camera` (with ``release_frame``).
        estimates: the board the estimates go to (``ESTIMATE_FIELDS``).
        x64: JAX in float64 (as the parent).
        cache_dir: JAX's persistent compilation cache (None: none).
        ready: event set once the tracker is compiled.
        stop: event ending the loop.
        log_queue: receives the per-frame log (or ``{"error": ...}``).
        priority: SCHED_FIFO priority once the tracker is compiled (0: none).
        nice: the process's nice value (threads started later inherit it).
        skip_unseen: tell the tracker the frame times it never saw before each frame
            (``BoxTracker.skip``); False: each frame is taken as 1 / fps after the last seen.
        gc_off: Python's garbage collector off while an episode runs, run at each release
            frame instead (a collection in mid-swing delays that frame's estimate).
        save_failed: keep up to this many frames after a release whose tracked fit failed
            (:func:`failed_frame_record`: the image as the tracker saw it, its occluded pixels,
            the tracker's snapshot before it), in the log's ``failed_frames``
            (:func:`failed_frames_file`); 0: none (a snapshot costs a copy of the track per
            frame).
    """
    rows: list[dict] = []
    try:
        os.setpriority(os.PRIO_PROCESS, 0, nice)
        import jax

        jax.config.update("jax_enable_x64", bool(x64))
        if cache_dir:
            jax.config.update("jax_compilation_cache_dir", str(cache_dir))
            jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
        from hec_jax.geometry import BoxTracker
        from hec_jax.geometry.track import FIT_SOURCES
        from hec_jax.loop.camera_loop import front_object_mask, mask_robot_and_replaced, robot_geoms
        from hec_jax.mjx_scene import CUBE_EDGE, scene_ids
        from hec_jax.realtime.clock import host_steal_ms, monotonic_s
        from hec_jax.realtime.plant import camera_model
        from hec_jax.realtime.shared import wait_for

        m, _ = camera_model(task, cam)  # the camera's pose and K: the rendered model's
        ids = scene_ids(m)
        arm = np.array(ids.arm_qpos)
        mcam = _MaskCamera(m, cam.width, cam.height)
        robot = robot_geoms(m, ids.hand_body)
        hand = robot[m.geom_bodyid[robot] == ids.hand_body] if cam.inpaint_hand else ()
        r_wc, t_wc = mcam.world_from_camera

        def masked(image, q_arm, tracker=None):
            """(the eye's image, its occluded pixels or None), as the simulated camera loop."""
            if cam.self_mask_margin_m is None:
                return image, None
            mcam.pose_arm(arm, q_arm)
            keep = None
            if cam.occlusion_aware_mask and tracker is not None:
                ahead = tracker.predict(1.0 / fps)  # this frame (frames never seen: skipped)
                keep = front_object_mask(image.shape, ahead, mcam, hand, mcam.intrinsics, CUBE_EDGE)
            out, replaced = mask_robot_and_replaced(
                image, mcam, robot, cam.self_mask_margin_m, hand, None, keep
            )
            return out, (replaced if cam.mask_aware_coverage else None)

        wait_for(lambda: camera.calibration.ready(1), 300.0, 0.01, "the calibration shots")
        tracker = BoxTracker(mcam.intrinsics, CUBE_EDGE, fps, cam.tracker, camera.background())
        warm, warm_occluded = masked(camera.release_frame(), np.asarray(q0)[arm])
        compiles = CompileMeter().install()
        tracker.warm_up(warm, warm_occluded)  # compile the search, tracking, re-acquisition
        warm_up_compile_ms = compiles.ms
        if priority:
            set_scheduling(os.SCHED_FIFO, priority)
        ready.set()
        last, episode, misses, published, dropped, number = -1, -1, 0, False, 0, -1
        failed: list[dict] = []
        while not stop.is_set():
            frame = camera.latest(last)
            if frame is None:
                time.sleep(_POLL_S)
                continue
            t0, cpu0, steal0 = monotonic_s(), time.process_time(), host_steal_ms()
            compile_ms0, compile_events0 = compiles.ms, compiles.events
            lost = frame.index - last - 1  # frames the camera made that the eye never saw
            dropped += lost
            last = frame.index
            if frame.episode != episode:  # a new release: a new throw for the tracker
                if gc_off:  # between throws: the loop waits for the release frame's answer
                    gc.enable()
                    gc.collect()
                    gc.disable()
                tracker.reset()
                episode, misses, published = frame.episode, 0, False
                # the tracker's frame 0 is the release frame (number 0), whatever came first
                gap = frame.number
            else:
                gap = frame.number - number - 1
            number = frame.number
            # frame times the eye never saw (dropped while it was busy, or not exposed): the
            # tracker's filter predicts over them, so this frame is taken at its own time
            if skip_unseen:
                tracker.skip(max(gap, 0))
            image, occluded = masked(frame.image, frame.q_arm, tracker)
            t_masked = monotonic_s()
            keep = len(failed) < save_failed and number > 0
            before = tracker.snapshot() if keep else None
            st = tracker.update(image, occluded)
            misses = 0 if st.valid else misses + 1
            x = xd = xdd = np.full(2, np.nan)
            if st.initialised:
                x = (r_wc @ np.asarray(st.position) + t_wc)[[0, 2]]
                xd = (r_wc @ np.asarray(st.velocity))[[0, 2]]
                xdd = (r_wc @ np.asarray(st.acceleration))[[0, 2]]
            t1 = monotonic_s()
            # the acquisition frame (0: the release state, the cube still held) is always
            # answered, so the control loop knows the eye is done with it. Written before the
            # frame's bookkeeping (its CPU and steal readings, ~55 us): where the camera shares
            # the eye's CPU (two CPUs) at real-time priority, it preempts the eye from each
            # frame's mid-exposure for a whole render, and an estimate done but not yet written
            # waited for it (13 ms once: docs/realtime.md, session 83)
            t_published = np.nan
            if st.initialised or published or number == 0:
                seen = bool(st.initialised) and misses <= cam.max_coast_frames
                estimates.write(
                    frame=frame.index,
                    episode=episode,
                    number=number,
                    t_stamp=frame.t_exposure,
                    x=_board_vector(x, seen),
                    xd=_board_vector(xd, seen),
                    xdd=_board_vector(xdd, seen),
                    seen=float(seen),
                    valid=float(st.valid),
                    initialised=float(st.initialised),
                    t_wall_exposure=frame.t_wall_exposure,
                    t_wall_done=t1,
                )
                t_published = monotonic_s()
                published = True
            # the frame's CPU time and steal include its publication
            cpu1, steal1 = time.process_time(), host_steal_ms()
            rows.append(
                dict(
                    index=frame.index,
                    episode=episode,
                    number=number,
                    dropped_before=lost,
                    frame_gap=gap,
                    t_exposure=frame.t_exposure,
                    t_wall_exposure=frame.t_wall_exposure,
                    t_wall_start=t0,
                    t_wall_done=t1,
                    # [s] the estimate written to the control loop's board (NaN: not written)
                    t_wall_published=t_published,
                    eye_ms=1e3 * (t1 - t0),
                    # the process's CPU time (all threads) and the host's steal per CPU from
                    # t_wall_start to just after the write (eye_ms ends at t_wall_done)
                    eye_cpu_ms=1e3 * (cpu1 - cpu0),
                    eye_steal_ms=_steal_delta(steal0, steal1),
                    # JAX's tracing and compiling within the frame (first use of a path)
                    jax_compile_ms=compiles.ms - compile_ms0,
                    jax_compile_events=compiles.events - compile_events0,
                    # the eye's stages: the robot's mask, then the tracker's own split
                    mask_ms=1e3 * (t_masked - t0),
                    detection_ms=st.timing_ms["detection_ms"],
                    estimation_ms=st.timing_ms["estimation_ms"],
                    valid=bool(st.valid),
                    initialised=bool(st.initialised),
                    # which of the tracker's hypotheses gave the fit (index into FIT_SOURCES)
                    fit_source=FIT_SOURCES.index(getattr(st, "fit_source", "")),
                    # failed while the filter ran, left to the prediction (defer_search)
                    search_deferred=bool(getattr(st, "search_deferred", False)),
                    # [m, m/s, m/s^2] world (x, z): the tracker's state (NaN before its track
                    # starts), the acceleration too, so that a run's estimates can be replayed;
                    # the board got zeros instead where the object counted as unseen
                    x_est=x,
                    xd_est=xd,
                    xdd_est=xdd,
                )
            )
            if keep and st.fit_source != "tracked":
                failed.append(failed_frame_record(rows[-1], image, occluded, before, st))
        gc.enable()
        out = _stack(rows)
        out["dropped"] = dropped
        out["warm_up_compile_ms"] = warm_up_compile_ms  # the meter heard the warm-up compile
        if save_failed:
            out["failed_frames"] = failed_frames_file(tracker, failed)
        log_queue.put(out)
    except Exception:  # noqa: BLE001 - reported to the parent, which raises
        log_queue.put({"error": traceback.format_exc()})
