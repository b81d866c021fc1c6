"""Deadline report of a real-time run (NumPy boundary): control ticks, the eye, the task.

* Control: per-tick latency from the tick's scheduled start (j dt) to the torques written,
  percentiles p50/p99/p99.9/max and a histogram; the same over every physics step's deadline
  (:func:`deadline_latency`: a skipped step waits for the next tick's torques), on which the
  p99.9 target is judged; the plant's physics steps split into fresh
  (torque from their own sample in time), late (torque after the deadline (j + 1) dt: the held
  one was applied) and skipped (no controller call at all: the loop fell behind); missed
  deadlines = late + skipped. The late count is recomputed from the recorded write times and
  must equal the plant's.
* Why the late ticks were late (:func:`miss_causes`): each one's latency split into its
  wake-up's lateness, the control thread's CPU time up to the torques, and the time it spent
  off the CPU meanwhile; each counted under the part furthest above its median.
* Eye: frames rendered (and exposed late or skipped by the camera), frames the eye processed and
  dropped (latest-frame policy), the latency from a frame's exposure to the tick where its
  estimate becomes the controller's object state, and the age of the state in force at each tick
  (tick time minus the exposure of the estimate in force). The age target needs every tick to
  have a seen estimate in force: a tick after the eye reported the cube lost counts against
  it (``ticks_without_estimate``).
* Task: the run's metrics beside the same run in simulated time (:func:`compare_metrics`).
"""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np

from hec_jax.geometry.track import FIT_SOURCES
from hec_jax.report import markdown_table
from hec_jax.runs import atomic_write_bytes, save_figure, write_json, write_npz

# latency histogram bins [us]: log-spaced from 10 us to 1 s
HIST_EDGES_US = np.concatenate([[0.0], np.logspace(1, 6, 101)])


def percentiles(x, scale: float = 1.0) -> dict:
    """{"p50", "p99", "p99_9", "max", "mean", "n"} of ``x`` * ``scale`` (NaNs dropped)."""
    x = np.asarray(x, float)
    x = x[np.isfinite(x)] * scale
    if x.size == 0:
        return {"p50": None, "p99": None, "p99_9": None, "max": None, "mean": None, "n": 0}
    p = np.percentile(x, [50, 99, 99.9])
    return {
        "p50": float(p[0]),
        "p99": float(p[1]),
        "p99_9": float(p[2]),
        "max": float(x.max()),
        "mean": float(x.mean()),
        "n": int(x.size),
    }


def tick_table(run) -> dict[str, np.ndarray]:
    """The ticks of every episode in one table: ``episode``, ``index`` (sample j), the recorded
    times [s] (from the episode's time 0), ``kind`` (plant: 0 fresh, 1 late, 2 skipped) and,
    where the run recorded it, ``t_origin`` (the episode's time 0 on the monotonic clock [s]).
    """
    origins = getattr(run, "origin_s", [])
    out: dict[str, list] = {}
    for e, rec in enumerate(run.ticks):
        n = len(rec["kind"])
        cols = dict(rec, episode=np.full(n, e), index=np.arange(n))
        if len(origins) == len(run.ticks):
            cols["t_origin"] = np.full(n, float(origins[e]))
        for k, v in cols.items():
            out.setdefault(k, []).append(np.asarray(v)[:n])
    return {k: np.concatenate(v) for k, v in out.items()}


def deadline_latency(tt: dict, dt: float) -> np.ndarray:
    """The latency of every physics step's deadline [s]: from the step's start j dt to the
    torques that answer it. A ticked step: its own torques written (the tick latency). A
    skipped step (no tick computed torques from its sample): the torques of the next tick in
    its episode, and where none came before the episode's end, that end (n dt, a lower bound).

    The issue's target, no missed control deadline at p99.9, is on this (every step, the
    skipped ones included); the tick latency alone leaves out the steps a stall skipped, so
    its p99.9 can be under the period while more than 0.1% of the deadlines were missed. A
    skipped step's latency is at least ``dt`` (held there against rounding).
    """
    index, episode = np.asarray(tt["index"]), np.asarray(tt["episode"])
    t_write = np.asarray(tt["t_write"], float)
    out = t_write - index * dt
    # each row's answer: the next finite t_write at or after it within its episode, else the
    # episode's end in steps (reverse scan; rows are grouped by episode, in time order)
    nxt = np.full(t_write.size, np.nan)
    steps_to_end = np.zeros(t_write.size)
    later, current, end_j = np.nan, None, 0
    for i in range(t_write.size - 1, -1, -1):
        if episode[i] != current:  # the last row of an episode
            current, later, end_j = episode[i], np.nan, int(index[i]) + 1
        if np.isfinite(t_write[i]):
            later = t_write[i]
        nxt[i] = later
        steps_to_end[i] = end_j - int(index[i])
    skipped = ~np.isfinite(t_write)
    waited = np.where(np.isfinite(nxt), nxt - index * dt, steps_to_end * dt)
    # a skipped step missed its deadline: at least one period (not a rounding under it)
    out[skipped] = np.maximum(waited[skipped], dt)
    return out


def deadline_report(run, dt: float, fps: float | None, camera_log=None, eye_log=None) -> dict:
    """The deadline report of a :class:`~hec_jax.realtime.runner.LoopRun` (module docstring).

    Args:
        run: the loop's records.
        dt: [s] control period.
        fps: [1/s] the camera's frame rate (None: no camera).
        camera_log: the camera's per-frame log (None: no camera).
        eye_log: the eye's per-frame log (None: no camera).
    """
    tt = tick_table(run)
    t_sched = tt["index"] * dt
    ticked = np.isfinite(tt["t_write"])
    lat = (tt["t_write"] - t_sched)[ticked]
    kind = tt["kind"]
    # late: torques taken at or after the deadline (j + 1) dt (the plant's own comparison)
    late_recorded = int(np.sum(tt["t_write"][ticked] >= (tt["index"][ticked] + 1) * dt))
    counts = {
        "steps": int(kind.size),
        "ticks": int(ticked.sum()),
        "fresh": int(np.sum(kind == 0)),
        "late": int(np.sum(kind == 1)),
        "skipped": int(np.sum(kind == 2)),
    }
    counts["missed"] = counts["late"] + counts["skipped"]
    counts["late_from_recorded_times"] = late_recorded
    counts["consistent"] = bool(
        counts["fresh"] + counts["late"] + counts["skipped"] == counts["steps"]
        and counts["fresh"] + counts["late"] == counts["ticks"]
        and late_recorded == counts["late"]
    )
    hist, _ = np.histogram(lat * 1e6, HIST_EDGES_US)
    control = {
        "period_us": dt * 1e6,
        "counts": counts,
        "missed_fraction": counts["missed"] / max(counts["steps"], 1),
        "latency_us": percentiles(lat, 1e6),
        # every physics step's deadline, the skipped steps included (the target's measure)
        "deadline_latency_us": percentiles(deadline_latency(tt, dt), 1e6),
        # from the step the clock waited for (t_due; records before it: the row's own step)
        "wake_jitter_us": percentiles((tt["t_wake"] - tt.get("t_due", t_sched))[ticked], 1e6),
        "observe_us": percentiles((tt["t_obs"] - tt["t_wake"])[ticked], 1e6),
        "step_us": percentiles((tt["t_step"] - tt["t_obs"])[ticked], 1e6),
        "write_us": percentiles((tt["t_write"] - tt["t_step"])[ticked], 1e6),
        "histogram": {"edges_us": HIST_EDGES_US.tolist(), "counts": hist.tolist()},
    }
    if "cpu_step" in tt:
        control["cpu"] = cpu_report(tt, ticked)
        control["miss_causes"] = miss_causes(tt, dt)
    p999 = control["deadline_latency_us"]["p99_9"]
    p999_ticks = control["latency_us"]["p99_9"]
    targets = {
        # the issue's: over every step's deadline (a skipped step is a missed deadline)
        "p99_9_deadline_within_period": bool(p999 is not None and p999 < dt * 1e6),
        # over the ticks alone, as reported up to session 55 (leaves out the skipped steps)
        "p99_9_tick_latency_within_period": bool(p999_ticks is not None and p999_ticks < dt * 1e6),
        "no_missed_deadline": counts["missed"] == 0,
    }
    report = {"control": control, "targets": targets}
    if fps is not None:
        report["eye"] = eye_report(run, tt, dt, fps, camera_log, eye_log)
        age_max = report["eye"]["age_ms"]["max"]
        # a tick with no seen estimate in force (the eye reported the cube lost) has no eye
        # state at all: it fails the target, it is not left out of it
        report["eye"]["ticks_without_estimate"] = int((ticked & ~np.isfinite(tt["t_stamp"])).sum())
        targets["eye_age_within_two_frame_periods"] = bool(
            age_max is not None
            and age_max <= 2e3 / fps
            and report["eye"]["ticks_without_estimate"] == 0
        )
    return report


CPU_STAGES = ("cpu_read", "cpu_observe", "cpu_step", "cpu_write")


def cpu_report(tt: dict, ticked: np.ndarray) -> dict:
    """Per-stage CPU time of the control thread [us] (percentiles over the ticks), their sum per
    tick, the CPU time of the process's other threads during the tick's work (mean), and the control
    thread's context switches per tick (mean; voluntary: waits, involuntary: preemptions).
    CPU time counts only the time the thread ran, so it does not grow with the time other
    processes hold the CPU (it does grow with the cache misses they cause).
    """
    out = {k[4:] + "_us": percentiles(tt[k][ticked], 1e-3) for k in CPU_STAGES}
    total = sum(tt[k][ticked] for k in CPU_STAGES)
    out["tick_us"] = percentiles(total, 1e-3)
    # a mean: the kernel brings other threads' CPU times up to date only at their switches
    other = tt["cpu_other_threads"][ticked]
    out["other_threads_mean_us"] = float(np.mean(other) * 1e-3) if other.size else None
    for k in ("switches_voluntary", "switches_involuntary"):
        out[f"{k}_per_tick"] = float(np.mean(tt[k][ticked])) if ticked.any() else None
    if "faults_major" in tt:  # runs recorded since 2026-12-04
        out["faults"] = page_faults(tt, ticked)
    return out


def page_faults(tt: dict, ticked: np.ndarray) -> dict:
    """The control thread's page faults over the run (each tick's count spans the previous
    tick's torques to its own): ``major`` and ``minor`` totals, ``ticks_with_major``, and
    ``missed_events_with_major``: runs of missed steps (:func:`missed_runs_ended_by`) whose
    first tick's count has a major fault, i.e. one fell between the last tick before the run
    and the torques of its first tick. A major fault waits for a read from disk (a code page or
    mapped file the kernel had dropped), typically 0.1-10 ms.
    """
    major = np.where(ticked, tt["faults_major"], 0)
    ended_by = missed_runs_ended_by(tt, ticked)
    with_major = int(np.sum((ended_by >= 0) & (major[np.maximum(ended_by, 0)] > 0)))
    return {
        "major": int(major.sum()),
        "minor": int(np.where(ticked, tt["faults_minor"], 0).sum()),
        "ticks_with_major": int((major > 0).sum()),
        "missed_events_with_major": int(with_major),
    }


# the parts of a tick's latency (:func:`miss_causes`)
MISS_CAUSES = ("woke_late", "cpu_work", "off_cpu")
# the control thread's CPU stages on the path to the torques (the write takes them at its start)
PATH_STAGES = ("cpu_read", "cpu_observe", "cpu_step")


def latency_parts(tt: dict, dt: float) -> dict[str, np.ndarray]:
    """Each tick's latency [s] (NaN where no tick) as the sum of three parts.

    * ``woke_late``: the wake-up after the time the clock waited for, t_wake - t_due (the
      clock's wait, the kernel's and the host's scheduling, or the previous tick still
      running). Runs recorded before ``t_due`` existed (2026-12-04) use the row's own j dt;
    * ``cpu_work``: the control thread's CPU time from the wake-up to the torques (plant read,
      observation, jitted step). In a virtual machine this includes any time the host takes
      the virtual CPU away without the guest accounting it as steal: a tick whose CPU time is
      several times the usual may have done no more work. After a stall it also holds the
      simulated plant's integration of the steps whose deadline passed (``MujocoPlant.read``
      catches up before the sample);
    * ``off_cpu``: the rest of that stretch, t_write - t_wake - cpu_work: the thread not
      running (preempted, by the host's hypervisor or a thread of higher priority, or waiting
      for XLA's threads), plus the few microseconds of the clock reads.

    A tick's row is the sample the plant returned (j). After a stall the plant catches up on
    the skipped steps and j is later than the step the clock waited for: the three parts then
    sum to t_write - t_due, the stall from the first skipped step's deadline on (that step's
    deadline latency), not to the row's own latency t_write - j dt; a thread that woke that
    late has ``woke_late`` the size of the stall. Without ``t_due`` such a stall was not
    seen in ``woke_late`` and the catch-up's integration counted as ``cpu_work``.
    """
    due = tt["t_due"] if "t_due" in tt else tt["index"] * dt
    woke = tt["t_wake"] - due
    cpu = sum(tt[k] for k in PATH_STAGES) * 1e-9
    return {"woke_late": woke, "cpu_work": cpu, "off_cpu": tt["t_write"] - tt["t_wake"] - cpu}


def miss_causes(tt: dict, dt: float) -> dict:
    """Why the late ticks (torques taken at or after the deadline (j + 1) dt) were late.

    Each late tick's latency is split by :func:`latency_parts`, and the tick is counted under
    the part that exceeds that part's median over all ticks by the most. One stall of the
    thread makes several misses in a row (the ticks after it wake late, steps are skipped), so
    the misses are also grouped into events: runs of consecutive missed steps (late or skipped,
    ``tt["kind"]`` 1 or 2) of one episode, each counted under the cause of the tick that ended
    its first stall: its first tick, late or, after skipped steps only, on time for its own
    step. With ``t_due`` that tick's parts span the stall from the step it waited for, so a
    thread that woke late, ran long or was held off the CPU before the plant's read is told
    apart. Runs recorded without ``t_due`` count an event with no late tick as ``woke_late``
    (the records cannot tell those three apart) and give an event that starts with a late
    tick that tick's cause, whose parts leave out the skipped steps' stretch.

    Returns ``late`` (count), ``counts`` {cause: late ticks}, ``events`` (count),
    ``event_counts`` {cause: events}, ``late_us`` {cause: percentiles over the late ticks [us]}
    and ``median_us`` {cause: median over all ticks [us]}.
    """
    ticked = np.isfinite(tt["t_write"])
    parts = latency_parts(tt, dt)
    late = ticked & (tt["t_write"] >= (tt["index"] + 1) * dt)
    median = {k: float(np.median(parts[k][ticked])) if ticked.any() else 0.0 for k in parts}
    excess_all = np.stack([np.where(ticked, parts[k] - median[k], -np.inf) for k in MISS_CAUSES])
    excess = np.where(late, excess_all, -np.inf)
    cause = np.where(late, np.argmax(excess, axis=0), -1)
    has_due = "t_due" in tt
    event_cause = []
    for row in missed_runs_ended_by(tt, ticked):
        if row >= 0 and (late[row] or has_due):
            event_cause.append(int(np.argmax(excess_all[:, row])))
        else:
            event_cause.append(0)
    event_cause = np.asarray(event_cause, int)
    return {
        "late": int(late.sum()),
        "counts": {k: int(np.sum(cause == i)) for i, k in enumerate(MISS_CAUSES)},
        "events": int(event_cause.size),
        "event_counts": {k: int(np.sum(event_cause == i)) for i, k in enumerate(MISS_CAUSES)},
        "late_us": {k: percentiles(parts[k][late], 1e6) for k in MISS_CAUSES},
        "median_us": {k: median[k] * 1e6 for k in MISS_CAUSES},
    }


def missed_runs_ended_by(tt: dict, ticked: np.ndarray) -> np.ndarray:
    """The runs of consecutive missed steps (plant ``kind`` 1 late or 2 skipped) within an
    episode, one entry each: the row of the tick that ended the run's first stall, i.e. the
    first tick of the episode from the run's start on (late, or on time for its own step after
    skipped steps); -1 where the episode ended first.
    """
    missed = np.asarray(tt["kind"]) != 0
    episode = np.asarray(tt.get("episode", np.zeros(missed.size, int)))
    continues = np.zeros(missed.size, bool)
    continues[1:] = missed[:-1] & (episode[1:] == episode[:-1])
    out = []
    for a in np.flatnonzero(missed & ~continues):
        rows = a + np.flatnonzero(ticked[a:] & (episode[a:] == episode[a]))
        out.append(int(rows[0]) if rows.size else -1)
    return np.asarray(out, int)


def in_contact(run, tt: dict) -> np.ndarray | None:
    """Per row of ``tt``: the hand touched the object during that physics step (a non-zero
    contact force in the episode's log); None without the logs' ``f_contact``.
    """
    logs = getattr(run, "logs", None)
    if not logs or any("f_contact" not in lg for lg in logs):
        return None
    flags = []  # tick_table's rows: episode by episode, samples 0 .. n - 1
    for e, lg in enumerate(logs):
        n = int(np.sum(tt["episode"] == e))
        touched = np.any(np.asarray(lg["f_contact"]) != 0, axis=-1)[:n]
        flags.append(np.pad(touched, (0, n - len(touched))))
    return np.concatenate(flags).astype(bool)


def measured_age(run, tt: dict, dt: float) -> np.ndarray | None:
    """Per tick [s]: the tick's time minus the exposure of the last frame whose own fit passed
    (``valid``) among the estimates the control loop has taken in the episode; NaN before the
    first. Beside the age of the state in force, which a coasted prediction (a failed frame
    published on time) renews: this one only a measurement renews, and a lost eye (no estimate
    in force) does not hide it. None for runs whose arrivals lack ``valid`` (before 2026-11-27).
    """
    if not run.arrivals or "valid" not in run.arrivals[0]:
        return None
    out = []
    for e, a in enumerate(run.arrivals):
        n = int(np.sum(tt["episode"] == e))
        ok = (a["valid"] > 0) & (a["number"] > 0)  # the release frame: the cube still held
        ticks, stamps = a["tick"][ok].astype(int), a["t_stamp"][ok]
        j = np.arange(n)
        last = np.searchsorted(ticks, j, side="right") - 1
        out.append(np.where(last >= 0, j * dt - stamps[np.maximum(last, 0)], np.nan))
    return np.concatenate(out) if out else np.zeros(0)


def eye_report(run, tt: dict, dt: float, fps: float, camera_log, eye_log) -> dict:
    """The eye's part of :func:`deadline_report`."""
    arr = {k: np.concatenate([a[k] for a in run.arrivals]) for k in run.arrivals[0]}
    # latencies of the frames exposed after the release (frame 0 is answered before it)
    seen = (arr["seen"] > 0) & (arr["number"] > 0)
    period_steps = int(round(1.0 / (fps * dt)))
    expected = int(sum(-(-len(rec["kind"]) // period_steps) for rec in run.ticks))
    out = {
        "fps": fps,
        "frame_period_ms": 1e3 / fps,
        "frames_expected": expected,
        "estimates_taken": int(len(arr["tick"])),
        "estimates_seen": int(seen.sum()),
        # exposure (plant time) -> the tick whose control step first uses the estimate
        "latency_ms": percentiles((arr["t_tick"] - arr["t_stamp"])[seen], 1e3),
        # the same on the wall clock: exposure -> taken by the control loop
        "latency_wall_ms": percentiles((arr["t_wall_taken"] - arr["t_wall_exposure"])[seen], 1e3),
        # exposure -> the eye's estimate published (render + eye)
        "pipeline_wall_ms": percentiles((arr["t_wall_done"] - arr["t_wall_exposure"])[seen], 1e3),
        # the eye done with a frame -> its estimate taken by the control loop (the write to the
        # board, then the loop's next tick; a preempted eye's write waits longer)
        "done_to_taken_ms": percentiles((arr["t_wall_taken"] - arr["t_wall_done"])[seen], 1e3),
        "age_ms": percentiles(tt["index"] * dt - tt["t_stamp"], 1e3),
        "ticks_with_estimate": int(np.isfinite(tt["t_stamp"]).sum()),
    }
    measured = measured_age(run, tt, dt)
    if measured is not None:
        # information beside the target: the age of the last measurement behind the state
        out["age_measured_ms"] = percentiles(measured, 1e3)
    # the same over the ticks whose physics step had no hand-object contact: in contact the
    # controller takes the object's state from touch (object_state.touch_object_state), not
    # the eye. Information beside the target, which counts every tick.
    contact = in_contact(run, tt)
    if contact is not None:
        age = (tt["index"] * dt - tt["t_stamp"])[~contact]
        out["age_out_of_contact_ms"] = percentiles(age, 1e3)
        out["ticks_in_contact"] = int(contact.sum())
    # where the state was oldest, and what the estimate that ended it spent its time on
    out["oldest_state"] = oldest_state(run, tt, dt, camera_log, eye_log)
    if camera_log:
        late = camera_log["step"] - camera_log["step_due"]
        out["camera"] = {
            "frames_rendered": int(len(camera_log["index"])),
            "frames_exposed_late": int(np.sum(late > 0)),
            "exposure_delay_ms": percentiles(late, 1e3 * dt),
            "frame_times_skipped": int(camera_log["skipped"]),
            "render_ms": percentiles(camera_log["render_ms"]),
        }
        if "t_wall_put" in camera_log:  # logs since session 79
            # held after rendering until the exposure's end (a renderer faster than half the
            # exposure), and rendered frames whose exposure would have ended after their episode
            out["camera"]["readout_wait_ms"] = percentiles(
                camera_log["t_wall_put"] - camera_log["t_wall_done"], 1e3
            )
            out["camera"]["frames_not_read_out"] = int(camera_log["not_read_out"])
        if "render_cpu_ms" in camera_log:  # logs since session 26
            out["camera"]["render_cpu_ms"] = percentiles(camera_log["render_cpu_ms"])
            out["camera"]["render_steal_ms_per_cpu"] = _steal_total(camera_log["render_steal_ms"])
            by_second = render_cpu_by_second(camera_log)
            if by_second is not None:
                out["camera"]["render_cpu_ms_per_second"] = by_second
    if eye_log:
        out["eye"] = {
            "frames_processed": int(len(eye_log["index"])),
            # rendered frames the eye skipped for a newer one (up to its last processed one,
            # those before its first included)
            "frames_dropped": int(eye_log["dropped"]),
            "frames_valid": int(np.sum(eye_log["valid"])),
            # failed while the filter ran and left to the prediction (TrackConfig.defer_search)
            "frames_search_deferred": int(np.sum(eye_log.get("search_deferred", 0))),
            # frames after the release; the release frames' search from scratch apart
            "eye_ms": percentiles(eye_log["eye_ms"][eye_log["number"] > 0]),
            "acquisition_ms": percentiles(eye_log["eye_ms"][eye_log["number"] == 0]),
        }
        if camera_log and len(eye_log["index"]):
            # rendered after the eye's last processed frame: the run ended before it took them
            after = camera_log["index"] > np.max(eye_log["index"])
            out["eye"]["frames_after_last_processed"] = int(np.sum(after))
        for stage in ("mask_ms", "detection_ms", "estimation_ms"):  # logs since session 20
            if stage in eye_log:
                out["eye"][stage] = percentiles(eye_log[stage][eye_log["number"] > 0])
        if "fit_source" in eye_log:  # logs since session 21
            # which hypothesis gave each frame's fit after the release (a failed tracked fit
            # recovered within its frame shows as "stopped", "local" or "local_turned")
            later = eye_log["fit_source"][eye_log["number"] > 0]
            out["eye"]["fits_by_source"] = {
                name or "invalid": int(np.sum(later == i)) for i, name in enumerate(FIT_SOURCES)
            }
        if "eye_cpu_ms" in eye_log:  # logs since session 26
            later = eye_log["number"] > 0
            out["eye"]["eye_cpu_ms"] = percentiles(eye_log["eye_cpu_ms"][later])
            out["eye"]["eye_steal_ms_per_cpu"] = _steal_total(eye_log["eye_steal_ms"])
            out["slow_frames"] = slow_frames(camera_log, eye_log, 1e3 / fps, ticks=tt, dt=dt)
        if "t_wall_published" in eye_log:  # logs since session 83
            # the eye done with a frame -> its estimate written to the board
            later = eye_log["number"] > 0
            published = eye_log["t_wall_published"] - eye_log["t_wall_done"]
            out["eye"]["publish_ms"] = percentiles(published[later], 1e3)
        if "jax_compile_ms" in eye_log:  # logs since session 47
            # frames in which JAX traced or compiled (a path's first use after the warm-up)
            traced = eye_log["jax_compile_events"] > 0
            out["eye"]["frames_compiling"] = int(np.sum(traced))
            out["eye"]["compile_ms_total"] = float(np.sum(eye_log["jax_compile_ms"]))
            out["eye"]["warm_up_compile_ms"] = float(eye_log["warm_up_compile_ms"])
        if camera_log:
            # accuracy of the eye at its frames against the rendered truth
            truth = dict(zip(camera_log["index"].tolist(), camera_log["x_true"], strict=True))
            err = [
                x - truth[int(i)]
                for i, x in zip(eye_log["index"], eye_log["x_est"], strict=True)
                if int(i) in truth and np.all(np.isfinite(x))
            ]
            if err:
                out["eye"]["position_rms_m"] = float(np.sqrt(np.mean(np.square(err))))
    return out


def render_cpu_by_second(camera_log, min_frames: int = 5) -> dict | None:
    """:func:`~.clock.speed_summary` of the render's CPU time [ms], its median over each whole
    second of wall time (``t_wall_start``) holding at least ``min_frames`` frames: the camera's
    CPU speed over the run. A render does about the same work every frame, so a spread here is
    the CPU's (docs/realtime.md, "CPUs whose speed wanders"; on the 2-core VM the eye's tracked
    frames followed it with correlation 0.87-0.98). None: no such second.
    """
    from hec_jax.realtime.clock import speed_summary

    t = np.asarray(camera_log["t_wall_start"], float)
    cpu = np.asarray(camera_log["render_cpu_ms"], float)
    if t.size == 0:
        return None
    second = np.floor(t - t[0]).astype(int)
    medians = [
        float(np.median(cpu[second == k]))
        for k in np.unique(second)
        if np.sum(second == k) >= min_frames
    ]
    return speed_summary(medians) if medians else None


def _steal_total(per_frame) -> list[float] | None:
    """[ms] per CPU: the host's steal summed over the frames' rows whose readings did not fail
    (None: not recorded).
    """
    a = np.asarray(per_frame, float)
    return np.nansum(a, axis=0).tolist() if a.ndim == 2 and a.shape[1] else None


def control_misses_between(ticks: dict, dt: float, t0: float, t1: float) -> tuple[int, float]:
    """The control loop's missed steps (plant ``kind`` late or skipped) whose deadline, wall
    time ``t_origin`` + (j + 1) dt, falls in [``t0``, ``t1``] (monotonic [s]): their count and
    the longest run of consecutive ones [ms]. A frame slowed while the control thread, alone on
    its own CPU, missed deadlines too was slowed by the machine (both CPUs stalled at once), not
    by the eye's own work.
    """
    deadline = ticks["t_origin"] + (ticks["index"] + 1) * dt
    hit = np.flatnonzero((ticks["kind"] != 0) & (deadline >= t0) & (deadline <= t1))
    if hit.size == 0:
        return 0, 0.0
    # consecutive steps of one episode are consecutive rows of the table
    breaks = np.flatnonzero(np.diff(hit) != 1)
    lengths = np.diff(np.concatenate([[0], breaks + 1, [hit.size]]))
    return int(hit.size), float(lengths.max() * dt * 1e3)


def slow_frames(
    camera_log, eye_log, period_ms: float, limit: int = 32, ticks=None, dt: float | None = None
) -> dict:
    """The frames after a release whose estimate was published more than one frame period
    after their exposure (wall clock): the ones that can age the state past two frame periods.
    For each (the first ``limit``): where the time went, wall [ms] against the process's CPU
    time [ms] and the host's steal [ms] per CPU, for the render and for the eye, and the fit's
    source. A stage whose wall time far exceeds its usual with steal on its CPU was slowed by
    the machine's host; one whose CPU time grew did more work (or ran on a slower CPU).

    With ``ticks`` (:func:`tick_table` with ``t_origin``) and ``dt`` [s], each row also gets
    :func:`control_misses_between` over the frame's exposure to its estimate
    (``control_missed``, ``control_longest_miss_ms``), and ``with_control_missed`` counts the
    slow frames (all of them) during which the control loop missed a deadline too.
    """
    later = eye_log["number"] > 0
    pipeline = 1e3 * (eye_log["t_wall_done"] - eye_log["t_wall_exposure"])
    slow = np.flatnonzero(later & (pipeline > period_ms))
    timed = ticks is not None and dt is not None and "t_origin" in ticks
    misses = {
        int(k): control_misses_between(
            ticks, dt, float(eye_log["t_wall_exposure"][k]), float(eye_log["t_wall_done"][k])
        )
        for k in (slow if timed else [])
    }
    render = {}
    if camera_log and "render_cpu_ms" in camera_log:
        for j, i in enumerate(camera_log["index"].tolist()):
            render[i] = (
                float(camera_log["render_ms"][j]),
                float(camera_log["render_cpu_ms"][j]),
                np.asarray(camera_log["render_steal_ms"][j], float).tolist(),
            )
    rows = []
    for k in slow[:limit]:
        r = render.get(int(eye_log["index"][k]), (None, None, None))
        src = int(eye_log["fit_source"][k]) if "fit_source" in eye_log else None
        rows.append(
            {
                "index": int(eye_log["index"][k]),
                "episode": int(eye_log["episode"][k]),
                "number": int(eye_log["number"][k]),
                "pipeline_ms": float(pipeline[k]),
                "render_ms": r[0],
                "render_cpu_ms": r[1],
                "render_steal_ms": r[2],
                "eye_ms": float(eye_log["eye_ms"][k]),
                "eye_cpu_ms": float(eye_log["eye_cpu_ms"][k]),
                "eye_steal_ms": np.asarray(eye_log["eye_steal_ms"][k], float).tolist(),
                "fit_source": None if src is None else (FIT_SOURCES[src] or "invalid"),
            }
        )
        if "jax_compile_ms" in eye_log:
            rows[-1]["jax_compile_ms"] = float(eye_log["jax_compile_ms"][k])
        if timed:
            rows[-1]["control_missed"], rows[-1]["control_longest_miss_ms"] = misses[int(k)]
    out = {"over_one_period": int(slow.size), "frames": rows}
    if timed:
        out["with_control_missed"] = sum(m[0] > 0 for m in misses.values())
    return out


def oldest_state(run, tt: dict, dt: float, camera_log=None, eye_log=None) -> dict | None:
    """Where the eye's state was oldest: the tick with the largest age of the estimate in force
    (the maximum of ``age_ms``, the first where tied) and the estimate that ended that stretch
    (the first the control loop took after it in its episode), with that estimate's time from
    its exposure to its taking split into stages [ms] on the wall clock: the render's start
    after the exposure, the render, read out and queued until the eye took the frame, the eye
    (its wall and CPU time, and the renders of later frames that ran meanwhile: on two CPUs
    the camera preempts the eye), and done to taken (``done_to_written_ms`` where the log has
    the write's time). The stages add up to ``latency_ms``. With ``t_origin`` in ``tt``, the
    control loop's missed steps between the eye's done and the taking (a stalled loop takes
    the estimate late) and during the whole latency. Where the logs have the CPU times, the
    CPU's speed then: ``eye_cpu_vs_median``, the eye's CPU time on the frame over the median of
    the run's frames with the same fit source (None where fewer than 5 have it), and
    ``render_cpu_vs_median``, the render CPU times of the frame and the next (frame index + 1;
    at an episode's last frame the next episode's first) over the run's median render (a
    render is the same work every frame: well above 1, the CPU ran slow; an eye ratio well
    above 1 with renders near 1, the eye had more to do). ``ended_by`` is None where no
    estimate came after the tick (the episode ended first), and the stages are left out where
    the camera's or the eye's log lacks the frame. None: no tick had an estimate in force.
    """
    age = tt["index"] * dt - tt["t_stamp"]
    if not np.isfinite(age).any():
        return None
    k = int(np.nanargmax(age))
    e, j = int(tt["episode"][k]), int(tt["index"][k])
    out = {"episode": e, "tick": j, "age_ms": float(1e3 * age[k])}
    contact = in_contact(run, tt)
    if contact is not None:
        out["in_contact"] = bool(contact[k])
    a = run.arrivals[e]
    after = np.flatnonzero(a["tick"] > j)
    if after.size == 0:
        out["ended_by"] = None
        return out
    m = int(after[0])
    exposure, done = float(a["t_wall_exposure"][m]), float(a["t_wall_done"][m])
    taken = float(a["t_wall_taken"][m])
    ended = {
        "frame": int(a["frame"][m]),
        "number": int(a["number"][m]),
        "tick": int(a["tick"][m]),
        "valid": bool(a["valid"][m]) if "valid" in a else None,
        "latency_ms": 1e3 * (taken - exposure),
        "done_to_taken_ms": 1e3 * (taken - done),
    }
    if "t_origin" in tt:
        ended["control_missed_done_to_taken"] = control_misses_between(tt, dt, done, taken)[0]
        ended["control_missed_in_latency"] = control_misses_between(tt, dt, exposure, taken)[0]
    frame = ended["frame"]
    cam = _row_of(camera_log, frame)
    eye = _row_of(eye_log, frame)
    if cam is not None and eye is not None and "t_wall_put" in camera_log:
        c_start, c_done = camera_log["t_wall_start"], camera_log["t_wall_done"]
        e_start, e_done = float(eye_log["t_wall_start"][eye]), float(eye_log["t_wall_done"][eye])
        # the renders that ran while the eye worked on the frame (of later frames: its own
        # ended before the eye took it)
        overlap = np.clip(np.minimum(c_done, e_done) - np.maximum(c_start, e_start), 0, None)
        ended["stages_ms"] = {
            "to_render": 1e3 * (float(c_start[cam]) - exposure),
            "render": 1e3 * (float(c_done[cam]) - float(c_start[cam])),
            "read_out_and_queued": 1e3 * (e_start - float(c_done[cam])),
            "eye": 1e3 * (e_done - e_start),
            "done_to_taken": ended["done_to_taken_ms"],
        }
        if "eye_cpu_ms" in eye_log:
            ended["eye_cpu_ms"] = float(eye_log["eye_cpu_ms"][eye])
        ended["renders_during_eye_ms"] = float(1e3 * np.sum(overlap))
        if "fit_source" in eye_log:
            ended["fit_source"] = FIT_SOURCES[int(eye_log["fit_source"][eye])] or "invalid"
            if "eye_cpu_ms" in eye_log:
                # against the run's frames with the same fit source: the eye's work or its CPU
                same = np.asarray(eye_log["fit_source"]) == eye_log["fit_source"][eye]
                ended["eye_cpu_vs_median"] = _over_median(eye_log["eye_cpu_ms"], same, eye)
        if "render_cpu_ms" in camera_log:
            # the CPU's speed then: a render is the same work every frame, so its CPU time
            # against the run's median tells a slow CPU from an eye with more to do; the
            # frame's own render and the next frame's (None where the log lacks it)
            everything = np.ones(len(camera_log["render_cpu_ms"]), bool)
            ended["render_cpu_vs_median"] = [
                None if row is None else _over_median(camera_log["render_cpu_ms"], everything, row)
                for row in (cam, _row_of(camera_log, frame + 1))
            ]
        if "t_wall_published" in eye_log:
            ended["done_to_written_ms"] = 1e3 * (float(eye_log["t_wall_published"][eye]) - done)
    out["ended_by"] = ended
    return out


def oldest_text(eye: dict) -> str:
    """One line of :func:`oldest_state` (``eye["oldest_state"]``) for the report's table."""
    o = eye["oldest_state"]
    where = f"episode {o['episode']}, step {o['tick']}: {o['age_ms']:.0f} ms"
    if "in_contact" in o:
        where += " (in contact)" if o["in_contact"] else " (out of contact)"
    b = o.get("ended_by")
    if b is None:
        return where + "; no estimate after it in the episode"
    text = (
        f"{where}; frame {b['number']}'s estimate, taken {b['latency_ms']:.1f} ms after its "
        "exposure"
    )
    st = b.get("stages_ms")
    if st is not None:
        eye_part = f"eye {st['eye']:.1f}"
        extras = []
        if "eye_cpu_ms" in b:
            cpu = f"CPU {b['eye_cpu_ms']:.1f}"
            if b.get("eye_cpu_vs_median") is not None:
                cpu += f", {b['eye_cpu_vs_median']:.2f}x the median of its fit source"
            extras.append(cpu)
        extras.append(f"later renders in it {b['renders_during_eye_ms']:.1f}")
        if "fit_source" in b:
            extras.append(b["fit_source"])
        eye_part += f" ({'; '.join(extras)})"
        text += (
            f": to render {st['to_render']:.1f} + render {st['render']:.1f} + read out and "
            f"queued {st['read_out_and_queued']:.1f} + {eye_part} + done to taken "
            f"{st['done_to_taken']:.1f}"
        )
    else:
        text += f"; done to taken {b['done_to_taken_ms']:.1f}"
    notes = []
    if "done_to_written_ms" in b:
        notes.append(f"written {b['done_to_written_ms']:.2f} ms after done")
    if "control_missed_done_to_taken" in b:
        notes.append(f"control steps missed meanwhile {b['control_missed_done_to_taken']}")
    ratios = b.get("render_cpu_vs_median")
    if ratios is not None:
        shown = " / ".join("-" if r is None else f"{r:.2f}x" for r in ratios)
        notes.append(f"render CPU this frame's / the next's {shown} the median")
    return text + (f" ({'; '.join(notes)})" if notes else "")


_MEDIAN_OF_AT_LEAST = 5  # frames behind a median that a frame's CPU time is held against


def _over_median(values, among, row: int) -> float | None:
    """``values[row]`` over the median of ``values[among]``; None where ``among`` holds fewer
    than ``_MEDIAN_OF_AT_LEAST`` values (a frame against itself and a few others says little)
    or the median is not positive.
    """
    chosen = np.asarray(values, np.float64)[among]
    if chosen.size < _MEDIAN_OF_AT_LEAST:
        return None
    median = float(np.median(chosen))
    return float(values[row]) / median if median > 0 else None


def _row_of(log, frame: int) -> int | None:
    """The row of the camera's or eye's log holding frame ``frame`` (its ``index``), or None."""
    if not log or "index" not in log:
        return None
    rows = np.flatnonzero(np.asarray(log["index"]) == frame)
    return int(rows[0]) if rows.size else None


_COMPARED = ("peak_force", "settle_force", "hits", "periodic_hits")


def compare_metrics(
    realtime: dict, simulated: dict, tolerance: float = 0.2, scales: dict | None = None
) -> dict:
    """{metric: {"realtime", "simulated", "ratio", "rel_diff", "within"}} for the metrics both
    have (means over seeds: peak and settle force for catching, hits for hitting).
    ``rel_diff``: |real time - simulated| / ``scales[metric]`` where given (e.g. the settle
    force against F_cd: a cube dropped in both runs settles at 0 in both), else / |simulated|;
    ``within``: ``rel_diff`` <= ``tolerance``.
    """
    scales = {} if scales is None else scales
    out = {}
    for key in _COMPARED:
        a, b = realtime.get(key), simulated.get(key)
        if not (isinstance(a, dict) and isinstance(b, dict)):
            continue
        a, b = a["mean"], b["mean"]
        scale = scales.get(key, abs(b))
        rel = abs(a - b) / scale if scale else None
        out[key] = {
            "realtime": a,
            "simulated": b,
            "ratio": a / b if b else None,
            "rel_diff": rel,
            "within": bool(rel is not None and rel <= tolerance),
        }
    for key in ("held_every_seed",):
        if key in realtime and key in simulated:
            out[key] = {"realtime": realtime[key], "simulated": simulated[key]}
    return out


def deadline_table(report: dict) -> list[str]:
    """Markdown lines of the deadline table (control latency, misses, eye)."""
    c = report["control"]
    lat, n = c["latency_us"], c["counts"]

    def us(v):
        return "-" if v is None else f"{v:.0f}"

    rows = [
        ("control ticks / physics steps", f"{n['ticks']} / {n['steps']}"),
        (
            "tick latency p50 / p99 / p99.9 / max [us]",
            " / ".join(us(lat[k]) for k in ("p50", "p99", "p99_9", "max")),
        ),
        (
            "deadline latency, every step (skipped: to the next torques) p50 / p99 / p99.9 / max [us]",
            " / ".join(us(c["deadline_latency_us"][k]) for k in ("p50", "p99", "p99_9", "max")),
        ),
        (
            "missed 1 ms deadlines (late + skipped)",
            f"{n['missed']} ({n['late']} + {n['skipped']}), "
            f"{100 * c['missed_fraction']:.3f}% of steps",
        ),
        (
            "  of which: wake jitter p99.9 / step p99.9 [us]",
            f"{us(c['wake_jitter_us']['p99_9'])} / {us(c['step_us']['p99_9'])}",
        ),
    ]
    cpu = c.get("cpu")
    if cpu:
        stages = ("read", "observe", "step", "write", "tick")
        causes = c.get("miss_causes")
        if causes:
            n_c, n_e = causes["counts"], causes["event_counts"]
            rows += [
                (
                    "late ticks by cause: woke late / CPU work / off the CPU",
                    " / ".join(str(n_c[k]) for k in MISS_CAUSES) + f" (of {causes['late']})",
                ),
                (
                    "runs of missed steps by the cause of their first tick (timed from the "
                    "step it waited for, where recorded)",
                    " / ".join(str(n_e[k]) for k in MISS_CAUSES) + f" (of {causes['events']})",
                ),
            ]
        rows += [
            (
                "control thread CPU p50 [us]: " + " / ".join(stages),
                " / ".join(us(cpu[f"{k}_us"]["p50"]) for k in stages),
            ),
            (
                "other threads' CPU mean [us] per tick; context switches per tick (vol., invol.)",
                f"{us(cpu['other_threads_mean_us'])}; "
                f"{cpu['switches_voluntary_per_tick']:.2f}, "
                f"{cpu['switches_involuntary_per_tick']:.2f}",
            ),
        ]
        faults = cpu.get("faults")
        if faults:
            rows.append(
                (
                    "control thread page faults: major / minor; ticks with a major one; "
                    "runs of missed steps with one",
                    f"{faults['major']} / {faults['minor']}; {faults['ticks_with_major']}; "
                    f"{faults['missed_events_with_major']}"
                    + (f" (of {causes['events']})" if causes else ""),
                )
            )
    eye = report.get("eye")
    if eye:

        def ms(d, digits: int = 1):
            return " / ".join(
                "-" if d[k] is None else f"{d[k]:.{digits}f}" for k in ("p50", "p99", "max")
            )

        rows += [
            ("eye latency exposure -> state p50 / p99 / max [ms]", ms(eye["latency_ms"])),
            (
                f"eye state age p50 / p99 / max [ms] (2 frames = {2 * eye['frame_period_ms']:.1f})",
                ms(eye["age_ms"]),
            ),
        ]
        if "age_out_of_contact_ms" in eye:
            rows.append(
                (
                    "... out of contact (state from the eye, not touch) p50 / p99 / max [ms]",
                    ms(eye["age_out_of_contact_ms"]),
                )
            )
        if "age_measured_ms" in eye:
            rows.append(
                (
                    "... of the last valid fit behind it p50 / p99 / max [ms]",
                    ms(eye["age_measured_ms"]),
                )
            )
        if eye.get("oldest_state") is not None:
            rows.append(
                ("eye state age's maximum, and the estimate that ended it", oldest_text(eye))
            )
        if "camera" in eye:
            cam = eye["camera"]
            rows += [
                (
                    "frames rendered / expected, exposed late, frame times skipped",
                    f"{cam['frames_rendered']} / {eye['frames_expected']}, "
                    f"{cam['frames_exposed_late']}, {cam['frame_times_skipped']}",
                ),
                ("render p50 / p99 / max [ms]", ms(cam["render_ms"])),
            ]
            if "readout_wait_ms" in cam:
                rows.append(
                    (
                        "held for the exposure's end p50 / p99 / max [ms]; not read out",
                        f"{ms(cam['readout_wait_ms'])}; {cam['frames_not_read_out']}",
                    )
                )
            if "render_cpu_ms" in cam:
                rows.append(("render process CPU p50 / p99 / max [ms]", ms(cam["render_cpu_ms"])))
            if "render_cpu_ms_per_second" in cam:  # the camera CPU's speed over the run
                r = cam["render_cpu_ms_per_second"]
                rows.append(
                    (
                        "render CPU, median per second: min / p50 / max [ms] (max / min)",
                        f"{r['min']:.1f} / {r['p50']:.1f} / {r['max']:.1f} "
                        f"({r['max_over_min']:.2f})",
                    )
                )
        if "eye" in eye:
            e = eye["eye"]
            rows += [
                (
                    "frames processed by the eye / dropped / valid / search deferred",
                    f"{e['frames_processed']} / {e['frames_dropped']} / {e['frames_valid']}"
                    f" / {e.get('frames_search_deferred', '-')}",
                ),
                (
                    "frames rendered after the eye's last (the run ended first)",
                    str(e.get("frames_after_last_processed", "-")),
                ),
                ("eye p50 / p99 / max [ms]", ms(e["eye_ms"])),
            ]
            if "eye_cpu_ms" in e:
                rows.append(("eye process CPU p50 / p99 / max [ms]", ms(e["eye_cpu_ms"])))
            if "publish_ms" in e:  # logs since session 83
                rows.append(
                    (
                        "eye done -> estimate written; -> taken by the loop p50 / p99 / max [ms]",
                        f"{ms(e['publish_ms'], 3)}; {ms(eye['done_to_taken_ms'])}",
                    )
                )
            elif "done_to_taken_ms" in eye:
                rows.append(
                    (
                        "eye done -> estimate taken by the loop p50 / p99 / max [ms]",
                        ms(eye["done_to_taken_ms"]),
                    )
                )
            if "mask_ms" in e:
                rows.append(
                    (
                        "... of which p50: mask / detection / estimation [ms]",
                        " / ".join(
                            "-" if e[k]["p50"] is None else f"{e[k]['p50']:.1f}"
                            for k in ("mask_ms", "detection_ms", "estimation_ms")
                        ),
                    )
                )
            slow = eye.get("slow_frames")
            if slow is not None:
                frames = slow["frames"]
                steal = sum(
                    sum(f["render_steal_ms"] or []) + sum(f["eye_steal_ms"]) for f in frames
                )
                rows.append(
                    (
                        "frames published > 1 frame period after exposure; host steal in their "
                        "render + eye [ms]",
                        f"{slow['over_one_period']}; {steal:.0f}",
                    )
                )
                if "with_control_missed" in slow:
                    longest = max((f["control_longest_miss_ms"] for f in frames), default=0.0)
                    rows.append(
                        (
                            "... of them with the control loop (its own CPU) missing deadlines "
                            "meanwhile; its longest miss [ms]",
                            f"{slow['with_control_missed']}; {longest:.0f}",
                        )
                    )
            if "fits_by_source" in e:
                by = e["fits_by_source"]
                rows.append(
                    (
                        "eye fits after the release: " + " / ".join(by),
                        " / ".join(str(v) for v in by.values()),
                    )
                )
    host = report.get("host")
    if host and host.get("steal_ms_per_cpu") is not None:
        rows.append(
            (
                "host steal over the run, per CPU [ms]",
                " / ".join(f"{v:.0f}" for v in host["steal_ms_per_cpu"]),
            )
        )
    rescue = (report.get("placement") or {}).get("pool_rescue")
    if rescue:
        rows.append(
            (
                f"pool under SCHED_IDLE, rescued after {rescue['after_us']:.0f} us: "
                "rescues / ms rescued / watchdog alive to the end",
                f"{rescue['rescues']} / {rescue['rescued_ms']:.1f} / {rescue['alive_to_the_end']}",
            )
        )
    return markdown_table(["quantity", "value"], rows)


def comparison_table(comparison: dict) -> list[str]:
    """Markdown lines: each compared metric, real time against each simulated twin."""
    rows = []
    for twin, comp in comparison.items():
        for key, v in comp.items():
            if "ratio" in v:
                ratio = "-" if v["ratio"] is None else f"{v['ratio']:.3f}"
                rel = "-" if v["rel_diff"] is None else f"{100 * v['rel_diff']:.1f}%"
                rows.append(
                    (
                        f"{key} (vs {twin})",
                        f"{v['realtime']:.4g}",
                        f"{v['simulated']:.4g}",
                        ratio,
                        f"{rel} ({'within' if v['within'] else 'outside'} 20%)",
                    )
                )
            else:
                rows.append((f"{key} (vs {twin})", v["realtime"], v["simulated"], "-", "-"))
    header = ["metric", "real time", "simulated time", "ratio", "difference"]
    return markdown_table(header, rows)


def write_report(folder: Path, result) -> None:
    """``deadline.json``, ``metrics.json`` (the run's task metrics, the twins', the ratios),
    ``deadline_histogram.png``, ``ticks.npz`` (every tick's recorded times, to recompute the
    report), with the camera ``eye_frames.npz`` (per frame: camera, eye, estimates taken) and,
    when the eye saved them, ``eye_failed_frames.pkl`` (``RealtimeConfig.eye_save_failed``), and
    ``trajectory_realtime.npz``/``trajectory_simulated_<twin>.npz``, into ``folder``.
    """
    from hec_jax.loop.report import save_trajectories

    folder = Path(folder)
    report = dict(result.report, load_average=result.load)
    write_json(folder / "deadline.json", report)
    write_json(
        folder / "metrics.json",
        {
            "condition": result.realtime.condition,
            "realtime": result.metrics,
            "simulated": {k: v["metrics"] for k, v in result.twins.items()},
            "simulated_wall_s": {k: v["wall_s"] for k, v in result.twins.items()},
            # [s] the camera twin's eye latency after the exposure's end, and whence
            **(
                {
                    "simulated_camera_latency": {
                        "latency_s": result.twins["camera"]["latency_s"],
                        "source": result.twins["camera"]["latency_source"],
                    }
                }
                if "camera" in result.twins
                else {}
            ),
            "comparison": result.comparison,
            "targets": dict(
                report["targets"],
                **{
                    f"task_metrics_within_20pct_of_{twin}": all(
                        v["within"] for v in comp.values() if "within" in v
                    )
                    for twin, comp in result.comparison.items()
                },
            ),
        },
    )
    write_npz(folder / "ticks.npz", **tick_table(result.loop_run))
    if result.eye_log:  # per frame: the camera's, the eye's, and the estimates the loop took
        arrivals = result.loop_run.arrivals
        write_npz(
            folder / "eye_frames.npz",
            **{f"camera_{k}": np.asarray(v) for k, v in result.camera_log.items()},
            **{f"eye_{k}": np.asarray(v) for k, v in result.eye_log.items()},
            **{f"taken_{k}": np.concatenate([a[k] for a in arrivals]) for k in arrivals[0]},
        )
    if result.eye_failed_frames is not None:  # the eye's failed frames, for a replay
        atomic_write_bytes(folder / "eye_failed_frames.pkl", pickle.dumps(result.eye_failed_frames))
    final = result.config.task.final_s > 0
    logs = {
        "realtime": result.logs,
        **{f"simulated_{k}": v["logs"] for k, v in result.twins.items()},
    }
    if final:
        logs = {k: v["final"] for k, v in logs.items()}
    save_trajectories(folder, logs, result.dt)
    histogram_figure(folder / "deadline_histogram.png", result)


def histogram_figure(path: Path, result) -> None:
    """Tick latency histogram (log counts, the 1 ms deadline marked) and, with the camera, the
    eye's latency and the age of its state.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tt = tick_table(result.loop_run)
    dt = result.dt
    ticked = np.isfinite(tt["t_write"])
    lat_us = (tt["t_write"] - tt["index"] * dt)[ticked] * 1e6
    eye = "eye" in result.report
    fig, axes = plt.subplots(1, 2 if eye else 1, figsize=(11 if eye else 6, 4), squeeze=False)
    ax = axes[0, 0]
    ax.hist(lat_us, bins=HIST_EDGES_US[1:], color="C0")
    ax.axvline(dt * 1e6, color="C3", ls="--", label=f"deadline {dt * 1e3:g} ms")
    lat = result.report["control"]["latency_us"]
    for k, ls in (("p50", ":"), ("p99_9", "-.")):
        ax.axvline(lat[k], color="k", ls=ls, label=f"{k.replace('_', '.')} {lat[k]:.0f} us")
    every = result.report["control"]["deadline_latency_us"]["p99_9"]
    ax.axvline(every, color="C1", ls="-.", label=f"p99.9 of every step (the target) {every:.0f} us")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("tick latency: scheduled start -> torques written [us]")
    ax.set_ylabel("ticks")
    n = result.report["control"]["counts"]
    ax.set_title(f"{n['ticks']} ticks, {n['missed']} missed deadlines")
    ax.legend(fontsize=8)
    if eye:
        ax = axes[0, 1]
        age = (tt["index"] * dt - tt["t_stamp"]) * 1e3
        age = age[np.isfinite(age)]
        arr = {k: np.concatenate([a[k] for a in result.loop_run.arrivals]) for k in ("t_tick",)}
        arr["t_stamp"] = np.concatenate([a["t_stamp"] for a in result.loop_run.arrivals])
        seen = np.concatenate([a["seen"] for a in result.loop_run.arrivals]) > 0
        seen &= np.concatenate([a["number"] for a in result.loop_run.arrivals]) > 0
        latency = (arr["t_tick"] - arr["t_stamp"])[seen] * 1e3
        bins = np.logspace(0, np.log10(max(age.max(initial=10), latency.max(initial=10)) * 1.1), 80)
        ax.hist(age, bins=bins, alpha=0.6, label="age of the state at each tick")
        ax.hist(latency, bins=bins, alpha=0.6, label="exposure -> state (per frame)")
        fp = result.report["eye"]["frame_period_ms"]
        ax.axvline(2 * fp, color="C3", ls="--", label=f"two frame periods {2 * fp:.1f} ms")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("[ms]")
        ax.set_ylabel("ticks / frames")
        ax.set_title("the eye's state")
        ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path)
    plt.close(fig)


def print_report(result) -> None:
    """The deadline table, the task metrics against simulated time, the targets."""
    print("\n".join(deadline_table(result.report)))
    print()
    print("\n".join(comparison_table(result.comparison)))
    if "camera" in result.twins:
        twin = result.twins["camera"]
        print(
            f"camera twin: its estimates used {1e3 * twin['latency_s']:.1f} ms after the "
            f"exposure's end ({twin['latency_source']})"
        )
    print()
    print("targets:", result.report["targets"])
    print("load average (1, 5, 15 min):", result.load)
