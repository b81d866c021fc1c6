"""The paper protocol (issue 23): presets, condition draws, the metrics the paper cares about on
synthetic traces with known answers, the ablation switches, and the fixed-impedance baseline.
"""

import dataclasses
import json

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from hec_jax import loop as tl
from hec_jax.loop import arms
from hec_jax.loop import paper_metrics as pm
from hec_jax.loop.config import catching_paper, hitting_paper
from hec_jax.loop.policy import rest_touch_point, switches
from hec_jax.loop.protocol import (
    HELD_OUT_SEED_OFFSET,
    ConditionRange,
    draw_conditions,
    make_protocol,
)
from hec_jax.mjx_scene import CUBE_EDGE, HAND_RADIUS, PendulumConfig, load_mj_model
from hec_jax.nets import LearnerConfig, LearnerInputs, NetConfig, SphereGeometry, task_energy
from hec_jax.nets import impedance_nets as nets

DT = 1e-3


def test_draws_lie_in_their_ranges_and_held_out_never_repeats_training():
    r = ConditionRange()
    base = PendulumConfig(hinge_x=0.55)
    train = draw_conditions(r, base, 50, 0)
    held = draw_conditions(r, base, 50, HELD_OUT_SEED_OFFSET)
    again = draw_conditions(r, base, 50, 0)
    for name in ("release_angle", "arrival_phase", "cube_mass"):
        lo, hi = getattr(r, f"{name}_range")
        v = np.asarray(getattr(train, name))
        assert np.all((v >= lo) & (v <= hi)) and np.ptp(v) > 0.5 * (hi - lo)
        assert not np.intersect1d(v, np.asarray(getattr(held, name))).size
        np.testing.assert_array_equal(v, np.asarray(getattr(again, name)))  # same seed
    np.testing.assert_array_equal(np.asarray(train.rod_length), 0.6)  # the preset's
    np.testing.assert_array_equal(np.asarray(train.hinge_x), 0.55)
    with pytest.raises(ValueError, match="release_angle_range"):
        ConditionRange(release_angle_range=(0.1, -0.1))


def test_rest_touch_point_touches_the_hanging_cube_in_mujoco():
    """Independent of the formula: MuJoCo's own geometry at the pendulum's rest."""
    m = load_mj_model()
    pend = PendulumConfig(hinge_x=0.55).conditions()
    x = rest_touch_point(pend, m)
    d = mujoco.MjData(m)
    m.body_pos[m.body_parentid[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "rod")]][0] = 0.55
    mujoco.mj_forward(m, d)
    cube = d.xpos[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "cube")]
    # the hand centre lies half a cube plus the hand radius beyond the cube's +x face centre
    np.testing.assert_allclose(x, [cube[0] + CUBE_EDGE / 2 + HAND_RADIUS, cube[2]], atol=1e-9)


def test_released_cube_starts_outside_the_virtual_sphere():
    """The paper preset's point: t_c falls during the swing (the cube enters from outside)."""
    exp = catching_paper()
    x_home = rest_touch_point(exp.task.pendulum.conditions())
    r = exp.task.learner.radius
    hinge = np.array([0.55, 1.25])
    l_c = 0.6 + CUBE_EDGE / 2
    for angle in ConditionRange().release_angle_range:
        cube = hinge + l_c * np.array([np.sin(angle), -np.cos(angle)])
        assert np.linalg.norm(cube - x_home) > r + 0.05


def test_paper_presets_share_hand_contact_and_learner():
    c, h = catching_paper().task, hitting_paper().task
    assert c.contact_solref == h.contact_solref and c.home == h.home == "rest_touch"
    assert c.learner.contact_stiffness == h.learner.contact_stiffness
    assert all(e > 0 for e in c.learner.eta) and c.learner.net.neutral_init
    assert c.x_home is None and c.object_accel_tau_s > 0


def test_neutral_initial_networks_output_zero():
    u = nets.u_max(NetConfig(), jnp.ones(2), 40 * jnp.ones(2), 400 * jnp.ones(2))
    x = jax.random.normal(jax.random.PRNGKey(1), (2, 4))

    def outputs(neutral, seed, zero_weights=False):
        p = nets.init_params(jax.random.PRNGKey(seed), NetConfig(neutral_init=neutral), jnp.float64)
        if zero_weights:
            p["output"] = dict(p["output"], weight=jnp.zeros_like(p["output"]["weight"]))
        return np.asarray(nets.apply(p, NetConfig(), x, u) / (u / 2))

    # Without the random output weights: Eq. 51 with bias 0 gives (U/2) tanh(-theta/2), about
    # -0.05 U/2 (an attractive virtual spring); the neutral bias gives exactly 0.
    np.testing.assert_allclose(outputs(False, 0, True), np.tanh(-0.05), rtol=1e-12)
    np.testing.assert_allclose(outputs(True, 0, True), 0.0, atol=1e-15)
    # With them (std 0.01), over 20 initialisations: centred on those values.
    printed = np.mean([outputs(False, s) for s in range(20)])
    neutral = np.mean([outputs(True, s) for s in range(20)])
    assert abs(printed - np.tanh(-0.05)) < 0.01 and abs(neutral) < 0.01


def _inputs(x_o, xd_o, in_contact=False):
    z = jnp.zeros(2)
    return LearnerInputs(z, z, z, x_o, xd_o, z, z, jnp.asarray(in_contact), SphereGeometry(z, z, z))


def test_gain_off_is_constant_alpha_zero_and_beta_minus_one():
    x_o, xd_o, xd_e = jnp.array([0.15, 0.0]), jnp.array([-1.0, 0.2]), jnp.array([0.3, -0.1])
    latched = jnp.array([-2.0, 0.5])
    base = dict(radius=0.25, r_b=0.085, mu=0.0)
    for task, expected in (
        ("catching", 0.5 * np.sum((0 * latched - (xd_o - xd_e)) ** 2)),
        ("hitting", 0.5 * np.sum((-1.0 * xd_o - xd_e) ** 2)),
    ):
        cfg = LearnerConfig(task=task, gain="off", **base)
        e = task_energy(cfg, jnp.zeros(2), xd_e, _inputs(x_o, xd_o), latched)
        np.testing.assert_allclose(e, expected, rtol=1e-12)
        paper = task_energy(
            LearnerConfig(task=task, **base), jnp.zeros(2), xd_e, _inputs(x_o, xd_o), latched
        )
        assert abs(float(paper) - expected) > 1e-3  # the distance shaping matters here
    with pytest.raises(ValueError, match="gain"):
        LearnerConfig(gain="none")


def _catch_log(f, xd_o, xd_e, inside=None):
    n = f.shape[0]
    fc = np.zeros((n, 3))
    fc[:, 0] = f
    log = {"f_contact": fc, "xd_o_true": xd_o, "xd_e": xd_e}
    if inside is not None:
        log["inside"] = inside
    return log


def test_catching_metrics_on_a_known_trace():
    n, f_cd = 3000, 2.0
    f = np.zeros(n)
    f[1000:1010] = 80.0  # impact
    f[1010:1400] = 5.0  # overshoot after the transient (1200..1400: 2.5 F_cd)
    f[1400:] = 2.1  # within 20% from 1400 on
    xd_o = np.tile([1.0, 0.0], (n, 1))
    xd_e = np.tile([0.25, 0.0], (n, 1))
    inside = np.arange(n) >= 700
    m = pm.catching_run_metrics(_catch_log(f, xd_o, xd_e, inside), DT, f_cd, 1e-3, 0.5)
    assert m["contact"] and m["held"]
    assert m["t_c_s"] == pytest.approx(0.7)
    assert m["relative_speed_at_contact"] == pytest.approx(0.75)
    assert m["peak_force"] == 80.0
    assert m["overshoot_over_f_cd"] == pytest.approx(2.5)
    assert m["time_to_f_cd_s"] == pytest.approx(0.4)
    assert m["settle_force"] == pytest.approx(2.1)
    # a bounce (second contact) is not held; the force enters the band to stay only after it
    f2 = f.copy()
    f2[1500:1600] = 0.0
    m2 = pm.catching_run_metrics(_catch_log(f2, xd_o, xd_e), DT, f_cd, 1e-3, 0.5)
    assert not m2["held"] and m2["time_to_f_cd_s"] == pytest.approx(0.6)
    none = pm.catching_run_metrics(_catch_log(np.zeros(n), xd_o, xd_e), DT, f_cd, 1e-3, 0.5)
    assert not none["contact"] and none["relative_speed_at_contact"] is None


def test_hitting_metrics_on_a_known_trace():
    n = 8000
    f = np.zeros(n)
    speed = np.zeros(n)
    starts = [1000, 2000, 3000, 4000, 5000]
    for k, s in enumerate(starts):  # five periodic hits, approach 1.0, 0.9, ... 0.6 m/s
        f[s : s + 10] = 50.0 + k
        speed[s - 30 : s] = 1.0 - 0.1 * k
        speed[s + 10 : s + 40] = 0.5
    log = {
        "f_contact": np.stack([f, 0 * f, 0 * f], 1),
        "xd_o_true": np.stack([speed, 0 * speed], 1),
    }
    m = pm.task_run_metrics("hitting", log, DT, 5.0, 1e-3, 0.5)
    assert m["hits"] == 5 and m["periodic_hits"] == 5
    np.testing.assert_allclose(m["approach_speeds"], [1.0, 0.9, 0.8, 0.7, 0.6])
    assert m["sustained"] == pytest.approx(0.6)
    assert m["max_pulse"] == 54.0 and m["pulse_over_f_hd"] == pytest.approx(54.0 / 5.0)
    np.testing.assert_allclose(m["speed_gain"], [0.5 - (1.0 - 0.1 * k) for k in range(5)])
    with pytest.raises(ValueError, match="'catching' or 'hitting', got 'catch'"):
        pm.task_run_metrics("catch", log, DT, 5.0, 1e-3, 0.5)  # not taken for hitting


def test_summary_counts_missing_values_and_fractions():
    runs = [{"a": 1.0, "b": True}, {"a": None, "b": False}, {"a": 3.0, "b": True}]
    s = pm.summarize(runs, ("a", "b"))
    assert s["a"] == {"mean": 2.0, "std": 1.0, "n": 2} and s["runs"] == 3
    assert s["b"]["fraction"] == pytest.approx(2 / 3)


def test_fixed_candidates_stay_inside_the_networks_output_range():
    task = catching_paper().task
    cand = arms.fixed_candidates(task, 5, 3)
    imp = task.impedance
    u = np.asarray(nets.u_max(task.learner.net, *(np.asarray(v) for v in imp.__dict__.values())))
    assert cand.shape == (75, 2, 3)
    assert np.all(np.abs(cand) <= 0.9 * u / 2 + 1e-12)
    assert np.all(cand[:, :, 0] + np.asarray(imp.k_e) > 0)  # Eq. 49 (strict) for every one
    # plain impedance (all zero) is a candidate, also on an even grid (--reduced's 4 x 4 x 1)
    assert np.any(np.all(cand == 0, axis=(1, 2)))
    # the default grid keeps its 7 x 7 x 3 (its middle point snapped to an exact 0, not doubled)
    default = arms.fixed_candidates(task, 7, 3)
    assert default.shape == (147, 2, 3) and np.sum(np.all(default == 0, axis=(1, 2))) == 1
    even = arms.fixed_candidates(task, 4, 1)
    assert even.shape == (25, 2, 3) and np.any(np.all(even == 0, axis=(1, 2)))
    assert np.any(np.all(arms.fixed_candidates(task, 3, 2)[:, :, 2] == 0, axis=1))


def test_ablations_change_only_their_field():
    task = catching_paper().task
    for arm, change in arms.ABLATIONS.items():
        t = arms.arm_task(task, arm)
        for name, value in change.items():
            assert tl.replace(task, **{name: value}) == t
        assert t != task
    assert arms.arm_task(task, "online") == task
    with pytest.raises(ValueError, match="unknown arms"):
        arms.PaperProtocol(arms=("online", "nope"))


def test_paper_cli_refuses_bad_arguments(capsys, monkeypatch):
    from hec_jax.loop.paper_report import paper_main

    def not_refused(*args, **kwargs):
        raise AssertionError("the arguments were not refused: the protocol started")

    monkeypatch.setattr(arms, "run_arms", not_refused)

    for argv in (
        ["--preset", "juggling_paper"],
        ["--preset", "catching_paper", "--eye", "camera", "--out", "/tmp/never"],
        ["--held-out", "0", "--out", "/tmp/never"],
        ["--arms", "online", "nope", "--out", "/tmp/never"],
        ["--reduced", "--seeds", "5", "--out", "/tmp/never"],  # --reduced would drop it
        ["--reduced", "--held-out", "6", "--out", "/tmp/never"],
    ):
        with pytest.raises(SystemExit) as e:
            paper_main(argv)
        assert e.value.code == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "error" in err


@pytest.mark.slow
def test_fixed_zero_impedance_is_plain_and_protocol_matches_per_swing_runs():
    """Two independent checks of the protocol's plumbing on a short run: a constant virtual
    impedance of 0 gives plain impedance's trajectory (to round-off); the training scan with the
    conditions as xs gives the same swings as one run per condition.
    """
    exp = catching_paper(seeds=1)
    task = dataclasses.replace(exp.task, swing_s=0.6, swings=2, settle_s=0.1)
    loop = tl.build_loop(task)
    run = make_protocol(loop, 0.6)
    train = draw_conditions(ConditionRange(), task.pendulum, 2, 0, jnp.float64)
    held = draw_conditions(ConditionRange(), task.pendulum, 2, 1, jnp.float64)
    params = jax.vmap(lambda k: loop.learner_init(k, jnp.float64).params)(
        jax.random.split(jax.random.PRNGKey(0), 1)
    )
    none = jax.tree_util.tree_map(lambda x: x[:0], train)
    _, plain = run(params, switches("plain"), switches("plain"), none, held)
    zero = switches("frozen", fixed=jnp.zeros((2, 3)))
    _, fixed0 = run(params, zero, zero, none, held)
    # to round-off (1 ulp seen: the plain arm multiplies the networks' O by 0)
    np.testing.assert_allclose(np.asarray(plain["qpos"]), np.asarray(fixed0["qpos"]), rtol=1e-12)
    learned = switches("learned")
    tr, _ = run(params, learned, learned, train, held)
    first = jax.tree_util.tree_map(lambda x: x[:1], train)
    tr1, _ = run(params, learned, learned, first, held)
    np.testing.assert_allclose(np.asarray(tr["qpos"][:, 0]), np.asarray(tr1["qpos"][:, 0]))


@pytest.mark.slow
def test_run_arms_end_to_end_with_bptt_on_a_tiny_protocol():
    """Every kind of arm runs through ``run_arms`` (a fixed search, BPTT, an ablation) and gives
    a row; BPTT's loss per epoch is finite.
    """
    exp = tl.replace(catching_paper(seeds=1), swings=2, swing_s=0.5, settle_s=0.1)
    protocol = arms.PaperProtocol(
        experiment=exp,
        held_out=1,
        eval_s=0.5,
        arms=("plain", "fixed_energy", "bptt", "mu_0"),
        fixed_grid=2,
        fixed_grid_m=1,
        fixed_search_pendulums=1,
        bptt_epochs=1,
        bptt_horizon_s=0.3,
    )
    results = arms.run_arms(protocol)
    rows = arms.table_rows(results, "catching")
    assert [r["arm"] for r in rows] == ["plain", "fixed_energy", "bptt", "mu_0"]
    loss = results["arms"]["bptt"]["bptt_loss_per_epoch"]
    assert len(loss) == 1 and len(loss[0]) == 2 and np.all(np.isfinite(loss))
    # a 2-value grid per parameter gets zero (plain impedance) added: 3 x 3 x 1 candidates
    assert results["fixed_search"]["candidates"] == 9


def test_merge_joins_disjoint_arms_as_one_run_and_refuses_mixed_runs(tmp_path, capsys):
    """``experiments/paper_merge.py`` (:func:`paper_report.merge_runs`): two run folders with
    disjoint arms give the table and metrics that one run of all the arms would have had (the
    same entries, arms in ``ALL_ARMS`` order, the fixed search from the run that ran it); runs
    of another protocol, other pendulums, a shared arm or an unfinished run are refused."""
    from hec_jax.loop import paper_report as pr
    from hec_jax.runs import run_folder, write_json

    def summary(speed):
        v = {"mean": speed, "std": 0.05, "n": 40}
        return {"relative_speed_at_contact": v, "held": {"fraction": 0.0, "n": 40}, "runs": 40}

    pendulums = {"training": {"cube_mass": [0.6, 0.7]}, "held_out": {"cube_mass": [0.8]}}
    search = {"candidates": 147, "fixed_energy": [1.0, 0.0, 0.0]}
    everything = {
        "arms": {
            "plain": {"summary": summary(1.3)},
            "fixed_energy": {"summary": summary(0.585)},
            "online": {"summary": summary(0.559)},
            "bptt": {"summary": summary(1.15)},
        },
        "pendulums": pendulums,
        "fixed_search": search,
    }

    def folder(name, arm_names, metrics, **protocol_changes):
        protocol = dataclasses.asdict(
            dataclasses.replace(arms.PaperProtocol(arms=arm_names), **protocol_changes)
        )
        settings = dict(protocol=protocol, preset="catching_paper", reduced=False, float32=False)
        with run_folder(tmp_path / name, 0, settings) as f:
            write_json(f / "metrics.json", metrics)
        return tmp_path / name

    def part(arm_names, with_search):
        entries = everything["arms"] | {"frozen": {"summary": summary(1.28)}}
        m = {"arms": {a: entries[a] for a in arm_names}, "pendulums": pendulums}
        return m | ({"fixed_search": search} if with_search else {})

    online = folder("online", ("online",), part(("online",), False))
    fixed = folder("fixed", ("plain", "fixed_energy"), part(("plain", "fixed_energy"), True))
    # the BPTT arm alone may have its own BPTT settings
    bptt = folder("bptt", ("bptt",), part(("bptt",), False), bptt_epochs=6)
    merged = pr.merge_main(
        ["--runs", str(online), str(bptt), str(fixed), "--out", str(tmp_path / "m")]
    )
    assert json.loads(json.dumps(merged)) == everything
    assert list(merged["arms"]) == ["plain", "fixed_energy", "online", "bptt"]
    table = (tmp_path / "m" / "table.md").read_text()
    assert table.strip() == arms.markdown_table(arms.table_rows(everything, "catching"))
    config = json.loads((tmp_path / "m" / "config.json").read_text())
    assert [s["arms"] for s in config["merged_from"]] == [
        ["online"],
        ["bptt"],
        ["plain", "fixed_energy"],
    ]
    capsys.readouterr()

    other_pendulums = dict(part(("frozen",), False), pendulums={"training": {}, "held_out": {}})
    refused = {
        "two runs": folder("again", ("online",), part(("online",), False)),
        "pendulums": folder("pend", ("frozen",), other_pendulums),
        "protocol": folder("held", ("frozen",), part(("frozen",), False), held_out=3),
    }
    for why, extra in refused.items():
        with pytest.raises(SystemExit) as e:
            pr.merge_main(
                ["--runs", str(online), str(fixed), str(extra), "--out", str(tmp_path / "x")]
            )
        assert e.value.code == 2, why
        assert "cannot merge" in capsys.readouterr().err, why
    assert not (tmp_path / "x").exists()  # a refused merge writes nothing
    unfinished = tmp_path / "unfinished"
    unfinished.mkdir()
    (unfinished / "metrics.json").write_text(json.dumps(part(("frozen",), False)))
    (unfinished / "config.json").write_text(json.dumps({"status": "running"}))
    with pytest.raises(SystemExit):
        pr.merge_main(["--runs", str(online), str(unfinished), "--out", str(tmp_path / "x")])
    with pytest.raises(SystemExit):
        pr.merge_main(["--runs", str(online), "--out", str(tmp_path / "x")])


def test_the_fixed_search_s_held_is_the_table_s():
    """:func:`arms.held_in_one_contact` (jitted, the fixed-impedance search's "held") against
    :func:`paper_metrics.catching_run_metrics`' ``held`` (NumPy, contact episodes) on random
    contact traces built to sit near each rule's edges: gaps just under and at the merge length,
    contact starting inside the settle window, bounces that come back to rest, no contact."""
    dt, threshold, settle_s = 1e-3, 0.5, 0.01
    tail, min_gap = 10, int(round(pm.CONTACT_MERGE_S / dt))
    held = jax.jit(arms.held_in_one_contact, static_argnums=(1, 2))
    rng = np.random.default_rng(11)
    cases = {True: 0, False: 0}
    for _ in range(300):
        # four trace lengths, not 90: each length is a compile of the jitted rule (30 s of the
        # default suite's time on the CI machine); the rules' edges lie in the gaps and starts
        steps = int(rng.choice([30, 61, 90, 119]))
        on = np.zeros(steps, bool)
        start = int(rng.integers(0, steps))
        on[start:] = True
        for _ in range(int(rng.integers(0, 3))):  # gaps around the merge length
            g0 = int(rng.integers(start, steps))
            on[g0 : g0 + int(rng.choice([1, min_gap - 1, min_gap, min_gap + 3]))] = False
        if rng.random() < 0.1:
            on[:] = False
        f = np.where(on, 2.0, 0.0)
        log = {
            "f_contact": np.stack([f, 0 * f, 0 * f, 0 * f, 0 * f, 0 * f], -1),
            "xd_o_true": np.zeros((steps, 2)),
            "xd_e": np.zeros((steps, 2)),
        }
        want = pm.catching_run_metrics(log, dt, 2.0, threshold, settle_s)["held"]
        assert bool(held(jnp.asarray(on), tail, min_gap)) == want, on.astype(int)
        cases[want] += 1
    assert min(cases.values()) > 30  # both answers tried
    # the merge length longer than the swing: no gap can split it
    assert bool(arms.held_in_one_contact(jnp.ones(5, bool), 2, 20))
