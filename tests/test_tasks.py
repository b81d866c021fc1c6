"""The closed loop of the experiments (MJX world + impedance hand + online learner), short runs."""

import jax
import numpy as np
import pytest

from hec_jax import loop as tl
from hec_jax.loop import metrics as mt
from hec_jax.mjx_scene import default_conditions
from hec_jax.nets import LearnerConfig


@pytest.fixture(scope="module")
def catching_logs():
    """3 swings of 0.9 s (contact at ~0.58 s), 1 seed, all three conditions, one compile."""
    config = tl.TaskConfig(
        learner=LearnerConfig(task="catching", r_b=0.085, eta=(0.3,) * 3, contact_stiffness=1e5),
        swing_s=0.9,
        swings=3,
    )
    logs, _ = tl.run_conditions(tl.build_loop(config), default_conditions(), seed=0, n_seeds=1)
    return logs


def test_contact_events():
    f = np.zeros(100)
    f[10:13] = 5.0
    f[15:17] = 3.0  # chatter within min_gap: the same event
    f[60:70] = 1.0
    assert mt.contact_events(f, 0.5, min_gap=5) == [(10, 17), (60, 70)]
    assert mt.contact_events(np.zeros(10), 0.5, min_gap=5) == []


def test_catching_loop_learns_to_soften_the_impact(catching_logs):
    peak = {c: mt.force_norm(lg)[0].max(-1) for c, lg in catching_logs.items()}  # per swing
    # Without learning every swing is the same (the world restarts at the same release).
    np.testing.assert_allclose(peak["plain"], peak["plain"][0], rtol=1e-9)
    np.testing.assert_allclose(peak["frozen"], peak["frozen"][0], rtol=1e-9)
    assert peak["plain"][0] > 100.0  # a hard impact at ~1 m/s
    # Learning lowers the peak force below both baselines already within these swings.
    assert peak["learned"][-1] < 0.8 * min(peak["plain"][0], peak["frozen"][0])
    # Strict Eq. 49 at every sample, and the plain condition has no virtual force at all.
    assert mt.stability_summary(catching_logs["learned"])["all_strictly_stable"]
    assert np.all(catching_logs["plain"]["f_o"] == 0.0)
    assert np.all(np.isfinite(catching_logs["learned"]["x_e"]))


def test_learning_only_inside_the_sphere(catching_logs):
    lg = catching_logs["learned"]
    assert np.any(lg["learning"])
    assert not np.any(lg["learning"] & ~lg["inside"])
    assert not np.any(catching_logs["frozen"]["learning"])


def test_switches_reject_unknown_condition():
    with pytest.raises(ValueError, match="condition"):
        tl.switches("bogus")
    assert jax.tree_util.tree_leaves(tl.switches("plain"))[0].shape == ()


def test_hit_series_periodic_run_and_bounded_pulses():
    dt = 1e-3
    f = np.zeros(14000)
    starts = [500, 1900, 3300, 4700, 6100, 7500, 10500]  # 6 hits 1.4 s apart, then a late one
    for k, s in enumerate(starts):
        f[s : s + 10] = 50.0 - 5.0 * k  # 10 ms pulses, shrinking
    h = mt.hit_series(f, dt, threshold=1e-3)
    assert h["hits"] == 7
    assert h["periodic_hits"] == 6 and h["series_first_hit"] == 0
    np.testing.assert_allclose(h["median_interval_s"], 1.4)
    assert h["pulses_bounded"] and h["pulse_growth"] == 1.0
    np.testing.assert_allclose(h["max_pulse_duration_s"], 0.010)
    f[6100:6110] = 80.0  # a pulse above the first: the strikes build up, not bounded
    assert not mt.hit_series(f, dt, threshold=1e-3)["pulses_bounded"]
    assert mt.hit_series(np.zeros(100), dt, 1e-3)["periodic_hits"] == 0


def test_settle_metrics():
    f = np.zeros(3000)
    f[400:] = 2.1
    f[400:450] = 100.0  # the impact
    m = mt.settle_metrics(f, 2.0, threshold=1e-3, tail=500)
    assert m["held"] and m["contacts"] == 1
    np.testing.assert_allclose(m["settle_force"], 2.1)
    np.testing.assert_allclose(m["settle_rel_error"], 0.05)
    f[1000:1300] = 0.0  # the object leaves the hand and strikes again
    assert not mt.settle_metrics(f, 2.0, threshold=1e-3, tail=500)["held"]


def test_hold_point_is_the_static_catch():
    """F_cd -> 0: the hand touches the hanging cube (hinge x + half cube + hand radius); the hold
    point moves toward the arriving cube as F_cd grows, by L_c sin(theta) with
    F_cd L_c = (m_c L_c + m_rod L / 2) g sin(theta)."""
    pendulum = default_conditions(hinge_x=0.55)
    x0 = tl.hold_point(0.0, pendulum, k_e=400.0)
    np.testing.assert_allclose(x0, [0.55 + 0.05 + 0.04, 1.25 - 0.65], atol=1e-12)
    m_rod = 7850.0 * np.pi * 0.003**2 * 0.6
    s = 2.0 * 0.65 / ((0.7 * 0.65 + m_rod * 0.3) * 9.81)
    x2 = tl.hold_point(2.0, pendulum, k_e=1e12)  # rigid hand: no spring deflection
    cube = np.array([0.55 - 0.65 * s, 1.25 - 0.65 * np.sqrt(1 - s**2)])
    np.testing.assert_allclose(np.linalg.norm(x2 - cube), 0.09, atol=1e-9)
    assert x2[0] < x0[0] - 0.15


def test_task_contact_parameters_reach_the_model_only():
    from hec_jax.mjx_scene import load_mjx_model

    lc = LearnerConfig(task="hitting")
    loop = tl.build_loop(tl.TaskConfig(learner=lc, contact_solref=(0.025, 0.2)))
    np.testing.assert_allclose(np.asarray(loop.mx.pair_solref), [[0.025, 0.2]])
    np.testing.assert_allclose(np.asarray(load_mjx_model().pair_solref), [[0.005, 1.0]])
    default = tl.build_loop(tl.TaskConfig(learner=lc))
    np.testing.assert_allclose(np.asarray(default.mx.pair_solref), [[0.005, 1.0]])


@pytest.mark.parametrize("field", ["swing_s", "settle_s", "final_s"])
def test_durations_under_half_a_control_step_are_refused(field):
    """A duration that rounds to 0 control steps (dt = 1 ms) would give an empty swing, a settle
    mean over the whole swing (f[-0:]) or an empty continuous run: refused when the loop is
    built. 0.6 ms rounds to one step and is taken."""
    short = {field: 0.0004} | ({"settle_s": 0.0004} if field == "swing_s" else {})
    with pytest.raises(ValueError, match=f"{field} .* under half a control step"):
        tl.build_loop(tl.TaskConfig(**short))
    assert tl.build_loop(tl.TaskConfig(swing_s=0.6e-3, settle_s=0.6e-3)).swing_steps == 1


def test_hinge_position_is_a_swept_condition():
    """The hinge x is a pytree leaf of the conditions: moving it moves the released cube by the
    same amount, inside one compiled function (vmap over two hinges)."""
    loop = tl.build_loop(tl.TaskConfig(swings=1))

    def cube_x(hinge_x):
        c = default_conditions()._replace(hinge_x=hinge_x)
        m = loop.model_for(c)
        return loop.data_for(m, c).xpos[loop.ids.cube_body, 0]

    x = jax.jit(jax.vmap(cube_x))(np.array([0.35, 0.55]))
    np.testing.assert_allclose(x[1] - x[0], 0.2, atol=1e-12)


def test_config_fields_are_validated():
    with pytest.raises(ValueError, match="swings"):
        tl.TaskConfig(swings=0)
    with pytest.raises(ValueError, match="swing_s"):
        tl.TaskConfig(swing_s=float("nan"))
    with pytest.raises(ValueError, match="seeds"):
        tl.ExperimentConfig(seeds=0)
    with pytest.raises(ValueError, match="cube_mass"):
        tl.replace(tl.catching(), cube_mass=-1.0)
    with pytest.raises(ValueError, match="must occur once"):
        tl.replace(tl.catching(), nonexistent=1.0)
    exp = tl.replace(tl.catching(), swings=3, mu=2e-3)
    assert exp.task.swings == 3 and exp.task.learner.mu == 2e-3


def test_catching_metrics_of_a_seed_without_contact_are_values_not_errors():
    """A learned hand that never touches the cube in one seed: the metrics say so (None values,
    a count), the others are averaged over the seeds that have them, and the targets compute."""
    seeds, swings, steps = 2, 2, 1000
    f = np.zeros((seeds, swings, steps, 3))
    f[0, :, 300:, 0] = 2.0  # seed 0 caught and holds with 2 N; seed 1 never touches
    f[0, :, 300:310, 0] = 50.0
    logs = {
        "f_contact": f,
        "inside": np.ones((seeds, swings, steps), bool),
        "xd_o": np.ones((seeds, swings, steps, 2)),
        "xd_e": np.zeros((seeds, swings, steps, 2)),
        "margins": np.ones((seeds, swings, steps, 2, 3)),
    }
    m = mt.catching_condition_metrics(logs, "learned", 2.0, 200, 1e-3, 1e-3)
    assert m["seeds_without_contact"] == 1
    assert m["per_seed"][1]["relative_speed_at_contact"] is None
    np.testing.assert_allclose(m["relative_speed_at_contact"]["mean"], np.sqrt(2.0))
    assert not m["held_every_seed"]


def test_catching_contact_speeds_use_the_simulators_object_velocity():
    """With a camera the controller's X_o' is the eye's estimate; the contact-speed metrics take
    the simulator's, so runs with different eyes compare the same quantity. Here the cube moves
    at 1 m/s, the estimate says 0.5 m/s and the hand moves at 0.5 m/s: the hand lags by 0.5 m/s
    and follows at half the cube's speed (the estimate would say 0 and 1)."""
    seeds, swings, steps = 1, 1, 1000
    f = np.zeros((seeds, swings, steps, 3))
    f[0, 0, 300:, 0] = 2.0
    shape = (seeds, swings, steps, 2)
    logs = {
        "f_contact": f,
        "inside": np.ones((seeds, swings, steps), bool),
        "xd_o": np.broadcast_to([0.5, 0.0], shape),
        "xd_o_true": np.broadcast_to([1.0, 0.0], shape),
        "xd_e": np.broadcast_to([0.5, 0.0], shape),
        "margins": np.ones((seeds, swings, steps, 2, 3)),
    }
    m = mt.catching_swing_metrics(logs, 0, 0, 2.0, 200, 1e-3, 1e-3)
    assert m["relative_speed_at_contact"] == pytest.approx(0.5)
    assert m["object_speed_at_contact"] == pytest.approx(1.0)
    assert m["hand_follow_ratio"] == pytest.approx(0.5)
    del logs["xd_o_true"]  # logs without the simulator's velocity: the logged one
    assert mt.catching_swing_metrics(logs, 0, 0, 2.0, 200, 1e-3, 1e-3)[
        "relative_speed_at_contact"
    ] == pytest.approx(0.0)
