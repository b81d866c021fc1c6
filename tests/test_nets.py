"""The networks (Eqs. 50-51) and the online learner (Eqs. 52-66)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from point_mass_world import B_E, DT, K_C, K_E, M_E, make_episodes, sphere_1d

from hec_jax import nets
from hec_jax.nets import LearnerConfig, LearnerInputs, NetConfig
from hec_jax.nets.learner import NETS_SHELL

CFG_1D = LearnerConfig(net=NetConfig(n_axes=1), contact_stiffness=K_C, eta=(0.1, 0.1, 0.1))


def _learner_1d(cfg=CFG_1D):
    """The learner of the 1-D world (target impedance M_E, B_E, K_E; sampling DT), jitted as the
    loop runs it (eager JAX would compile each operation on its own: the suite's time)."""
    init, update = nets.make_online_learner(cfg, DT, (M_E,), (B_E,), (K_E,))
    return jax.jit(init, static_argnums=1), jax.jit(update)


def _inputs_1d(values, contact, radius=CFG_1D.radius):
    """LearnerInputs of one 1-D sample (x_e, xd_e, xdd_e, x_o, xd_o, xdd_o, f_int) with the
    sphere geometry of Eqs. 45-46 in 1-D."""
    x = [jnp.array([v]) for v in values]
    sphere = sphere_1d(x[3] - x[0], x[4] - x[1], x[5] - x[2], radius)
    return LearnerInputs(*x, jnp.asarray(contact), sphere)


def test_output_unit_is_eq51_and_its_derivative():
    x = jnp.linspace(-30.0, 30.0, 601)
    u, theta = 7.0, 0.1
    printed = u / 2 * (1 - jnp.exp(-x + theta)) / (1 + jnp.exp(-x + theta))
    np.testing.assert_allclose(nets.output_unit(x, u, theta), printed, atol=1e-12)
    grad = jax.vmap(jax.grad(lambda v: nets.output_unit(v, u, theta)))(x)
    np.testing.assert_allclose(nets.output_unit_derivative(x, u, theta), grad, atol=1e-12)
    h = 1e-6
    fd = (nets.output_unit(x + h, u, theta) - nets.output_unit(x - h, u, theta)) / (2 * h)
    np.testing.assert_allclose(nets.output_unit_derivative(x, u, theta), fd, atol=1e-8)
    assert np.all(np.abs(nets.output_unit(x, u, theta)) <= u / 2)


def test_stability_by_construction_under_random_weights():
    config = NetConfig()
    m_e, b_e, k_e = jnp.array([1.0, 2.0]), jnp.array([40.0, 30.0]), jnp.array([400.0, 100.0])
    u = nets.u_max(config, m_e, b_e, k_e)
    # test data from NumPy and one jit: eager JAX compiles each operation (the suite's time)
    apply = jax.jit(jax.vmap(nets.apply, in_axes=(None, None, 0, None)), static_argnums=1)
    for seed in range(5):
        params = nets.init_params(jax.random.PRNGKey(seed), config, jnp.float64)
        # Blow the weights up so outputs saturate (tanh rounds to +-1).
        params = jax.tree_util.tree_map(lambda p, s=seed: p * 1e3 * (s + 1), params)
        inputs = jnp.asarray(np.random.default_rng(seed).normal(size=(256, 2, 4)) * 10.0)
        o = apply(params, config, inputs, u)
        margins = nets.stability_margins(o, m_e, b_e, k_e)
        assert np.all(np.asarray(margins) > 0)
        assert np.min(margins) >= config.margin * 0.999  # at least margin x min(M_e) (M_e >= 1)


def test_apply_matches_the_flax_reference_module():
    """``apply`` (weights (out, in), multiply-and-sum layers) against Flax ``nn.Dense`` layers
    (kernels (in, out), matrix products) on the same weights, for a non-default structure too."""
    apply = jax.jit(jax.vmap(nets.apply, in_axes=(None, None, 0, None)), static_argnums=1)
    for config in (NetConfig(), NetConfig(n_axes=3, hidden=(7, 5, 3), theta=-0.4)):
        rng = np.random.default_rng(len(config.hidden))  # test data from NumPy (one compile)
        params = nets.init_params(jax.random.PRNGKey(len(config.hidden)), config, jnp.float64)
        # random weights everywhere (the initial output layer is nearly zero)
        params = jax.tree_util.tree_map(lambda w, r=rng: w + r.normal(size=w.shape), params)
        flax_params = nets.to_flax(params, len(config.hidden))
        back = nets.from_flax(flax_params, len(config.hidden))
        for a, b in zip(
            jax.tree_util.tree_leaves(params), jax.tree_util.tree_leaves(back), strict=True
        ):
            np.testing.assert_array_equal(a, b)
        inputs = jnp.asarray(rng.normal(size=(64, config.n_axes, 4)))
        u = jnp.arange(1.0, 1.0 + 3 * config.n_axes).reshape(config.n_axes, 3)
        got = apply(params, config, inputs, u)
        model = nets.FlaxMlp(config.hidden, config.init_output_std)
        per_net = lambda p, x, model=model: model.apply({"params": p}, x)  # noqa: E731
        pre = jax.jit(jax.vmap(jax.vmap(jax.vmap(per_net, (0, None)), (0, 0)), (None, 0)))(
            flax_params, inputs
        )
        want = np.asarray(u) / 2 * np.tanh((np.asarray(pre) - config.theta) / 2)
        assert got.shape == (64, config.n_axes, 3)
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)


def test_gain_functions_eq62_eq66():
    r, r_b = 0.25, 0.06
    rho = jnp.array([0.0, 0.03, r_b, (r + r_b) / 2, r, 0.3])
    alpha = nets.gain_alpha(rho, r, r_b)
    beta = nets.gain_beta(rho, r, r_b)
    np.testing.assert_allclose(alpha[:3], [0.0, 0.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(alpha[3], np.sin(np.pi / 4), atol=1e-15)
    np.testing.assert_allclose(alpha[4], 1.0, atol=1e-15)
    np.testing.assert_allclose(beta[:2], [0.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(beta[2], -1.0, atol=1e-15)  # the jump at R_b (as printed)
    np.testing.assert_allclose(beta[3], np.sin(np.pi / 4) - 1, atol=1e-15)
    np.testing.assert_allclose(beta[4], 0.0, atol=1e-15)


def _inputs_2d(contact, f_int):
    return LearnerInputs(
        x_e=jnp.array([0.0, 0.1]),
        xd_e=jnp.array([0.2, -0.1]),
        xdd_e=jnp.zeros(2),
        x_o=jnp.array([0.12, 0.05]),
        xd_o=jnp.array([-0.8, 0.3]),
        xdd_o=jnp.array([0.0, -9.8]),
        f_int=jnp.asarray(f_int),
        in_contact=jnp.asarray(contact),
        sphere=nets.SphereGeometry(*(jnp.zeros(2),) * 3),  # not used by the energy
    )


def test_energy_functions_against_their_equations():
    cfg_c = LearnerConfig(task="catching", mu=0.01, f_desired=2.0)
    cfg_h = LearnerConfig(task="hitting", mu=0.01, f_desired=5.0)
    v_tc = jnp.array([-1.0, 0.4])
    for contact, f_int in ((False, [0.0, 0.0]), (True, [-3.0, 1.0])):
        inp = _inputs_2d(contact, f_int)
        x_r = np.asarray(inp.x_o - inp.x_e)
        rho = np.linalg.norm(x_r)
        n = x_r / rho
        f_d = -cfg_c.f_desired * n * contact
        alpha = np.sin((rho - 0.06) * np.pi / (2 * (0.25 - 0.06)))
        e_cv = 0.5 * np.sum((alpha * np.asarray(v_tc) - np.asarray(inp.xd_o - inp.xd_e)) ** 2)
        e_cf = 0.5 * np.sum((f_d - np.asarray(f_int)) ** 2)
        got = nets.task_energy(cfg_c, inp.x_e, inp.xd_e, inp, v_tc)
        np.testing.assert_allclose(got, e_cv + cfg_c.mu * e_cf, rtol=1e-12)
        beta = alpha - 1
        f_hd = -cfg_h.f_desired * n * contact
        e_hv = 0.5 * np.sum((beta * np.asarray(inp.xd_o) - np.asarray(inp.xd_e)) ** 2)
        e_hf = 0.5 * np.sum((f_hd - np.asarray(f_int)) ** 2)
        got = nets.task_energy(cfg_h, inp.x_e, inp.xd_e, inp, v_tc)
        np.testing.assert_allclose(got, e_hv + cfg_h.mu * e_hf, rtol=1e-12)


def _sigmoid(x):
    return 1.0 / (1.0 + np.exp(-x))


def _assert_same_params(a: dict, b: dict) -> None:
    """Bitwise equal network parameters."""
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b), strict=True):
        np.testing.assert_array_equal(x, y)


def test_update_equals_hand_computed_update_1d():
    """1-D point mass, object approaching inside the sphere, no contact: the learner's weight change
    equals Eqs. 52-58 worked out by hand in NumPy (forward pass, dE/dF_act, backprop); with
    ``allow=False`` the same sample changes no weight."""
    init, update = _learner_1d()
    state = init(jax.random.PRNGKey(3), jnp.float64)
    x_e, v_e, a_e, x_o, v_o, a_o = 0.01, 0.05, 0.3, 0.2, -0.9, 1.5
    v_tc = -1.1
    state = state._replace(xd_r_tc=jnp.array([v_tc]), was_inside=jnp.asarray(True))
    inputs = _inputs_1d((x_e, v_e, a_e, x_o, v_o, a_o, 0.0), False)
    new_state, out = update(state, inputs)
    # --- by hand ---
    cfg, r, r_b, dt = CFG_1D, CFG_1D.radius, CFG_1D.r_b, DT
    x_r, v_r, a_r = x_o - x_e, v_o - v_e, a_o - a_e
    terms = np.array([x_r - r, v_r, a_r])  # dX_o (n = +1), dX_o', dX_o'' for (K, B, M)
    net_in = np.array([x_r, v_r, a_r, 0.0]) / np.array(cfg.net.input_scale)
    p = jax.tree_util.tree_map(lambda a: np.asarray(a)[0], state.params)  # axis 0
    u = 2 * (1 - cfg.net.margin) * np.array([K_E, B_E, M_E])
    phase = (x_r - r_b) * np.pi / (2 * (r - r_b))
    alpha, dalpha = np.sin(phase), np.cos(phase) * np.pi / (2 * (r - r_b))
    resid = alpha * v_tc - v_r
    de_dve = resid  # d/dv_e of 1/2 (alpha v_tc - (v_o - v_e))^2
    de_dxe = resid * v_tc * dalpha * (-1.0)  # through alpha(|x_o - x_e|)
    g = de_dxe * dt**2 + de_dve * dt  # Eqs. 54-58
    np.testing.assert_allclose(out.de_df_act, [g], rtol=1e-12)
    o = np.zeros(3)
    for k in range(3):
        # weights (out, in) as Eq. 50 indexes them: w_ij from unit j to unit i
        w1, b1 = p["hidden_0"]["weight"][k], p["hidden_0"]["bias"][k]
        w2, b2 = p["hidden_1"]["weight"][k], p["hidden_1"]["bias"][k]
        w3, b3 = p["output"]["weight"][k], p["output"]["bias"][k]
        y1 = _sigmoid(w1 @ net_in + b1)
        y2 = _sigmoid(w2 @ y1 + b2)
        x = w3 @ y2 + b3
        th = np.tanh((x - cfg.net.theta) / 2)
        o[k] = u[k] / 2 * th
        delta = g * terms[k] * u[k] / 4 * (1 - th**2)  # dE/dx of the output unit
        eta = cfg.eta[k]
        np.testing.assert_allclose(
            np.asarray(new_state.params["output"]["bias"][0, k]), b3 - eta * delta, rtol=1e-10
        )
        np.testing.assert_allclose(
            np.asarray(new_state.params["output"]["weight"][0, k]),
            w3 - eta * delta * y2,
            rtol=1e-10,
        )
        delta2 = (w3 * delta) * y2 * (1 - y2)
        np.testing.assert_allclose(
            np.asarray(new_state.params["hidden_1"]["weight"][0, k]),
            w2 - eta * np.outer(delta2, y1),
            rtol=1e-10,
            atol=1e-16,
        )
        delta1 = (delta2 @ w2) * y1 * (1 - y1)
        np.testing.assert_allclose(
            np.asarray(new_state.params["hidden_0"]["weight"][0, k]),
            w1 - eta * np.outer(delta1, net_in),
            rtol=1e-10,
            atol=1e-16,
        )
    np.testing.assert_allclose(out.impedance[0], o, rtol=1e-12)
    np.testing.assert_allclose(out.f_o, [np.sum(o * terms)], rtol=1e-12)
    assert bool(out.learning)
    held_state, held_out = update(state, inputs, False)
    assert not bool(held_out.learning)
    np.testing.assert_array_equal(held_out.f_o, out.f_o)
    _assert_same_params(state.params, held_state.params)


def test_no_learning_outside_sphere_and_while_receding_without_contact():
    init, update = _learner_1d()
    state = init(jax.random.PRNGKey(0), jnp.float64)
    for x_o, v_o in ((0.5, -1.0), (0.2, +0.5)):  # outside; inside but receding
        inputs = _inputs_1d((0.0, 0.0, 0.0, x_o, v_o, 0.0, 0.0), False)
        new_state, out = update(state, inputs)
        assert not bool(out.learning)
        _assert_same_params(state.params, new_state.params)
    assert float(update(state, inputs)[1].f_o[0]) != 0.0  # inside: F_o acts even when not learning


FIELDS_1D = ("x_e", "xd_e", "xdd_e", "x_o", "xd_o", "xdd_o", "f_int")


@pytest.mark.parametrize("bad_value", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("field", FIELDS_1D)
def test_a_non_finite_input_never_reaches_the_weights(field, bad_value):
    """A NaN/inf in any input while learning (object inside the sphere, approaching): the sample
    is skipped (no weight change, F_o = 0, O = 0, E_cf and the encounter's memory unchanged),
    counted and flagged; the next finite sample learns as if it had not happened."""
    init, update = _learner_1d()
    state = init(jax.random.PRNGKey(0), jnp.float64)._replace(
        was_inside=jnp.asarray(True), xd_r_tc=jnp.array([-1.1])
    )
    good_values = (0.01, 0.05, 0.3, 0.2, -0.9, 1.5, 0.0)
    good = _inputs_1d(good_values, False)
    assert bool(update(state, good)[1].learning)  # this sample would learn
    values = [bad_value if f == field else v for f, v in zip(FIELDS_1D, good_values, strict=True)]
    skipped_state, out = update(state, _inputs_1d(values, False))
    assert not bool(out.finite) and not bool(out.learning) and not bool(out.inside)
    np.testing.assert_array_equal(out.f_o, 0.0)
    np.testing.assert_array_equal(out.impedance, 0.0)
    _assert_same_params(state.params, skipped_state.params)
    assert int(skipped_state.nonfinite_samples) == 1
    for name in ("xd_r_tc", "was_inside", "touched", "energy_f", "encounters"):
        np.testing.assert_array_equal(getattr(skipped_state, name), getattr(state, name), name)
    after, _ = update(skipped_state, good)
    reference, _ = update(state, good)
    _assert_same_params(after.params, reference.params)


def test_a_non_finite_sphere_geometry_is_skipped_too():
    init, update = _learner_1d()
    state = init(jax.random.PRNGKey(0), jnp.float64)
    inputs = _inputs_1d((0.01, 0.05, 0.3, 0.2, -0.9, 1.5, 0.0), False)
    inputs = inputs._replace(sphere=inputs.sphere._replace(dxd_o=jnp.array([np.nan])))
    new_state, out = update(state, inputs)
    assert not bool(out.finite) and not bool(out.learning)
    np.testing.assert_array_equal(out.f_o, 0.0)
    _assert_same_params(state.params, new_state.params)


@pytest.fixture(scope="module")
def learning_run():
    run = make_episodes(CFG_1D, steps=1200, learn=True)
    _, logs = run(jax.random.PRNGKey(0), 6)
    return jax.tree_util.tree_map(np.asarray, logs)


def test_short_learning_run_lowers_energy_and_peak_force(learning_run):
    """Six 1.2 s swings with the weights carried over: the task energy accumulated inside the sphere
    and the peak contact force fall from swing to swing and below the frozen initial networks."""
    logs = learning_run
    energy = np.sum(logs["energy"] * logs["inside"], axis=1) * DT  # per episode
    peak = -np.min(logs["f_int"], axis=1)
    _, flog = make_episodes(CFG_1D, steps=1200, learn=False)(jax.random.PRNGKey(0), 1)
    frozen_energy = float(np.sum(flog["energy"] * flog["inside"]) * DT)
    frozen_peak = float(-np.min(np.asarray(flog["f_int"])))
    assert energy[0] < frozen_energy  # learning acts within the first swing already
    assert energy[-1] < energy[0]
    assert np.all(np.diff(peak) < 0)
    assert peak[-1] < 0.5 * frozen_peak
    assert np.all(logs["margins"] > 0)  # strict Eq. 49 at every sample


def test_catching_velocity_term_only_before_contact():
    """Sec. 6.2: relative velocity is reduced before contact, the force controlled after it."""
    cfg = LearnerConfig(task="catching", mu=0.01, f_desired=2.0)
    inp = _inputs_2d(True, [-3.0, 1.0])
    v_tc = jnp.array([-1.0, 0.4])
    before = nets.task_energy(cfg, inp.x_e, inp.xd_e, inp, v_tc, touched=False)
    after = nets.task_energy(cfg, inp.x_e, inp.xd_e, inp, v_tc, touched=True)
    x_r = np.asarray(inp.x_o - inp.x_e)
    n = x_r / np.linalg.norm(x_r)
    e_cf = 0.5 * np.sum((-cfg.f_desired * n - np.array([-3.0, 1.0])) ** 2)
    np.testing.assert_allclose(after, cfg.mu * e_cf, rtol=1e-12)
    assert before > after


# --- the network step's two implementations (hec_jax.nets.network_step) ---------------------


def _batch_of_steps(dtype, batch=5, n_axes=2, hidden=(20, 20)):
    """Per-run parameters, inputs, dE/dO and learning flags (one run with a NaN dE/dO that does
    not learn); rates and U shared, as the learner passes them."""
    cfg = NetConfig(n_axes=n_axes, hidden=hidden)
    keys = jax.random.split(jax.random.PRNGKey(7), batch)
    params = jax.jit(jax.vmap(lambda k: nets.init_params(k, cfg, dtype)))(keys)
    params = jax.tree_util.tree_map(lambda p: 3.0 * p, params)  # outputs away from 0
    rng = np.random.default_rng(8)  # test data from NumPy (eager JAX compiles each operation)
    net_in = jnp.asarray(rng.normal(size=(batch, n_axes, 4)), dtype)
    g_scale = jnp.asarray(10.0 * rng.normal(size=(batch, n_axes, 3)), dtype)
    g_scale = g_scale.at[1, 0, 0].set(jnp.nan)
    learning = jnp.arange(batch) % 3 != 1  # run 1 (with the NaN) does not learn
    eta = jnp.asarray([0.3, 0.2, 0.1], dtype)
    u = jnp.asarray([[800.0, 80.0, 2.0]], dtype) / (1.0 + jnp.arange(n_axes, dtype=dtype)[:, None])
    return params, net_in, g_scale, learning, eta, u


def _vmapped_step(kernel, eta, u, active=False):
    """jit(vmap(network_step)) over (params, net_in, g_scale, learning[, active])."""
    if active:
        step = lambda p, x, g, lrn, act: nets.network_step(  # noqa: E731
            p, x, g, lrn, eta, u, 0.1, kernel, active=act
        )
    else:
        step = lambda p, x, g, lrn: nets.network_step(  # noqa: E731
            p, x, g, lrn, eta, u, 0.1, kernel
        )
    return jax.jit(jax.vmap(step))


@pytest.mark.parametrize(
    ("dtype", "hidden", "with_active", "n_axes"),
    [
        # the default suite keeps the last two (both dtypes, with ``active``, runs straddled by
        # a kernel program); the others are slow (each compiles its own kernel program)
        pytest.param(jnp.float32, (20, 20), False, 2, marks=pytest.mark.slow),
        pytest.param(jnp.float64, (20, 20), False, 2, marks=pytest.mark.slow),
        pytest.param(jnp.float64, (12, 24), False, 2, marks=pytest.mark.slow),
        (jnp.float32, (20, 20), True, 2),
        # 3 networks per run: kernel programs (2 networks each) straddle runs
        (jnp.float64, (20, 20), True, 1),
    ],
)
def test_network_step_kernel_matches_the_reference(dtype, hidden, with_active, n_axes):
    """The Pallas Triton kernel (through Pallas' interpreter) gives the reference's O and updated
    weights to rounding, keeps the weights of runs that do not learn bitwise (also with a NaN
    dE/dO), and changes the others by more than the tolerance. With ``active``, inactive runs
    (one of them flagged learning) give O = 0 and keep their weights bitwise in both."""
    params, net_in, g, learning, eta, u = _batch_of_steps(dtype, n_axes=n_axes, hidden=hidden)
    args = (params, net_in, g, learning)
    updated = learning
    if with_active:
        # runs 0 and 2 (both flagged learning) inactive; with 3 networks per run, kernel
        # programs hold (inactive, active) and (active, inactive) pairs of networks
        active = jnp.asarray([False, True, False, True, True])
        assert bool(learning[0]) and bool(learning[2])
        args += (active,)
        updated = learning & active
    o_ref, p_ref = _vmapped_step("xla", eta, u, with_active)(*args)
    o_ker, p_ker = _vmapped_step("interpret", eta, u, with_active)(*args)
    if with_active:  # the reference itself: O = 0 and weights held where inactive, else as before
        o_all, p_all = _vmapped_step("xla", eta, u)(params, net_in, g, updated)
        np.testing.assert_array_equal(o_ref[~active], 0.0)
        np.testing.assert_array_equal(o_ref[active], o_all[active])
        _assert_same_params((o_ref[active], p_ref), (o_all[active], p_all))
    rtol = 1e-13 if dtype == jnp.float64 else 1e-6  # of each leaf's largest entry
    scale = lambda a: float(jnp.max(jnp.abs(a)))  # noqa: E731
    assert o_ker.dtype == dtype
    np.testing.assert_allclose(o_ker, o_ref, rtol=0, atol=rtol * scale(o_ref))
    if with_active:
        np.testing.assert_array_equal(o_ker[~active], 0.0)
    moved = 0.0
    for a, b, w in zip(
        *(jax.tree_util.tree_leaves(t) for t in (p_ker, p_ref, params)), strict=True
    ):
        assert a.dtype == dtype and a.shape == w.shape
        np.testing.assert_allclose(a, b, rtol=0, atol=rtol * scale(b))
        np.testing.assert_array_equal(a[~updated], w[~updated])  # held exactly
        moved = max(moved, scale(a[updated] - w[updated]) / scale(b))
    assert moved > 1e3 * rtol


def test_network_step_kernel_is_differentiable_through_the_reference():
    """grad through the kernel's ``custom_jvp`` equals grad through the reference (float64)."""
    params, net_in, g, learning, eta, u = _batch_of_steps(jnp.float64)
    g = jnp.nan_to_num(g)

    def loss(kernel, params, g):
        o, new = jax.vmap(
            lambda p, x, gg, lrn: nets.network_step(p, x, gg, lrn, eta, u, 0.1, kernel)
        )(params, net_in, g, learning)
        leaves = jax.tree_util.tree_leaves(new)
        return jnp.sum(o**2) + sum(jnp.sum(jnp.sin(w)) for w in leaves)

    # jitted: one compile each rather than one per operation
    ref = jax.jit(jax.grad(lambda p, gg: loss("xla", p, gg), argnums=(0, 1)))(params, g)
    ker = jax.jit(jax.grad(lambda p, gg: loss("interpret", p, gg), argnums=(0, 1)))(params, g)
    for a, b in zip(jax.tree_util.tree_leaves(ker), jax.tree_util.tree_leaves(ref), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12 * float(jnp.max(jnp.abs(b))))


def test_network_step_triton_off_the_gpu_and_unbatched_is_the_reference():
    """kernel='triton' runs the reference (bitwise) where there is no CUDA device or no vmap, and
    bad kernels or network shapes are refused."""
    params, net_in, g, learning, eta, u = _batch_of_steps(jnp.float64)
    if jax.default_backend() != "gpu":
        batched = _vmapped_step("triton", eta, u)(params, net_in, g, learning)
        _assert_same_params(batched, _vmapped_step("xla", eta, u)(params, net_in, g, learning))
    one = lambda a: a[0]  # noqa: E731
    args = (jax.tree_util.tree_map(one, params), net_in[0], g[0], learning[0], eta, u)
    single = nets.network_step(*args, 0.1, "triton")
    _assert_same_params(single, nets.network_step(*args, 0.1, "xla"))
    with pytest.raises(ValueError, match="kernel must be one of"):
        nets.network_step(*args, 0.1, "cuda")
    with pytest.raises(ValueError, match="kernel must be one of"):
        LearnerConfig(kernel="cuda")
    deep = nets.init_params(jax.random.PRNGKey(0), NetConfig(hidden=(20, 20, 20)), jnp.float64)
    with pytest.raises(ValueError, match="two hidden layers"):
        nets.network_step(deep, net_in[0], g[0], learning[0], eta, u, 0.1, "triton")
    for hidden in ((20, 40), (40, 20)):
        wide = nets.init_params(jax.random.PRNGKey(0), NetConfig(hidden=hidden), jnp.float64)
        with pytest.raises(ValueError, match="at most 32 units"):
            nets.network_step(wide, net_in[0], g[0], learning[0], eta, u, 0.1, "triton")


@pytest.mark.slow  # the kernel's step against the reference is in the default suite (above)
def test_learning_with_the_kernel_follows_the_reference_world():
    """Two 1.2 s episodes of the 1-D world for three network seeds (vmapped) with the learner's
    kernel (through Pallas' interpreter) and with the reference: the same contact forces,
    impedances and final weights to float64 rounding; also with the networks evaluated inside the
    virtual sphere only (``nets_outside=False``), O then 0 outside it."""
    cfg_kernel = LearnerConfig(**{**CFG_1D.__dict__, "kernel": "interpret"})
    cfg_inside = LearnerConfig(**{**cfg_kernel.__dict__, "nets_outside": False})
    keys = jax.random.split(jax.random.PRNGKey(0), 3)
    runs = {}
    for name, cfg in (("xla", CFG_1D), ("interpret", cfg_kernel), ("inside", cfg_inside)):
        run = make_episodes(cfg, steps=1200, learn=True)
        runs[name] = jax.vmap(lambda k, run=run: run(k, 2))(keys)
    ls_ref, logs_ref = runs["xla"]
    assert np.mean(logs_ref["learning"]) > 0.05  # the comparison covers learning samples
    inside = np.asarray(logs_ref["inside"])
    assert 0.05 < np.mean(inside) < 0.95  # and samples outside the sphere
    rho = np.abs(np.asarray(logs_ref["x_o"]) - np.asarray(logs_ref["x_e"]))
    active = rho <= CFG_1D.radius * (1.0 + NETS_SHELL)  # the networks' shell past the sphere
    peak = float(np.max(np.abs(logs_ref["f_int"])))
    assert peak > 1.0  # and contact
    for name in ("interpret", "inside"):  # the kernel; the kernel with the networks inside only
        ls_ker, logs_ker = runs[name]
        np.testing.assert_array_equal(logs_ker["inside"], inside)
        np.testing.assert_allclose(logs_ker["f_int"], logs_ref["f_int"], rtol=0, atol=1e-9 * peak)
        imp_ref = np.asarray(logs_ref["impedance"])
        if name == "inside":  # O = 0 outside the sphere, where F_o does not use it (Eq. 47)
            np.testing.assert_array_equal(np.asarray(logs_ker["impedance"])[~active], 0.0)
            imp_ref = np.where(active[..., None], imp_ref, 0.0)
        np.testing.assert_allclose(logs_ker["impedance"], imp_ref, rtol=1e-9, atol=1e-9)
        for a, b in zip(
            *(jax.tree_util.tree_leaves(s.params) for s in (ls_ker, ls_ref)), strict=True
        ):
            np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12)


def test_configs_and_apply_refuse_what_they_cannot_handle():
    for bad in (
        dict(mu=-1.0),
        dict(contact_stiffness=-1.0),
        dict(radius=float("inf")),
        dict(eta=(0.1, float("nan"), 0.1)),
        dict(f_desired=float("nan")),
    ):
        with pytest.raises(ValueError, match=next(iter(bad)) if "eta" not in bad else "eta"):
            LearnerConfig(**bad)
    with pytest.raises(ValueError, match="input_scale"):
        NetConfig(input_scale=(0.0, 1.0, 1.0, 1.0))
    with pytest.raises(ValueError, match="hidden"):
        NetConfig(hidden=())
    for margin in (0.0, 1.0):  # 0: K_o + K_e = 0 at a saturated output, not > 0
        with pytest.raises(ValueError, match="margin"):
            NetConfig(margin=margin)
    cfg = NetConfig()
    params = nets.init_params(jax.random.PRNGKey(0), cfg, jnp.float64)
    u = nets.u_max(cfg, jnp.ones(2), 40.0 * jnp.ones(2), 400.0 * jnp.ones(2))
    assert nets.apply(params, cfg, jnp.zeros((2, 4)), u).shape == (2, 3)
    for shape in ((2, 3), (1, 4), (4,)):  # wrong width; a width-1 axis is not broadcast
        with pytest.raises(ValueError, match="inputs must have shape"):
            nets.apply(params, cfg, jnp.zeros(shape), u)


def test_at_the_centre_of_the_sphere_the_learner_agrees_with_the_controller():
    """At X_r = 0 the sphere's normal is undefined and the controller gives no virtual force
    (``SphereKinematics.inside``: 0 < |X_r| <= r); the learner counts the sample as outside too,
    so it neither reports a force the hand does not get nor learns from it."""
    from hec_jax import control as C
    from hec_jax.nets import LearnerInputs, SphereGeometry

    cfg = LearnerConfig()
    init, update = nets.make_online_learner(cfg, 1e-3, [1.0, 1.0], [40.0, 40.0], [400.0, 400.0])
    state = init(jax.random.PRNGKey(0), jnp.float64)
    x = np.array([0.3, 0.2])
    for x_o in (x, x + np.array([0.05, 0.0])):  # at the centre; inside, off it
        sk = C.sphere_kinematics(x_o - x, np.array([0.5, 0.1]), np.zeros(2), cfg.radius)
        values = (x, np.zeros(2), np.zeros(2), x_o, np.array([0.5, 0.1]), np.zeros(2), np.zeros(2))
        inputs = LearnerInputs(
            *(jnp.asarray(v) for v in values),
            jnp.asarray(False),
            SphereGeometry(sk.dx_o, sk.dxd_o, sk.dxdd_o),
        )
        _, out = update(state, inputs)
        assert bool(out.inside) == bool(sk.inside) == (not np.array_equal(x_o, x))
        if not sk.inside:
            np.testing.assert_array_equal(out.f_o, 0.0)
