"""The closed loop of the experiments (MJX world + impedance hand + online learner), short runs."""

import jax
import numpy as np
import pytest

from experiments import task_loop as tl
from hec_jax.mjx_scene import default_conditions
from hec_jax.nets import LearnerConfig


@pytest.fixture(scope="module")
def catching_logs():
    """3 swings of 0.9 s (contact at ~0.58 s), 1 seed, all three conditions, one compile."""
    config = tl.TaskConfig(
        learner=LearnerConfig(task="catching", r_b=0.085, eta=(0.3,) * 3, contact_stiffness=1e5),
        swing_steps=900,
        swings=3,
    )
    logs, _ = tl.run_conditions(config, default_conditions(), seed=0, n_seeds=1)
    return logs


def test_contact_events():
    f = np.zeros(100)
    f[10:13] = 5.0
    f[15:17] = 3.0  # chatter within min_gap: the same event
    f[60:70] = 1.0
    assert tl.contact_events(f, 0.5, min_gap=5) == [(10, 17), (60, 70)]
    assert tl.contact_events(np.zeros(10), 0.5, min_gap=5) == []


def test_catching_loop_learns_to_soften_the_impact(catching_logs):
    peak = {c: tl.force_norm(lg)[0].max(-1) for c, lg in catching_logs.items()}  # per swing
    # Without learning every swing is the same (the world restarts at the same release).
    np.testing.assert_allclose(peak["plain"], peak["plain"][0], rtol=1e-9)
    np.testing.assert_allclose(peak["frozen"], peak["frozen"][0], rtol=1e-9)
    assert peak["plain"][0] > 100.0  # a hard impact at ~1 m/s
    # Learning lowers the peak force below both baselines already within these swings.
    assert peak["learned"][-1] < 0.8 * min(peak["plain"][0], peak["frozen"][0])
    # Strict Eq. 49 at every sample, and the plain condition has no virtual force at all.
    assert tl.stability_summary(catching_logs["learned"])["all_strictly_stable"]
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
