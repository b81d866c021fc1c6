"""Pure control functions: Eq. 42-44 algebra, virtual sphere (Eqs. 45-47), Eq. 49, validation."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hec_jax import control as C

DT = 1e-3  # [s] control period of the tests' controller (the scene's time step)
TORQUE_LIMIT = (100.0, 60.0, 20.0)  # [N m] the scene's motor ctrlrange


def _random_obs(rng, f_int=None):
    A = rng.normal(size=(3, 3))
    M = A @ A.T + 0.5 * np.eye(3)
    return C.TaskObs(
        q=jnp.asarray(rng.normal(size=3)),
        qd=jnp.asarray(rng.normal(size=3)),
        M=jnp.asarray(M),
        h=jnp.asarray(rng.normal(size=3) * 5),
        x_e=jnp.asarray(rng.normal(size=2)),
        xd_e=jnp.asarray(rng.normal(size=2)),
        J=jnp.asarray(rng.normal(size=(2, 3))),
        jdot_qdot=jnp.asarray(rng.normal(size=2)),
        f_int=jnp.asarray(rng.normal(size=2) * 3 if f_int is None else f_int),
        x_o=jnp.asarray(rng.normal(size=2)),
        xd_o=jnp.asarray(rng.normal(size=2)),
    )


def test_control_law_gives_eq48_algebraically():
    """Plugging tau of Eqs. 41-44 into Eq. 39 (NumPy) gives M_e ddX + B_e dX' + K_e dX = F_int + F_o,
    and the null-space term produces no task acceleration."""
    rng = np.random.default_rng(1)
    cfg = C.ControllerConfig(mx_damping=0.0)
    for _ in range(5):
        obs = _random_obs(rng)
        p = C.impedance_params(
            rng.uniform(0.2, 2, 2), rng.uniform(5, 50, 2), rng.uniform(50, 500, 2)
        )
        tgt = C.Target(*(jnp.asarray(rng.normal(size=2)) for _ in range(3)))
        f_o = jnp.asarray(rng.normal(size=2))
        q_post = jnp.asarray(rng.normal(size=3))
        tau, _ = C.impedance_torque(obs, p, tgt, f_o, q_post, cfg)
        M, J, h = (np.asarray(x) for x in (obs.M, obs.J, obs.h))
        qdd = np.linalg.solve(M, np.asarray(tau) + J.T @ np.asarray(obs.f_int) - h)  # Eq. 39
        xdd = J @ qdd + np.asarray(obs.jdot_qdot)
        dX = np.asarray(obs.x_e - tgt.x_d)
        dXd = np.asarray(obs.xd_e - tgt.xd_d)
        lhs = np.asarray(p.m_e) * (xdd - np.asarray(tgt.xdd_d)) + np.asarray(p.b_e) * dXd
        lhs = lhs + np.asarray(p.k_e) * dX
        np.testing.assert_allclose(lhs, np.asarray(obs.f_int + f_o), rtol=1e-9, atol=1e-9)
        # null-space torque alone: zero task acceleration (dynamic consistency)
        tau_q1, _ = C.impedance_torque(obs, p, tgt, f_o, q_post + 1.0, cfg)
        dq = np.linalg.solve(M, np.asarray(tau_q1 - tau))
        np.testing.assert_allclose(J @ dq, 0.0, atol=1e-9)
        assert np.linalg.norm(dq) > 1e-3  # the posture term does act in the null space


def test_operational_inertia_damped_near_singularity():
    """Eq. 44 equals the exact inverse away from singularities and stays finite at one."""
    rng = np.random.default_rng(2)
    obs = _random_obs(rng)
    M, J = obs.M, obs.J
    Mx, cond = C.operational_inertia(M, J, 1e-6)
    exact = np.linalg.inv(np.asarray(J) @ np.linalg.solve(np.asarray(M), np.asarray(J).T))
    np.testing.assert_allclose(np.asarray(Mx), exact, rtol=1e-8)
    J_sing = jnp.stack([J[0], 2.0 * J[0]])  # rank 1
    Mx_s, cond_s = C.operational_inertia(M, J_sing, 1e-3)
    assert np.all(np.isfinite(np.asarray(Mx_s)))
    assert float(cond_s) > 1e10 and np.max(np.abs(np.asarray(Mx_s))) < 1e4


def _damped_inverse_by_eigh(A, damping):
    """Reference for Eq. 44's damped inverse (float64 NumPy eigendecomposition)."""
    s, V = np.linalg.eigh(0.5 * (A + A.T))
    s = np.maximum(s, 0.0)
    return (V * (s / (s**2 + damping**2))[None, :]) @ V.T, s[-1] / s[0]


@pytest.mark.parametrize("damping", [0.0, 1e-3, 0.3])
def test_operational_inertia_closed_form_matches_eigh(damping):
    """The closed form (Cayley-Hamilton, no eigendecomposition) equals V diag(s/(s^2+l^2)) V^T from
    NumPy's eigh, for well and badly conditioned A = J M^-1 J^T, in float64 and float32."""
    rng = np.random.default_rng(7)
    for k in range(40):
        obs = _random_obs(rng)
        M, J = np.asarray(obs.M), np.asarray(obs.J)
        if k % 4 == 3:  # nearly dependent rows: cond up to ~1e6
            J = np.stack([J[0], J[0] + 10.0 ** -rng.uniform(1, 3) * rng.normal(size=3)])
        A = J @ np.linalg.solve(M, J.T)
        ref, cond_ref = _damped_inverse_by_eigh(A, damping)
        Mx, cond = C.operational_inertia(jnp.asarray(M), jnp.asarray(J), damping)
        np.testing.assert_allclose(np.asarray(Mx), ref, rtol=1e-7 * cond_ref, atol=0)
        np.testing.assert_allclose(float(cond), cond_ref, rtol=1e-7 * cond_ref)
        if cond_ref < 100:
            Mx32, _ = C.operational_inertia(
                jnp.asarray(M, jnp.float32), jnp.asarray(J, jnp.float32), damping
            )
            assert Mx32.dtype == jnp.float32
            scale = np.max(np.abs(ref))
            np.testing.assert_allclose(np.asarray(Mx32), ref, atol=1e-4 * scale * cond_ref)


def test_solve_spd_matches_numpy_and_its_derivative_central_differences():
    """The unrolled Cholesky solve equals NumPy's LU solve on random SPD matrices (n = 1..5,
    condition numbers up to ~1e6) in float64, reads only the lower triangle, and its derivative in
    A and B equals central differences; float32 to its precision."""
    rng = np.random.default_rng(11)
    conds = []
    for n in range(1, 6):
        for k in range(10):
            Q, _ = np.linalg.qr(rng.normal(size=(n, n)))
            s = 10.0 ** rng.uniform(-3 * (k % 3), 0, size=n)
            if k % 3 == 2 and n > 1:
                s[0], s[-1] = 1.0, 1e-6  # the extremes of the range: cond ~1e6
            A = (Q * s) @ Q.T + 1e-7 * np.eye(n)  # eigenvalues 1e-6..1 (+1e-7): cond to ~1e6
            B = rng.normal(size=(n, 2))
            ref = np.linalg.solve(A, B)
            cond = np.linalg.cond(A)
            conds.append(cond)
            x = np.asarray(C.solve_spd(jnp.asarray(A), jnp.asarray(B)))
            np.testing.assert_allclose(x, ref, rtol=0, atol=1e-13 * cond * np.abs(ref).max())
            upper_garbage = np.triu(rng.normal(size=(n, n)), 1)  # only tril is read
            x_tril = np.asarray(C.solve_spd(jnp.asarray(np.tril(A) + upper_garbage), B))
            np.testing.assert_array_equal(x_tril, x)
            if cond < 100:
                x32 = C.solve_spd(jnp.asarray(A, jnp.float32), jnp.asarray(B, jnp.float32))
                assert x32.dtype == jnp.float32
                np.testing.assert_allclose(
                    np.asarray(x32), ref, atol=1e-5 * cond * np.abs(ref).max()
                )
    assert max(conds) > 5e5  # the claimed range was reached
    for bad_a, bad_b in ((np.eye(3)[:2], np.ones(3)), (np.eye(3), np.ones(2)), (np.eye(3), 1.0)):
        with pytest.raises(ValueError, match="need A"):
            C.solve_spd(jnp.asarray(bad_a), jnp.asarray(bad_b))
    A = jnp.asarray(np.array([[2.0, 0.3, 0.1], [0.3, 1.5, -0.2], [0.1, -0.2, 1.0]]))
    B = jnp.asarray(rng.normal(size=(3, 2)))
    W = jnp.asarray(rng.normal(size=(3, 2)))

    def f(A, B):  # symmetric use of A, as for M(theta)
        return jnp.sum(W * C.solve_spd(0.5 * (A + A.T), B))

    gA, gB = jax.grad(f, argnums=(0, 1))(A, B)
    ref_gA, ref_gB = jax.grad(
        lambda A, B: jnp.sum(W * jnp.linalg.solve(0.5 * (A + A.T), B)), argnums=(0, 1)
    )(A, B)
    np.testing.assert_allclose(np.asarray(gA), np.asarray(ref_gA), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(np.asarray(gB), np.asarray(ref_gB), rtol=1e-12, atol=1e-14)
    h = 1e-6
    e = jnp.zeros((3, 3)).at[2, 0].set(h)
    fd = (float(f(A + e, B)) - float(f(A - e, B))) / (2 * h)
    np.testing.assert_allclose(float(gA[2, 0]), fd, rtol=1e-7)
    with pytest.raises(ValueError, match="need A"):
        C.solve_spd(jnp.eye(3), jnp.zeros((2, 2)))


def test_operational_inertia_derivative_finite_at_equal_eigenvalues():
    """A = J M^-1 J^T = c I (equal eigenvalues, where the derivative of an eigendecomposition is
    singular): finite derivative, equal to central differences."""
    M = jnp.eye(3) * 2.0
    J = jnp.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # A = I / 2

    def f(J):
        return jnp.sum(C.operational_inertia(M, J, 1e-3)[0] * jnp.array([[1.0, 2.0], [3.0, 4.0]]))

    g = np.asarray(jax.grad(f)(J))
    assert np.all(np.isfinite(g))
    h = 1e-6
    fd = np.zeros((2, 3))
    for i in range(2):
        for j in range(3):
            e = jnp.zeros((2, 3)).at[i, j].set(h)
            fd[i, j] = (float(f(J + e)) - float(f(J - e))) / (2 * h)
    np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-8)


def _poly_path(a, b, c):
    return lambda t: a + b * t + c * t**2


def test_sphere_derivatives_match_autodiff():
    """dX_o', dX_o'' of Eq. 45 with n from Eq. 46 equal autodiff d/dt along a quadratic path."""
    rng = np.random.default_rng(3)
    r = 0.25
    for _ in range(5):
        a, b, c = (jnp.asarray(rng.normal(size=2) * s) for s in (0.2, 0.5, 2.0))
        path = _poly_path(a, b, c)

        def dxo(t, path=path):
            x = path(t)
            return x - r * x / jnp.linalg.norm(x)

        t0 = 0.1
        d1 = jax.jacfwd(dxo)(t0)
        d2 = jax.jacfwd(jax.jacfwd(dxo))(t0)
        x_r = path(t0)
        sk = C.sphere_kinematics(x_r, jax.jacfwd(path)(t0), jax.jacfwd(jax.jacfwd(path))(t0), r)
        np.testing.assert_allclose(np.asarray(sk.dx_o), np.asarray(dxo(t0)), rtol=1e-12)
        np.testing.assert_allclose(np.asarray(sk.dxd_o), np.asarray(d1), rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(np.asarray(sk.dxdd_o), np.asarray(d2), rtol=1e-9, atol=1e-10)


def test_virtual_force_signs_and_regions():
    """Eq. 47: zero outside and at the centre; K_o > 0 pushes the hand away from the object."""
    vp = C.virtual_params(0.0, 0.0, 300.0, 0.25)
    z = jnp.zeros(2)
    inside = C.sphere_kinematics(jnp.array([0.1, 0.05]), z, z, vp.r)
    f = C.virtual_force(vp, inside)
    assert float(jnp.dot(f, inside.x_r)) < 0  # pushes the hand (at the centre) away from X_o
    np.testing.assert_allclose(
        np.asarray(f), -300.0 * (0.25 - float(inside.rho)) * np.asarray(inside.n)
    )
    outside = C.sphere_kinematics(jnp.array([0.3, 0.0]), jnp.ones(2), z, vp.r)
    assert np.all(np.asarray(C.virtual_force(vp, outside)) == 0)
    centre = C.sphere_kinematics(z, jnp.ones(2), jnp.ones(2), vp.r)
    assert np.all(np.asarray(C.virtual_force(vp, centre)) == 0)
    g = jax.grad(lambda x: C.virtual_force(vp, C.sphere_kinematics(x, z, z, vp.r)).sum())(z)
    assert np.all(np.isfinite(np.asarray(g)))  # NaN-safe at X_r = 0


@settings(max_examples=50, deadline=None)
@given(
    # No subnormals: XLA on CPU flushes them to zero (so 2e-309 would come back as 0.0).
    st.lists(st.floats(-50, 50, allow_subnormal=False), min_size=6, max_size=6),
    st.lists(st.floats(0.01, 50, allow_subnormal=False), min_size=3, max_size=3),
)
def test_eq49_projection(vals, target):
    """project_stable lands in the strict stable set, is idempotent and keeps stable values."""
    m_o, b_o, k_o = (jnp.asarray(vals[2 * i : 2 * i + 2]) for i in range(3))
    m_e, b_e, k_e = (jnp.full(2, t) for t in target)
    vp = C.VirtualParams(m_o, b_o, k_o, jnp.asarray(0.25))
    pr = C.project_stable(vp, m_e, b_e, k_e)
    assert np.all(np.asarray(C.is_stable(m_e, b_e, k_e, pr.m_o, pr.b_o, pr.k_o)))
    pr2 = C.project_stable(pr, m_e, b_e, k_e)
    for x, y in zip(pr[:3], pr2[:3], strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    stable = np.asarray(C.is_stable(m_e, b_e, k_e, vp.m_o, vp.b_o, vp.k_o))
    kept = (np.asarray(vp.m_o) >= -0.999 * np.asarray(m_e)) & (
        np.asarray(vp.b_o) >= -0.999 * np.asarray(b_e)
    )
    kept &= np.asarray(vp.k_o) >= -0.999 * np.asarray(k_e)
    for name in ("m_o", "b_o", "k_o"):  # all three kept, not only M_o
        assert np.all(np.asarray(getattr(pr, name))[kept] == np.asarray(getattr(vp, name))[kept])
    assert np.all(stable[kept])


def test_eq49_printed_condition_not_sufficient():
    """K_o = -K_e alone satisfies the printed '>=' but leaves a pole at s = 0: not strictly stable.
    The strict form agrees with the poles of (M_o + M_e) s^2 + (B_o + B_e) s + (K_o + K_e)
    (NumPy's roots) on random virtual impedances, about half of them unstable."""
    one = jnp.ones(2)
    assert not np.any(
        np.asarray(C.is_stable(one, 40 * one, 400 * one, 0 * one, 0 * one, -400 * one))
    )
    rng = np.random.default_rng(9)
    m_e, b_e, k_e = 1.0, 40.0, 400.0
    m_o = rng.uniform(-0.9, 1.0, 400)  # M_o + M_e > 0: a positive mass, Eq. 48 as written
    b_o, k_o = rng.uniform(-60.0, 20.0, 400), rng.uniform(-600.0, 200.0, 400)
    poles_left = [
        bool(np.all(np.roots([m + m_e, b + b_e, k + k_e]).real < 0))
        for m, b, k in zip(m_o, b_o, k_o, strict=True)
    ]
    got = np.asarray(
        C.is_stable(m_e, b_e, k_e, jnp.asarray(m_o), jnp.asarray(b_o), jnp.asarray(k_o))
    )
    np.testing.assert_array_equal(got, poles_left)
    assert 0.2 < np.mean(poles_left) < 0.8


def test_validation_errors():
    with pytest.raises(ValueError):
        C.impedance_params(0.0, 40.0, 400.0)
    with pytest.raises(ValueError):
        C.impedance_params(1.0, -1.0, 400.0)
    with pytest.raises(ValueError):
        C.impedance_params(1.0, 40.0, -1.0)
    with pytest.raises(ValueError):
        C.impedance_params(np.ones(3), 40.0, 400.0)
    with pytest.raises(ValueError):
        C.virtual_params(0.0, 0.0, 100.0, 0.0)
    with pytest.raises(ValueError):
        C.virtual_params(np.nan, 0.0, 100.0, 0.25)
    with pytest.raises(ValueError, match="mx_damping"):
        C.ControllerConfig(mx_damping=-1.0)
    with pytest.raises(ValueError, match="dt"):
        C.make_impedance_controller(0.0, TORQUE_LIMIT)
    with pytest.raises(ValueError, match="torque_limit"):
        C.make_impedance_controller(DT, (100.0, 60.0))
    with pytest.raises(ValueError):
        C.fixed_target([0.1, 0.2, 0.3])
    init, apply = C.make_impedance_controller(DT, TORQUE_LIMIT)
    obs = _random_obs(np.random.default_rng(4))
    with pytest.raises(ValueError):
        init(obs._replace(J=jnp.zeros((3, 3))))
    st0 = init(obs)
    p = C.impedance_params(1.0, 40.0, 400.0)
    vp = C.virtual_params(0.0, 0.0, 0.0, 0.25)
    with pytest.raises(ValueError):
        apply(p, vp, C.fixed_target([0.0, 0.0]), st0, obs._replace(f_int=jnp.zeros(3)))


def test_a_singular_jacobian_without_damping_is_flagged_not_hidden():
    """With ``mx_damping`` = 0 a singular J (a straight arm) has no operational inertia: M_x is
    0/0 and the torques are NaN. The info says so (``mx_cond`` inf, ``saturated`` True: a NaN
    torque is not "within the limit"); the default damping gives finite torques there."""
    obs = _random_obs(np.random.default_rng(6), f_int=np.zeros(2))
    obs = obs._replace(J=jnp.array([[1.0, 0.5, 0.25], [0.0, 0.0, 0.0]]))  # rank 1
    p = C.impedance_params(1.0, 40.0, 400.0)
    vp = C.virtual_params(0.0, 0.0, 0.0, 0.25)
    tgt = C.fixed_target([0.0, 0.0])
    for damping, finite in ((0.0, False), (C.ControllerConfig().mx_damping, True)):
        init, apply = C.make_impedance_controller(
            DT, TORQUE_LIMIT, C.ControllerConfig(mx_damping=damping)
        )
        _, _, info = apply(p, vp, tgt, init(obs), obs)
        assert bool(jnp.all(jnp.isfinite(info.tau_cmd))) == finite
        over = bool(np.any(np.abs(np.asarray(info.tau_cmd)) > np.asarray(TORQUE_LIMIT)))
        assert bool(info.saturated) == (over or not finite) and np.isinf(info.mx_cond)


def test_controller_jit_vmap_grad():
    """apply works under jit, vmap (over parameters) and grad (w.r.t. K_e), with finite values."""
    init, apply = C.make_impedance_controller(DT, TORQUE_LIMIT)
    obs = _random_obs(np.random.default_rng(5))
    st0 = init(obs)
    vp = C.virtual_params(0.5, 5.0, 300.0, 5.0)  # object inside a large sphere
    tgt = C.fixed_target([0.0, 0.0])

    def tau_of(k_e):
        p = C.ImpedanceParams(jnp.ones(2), 40.0 * jnp.ones(2), k_e)
        return apply(p, vp, tgt, st0, obs)[2].tau_cmd  # before saturation

    t_jit = jax.jit(tau_of)(400.0 * jnp.ones(2))
    t_vmap = jax.vmap(tau_of)(jnp.stack([400.0 * jnp.ones(2), 200.0 * jnp.ones(2)]))
    np.testing.assert_allclose(np.asarray(t_vmap[0]), np.asarray(t_jit), rtol=1e-12)
    g = jax.jacfwd(tau_of)(400.0 * jnp.ones(2))
    # d tau / d K_e = J^T M_x M_e^-1 (-dX) (Eq. 42), independent of everything else; M_x the
    # damped inverse of Eq. 44 (default damping 1e-3) from NumPy's eigh, not the code's
    J, M = np.asarray(obs.J), np.asarray(obs.M)
    Mx, _ = _damped_inverse_by_eigh(J @ np.linalg.solve(M, J.T), C.ControllerConfig().mx_damping)
    expected = J.T @ Mx @ np.diag(-np.asarray(obs.x_e))
    np.testing.assert_allclose(np.asarray(g), expected, rtol=1e-9)


@pytest.mark.parametrize("field", ["x_o", "xd_o", "xdd_o"])
@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_a_non_finite_object_estimate_gives_no_virtual_force(field, bad):
    """A NaN/inf object estimate (a lost eye): F_o = 0 and the torque is plain impedance
    control's, finite; a finite estimate inside the sphere gives a non-zero F_o."""
    init, apply = C.make_impedance_controller(DT, TORQUE_LIMIT)
    obs = _random_obs(np.random.default_rng(6))
    obs = obs._replace(x_o=obs.x_e + jnp.array([0.1, 0.0]), xdd_o=jnp.zeros(2))
    st0 = init(obs)
    p = C.impedance_params(1.0, 40.0, 400.0)
    vp = C.virtual_params(0.2, 5.0, 100.0, 0.25)
    tgt = C.fixed_target([0.0, 0.0])
    _, _, info = apply(p, vp, tgt, st0, obs)
    assert np.all(np.asarray(info.f_o) != 0.0)
    bad_obs = obs._replace(**{field: getattr(obs, field).at[0].set(bad)})
    tau, _, info = apply(p, vp, tgt, st0, bad_obs)
    tau_plain, _, _ = apply(p, C.virtual_params(0.0, 0.0, 0.0, 0.25), tgt, st0, obs)
    np.testing.assert_array_equal(info.f_o, 0.0)
    assert np.all(np.isfinite(tau))
    np.testing.assert_allclose(tau, tau_plain, rtol=1e-12)


def test_dt_elapsed_spans_the_backward_differences():
    """``dt_elapsed``: X_e'' and X_o'' (differenced when the observation has no X_o'') over the
    time since the previous call, hand-computed; None is ``dt`` bit for bit."""
    init, apply = C.make_impedance_controller(DT, TORQUE_LIMIT)
    rng = np.random.default_rng(9)
    obs = _random_obs(rng)
    obs = obs._replace(x_o=obs.x_e + jnp.array([0.1, 0.05]))  # inside the sphere
    st0 = init(obs)._replace(
        xd_e_prev=obs.xd_e - jnp.array([0.02, -0.01]), xd_o_prev=obs.xd_o - jnp.array([0.03, 0.04])
    )
    p = C.impedance_params(1.0, 40.0, 400.0)
    vp = C.virtual_params(0.2, 5.0, 100.0, 0.25)
    tgt = C.fixed_target([0.0, 0.0])
    _, _, info = apply(p, vp, tgt, st0, obs, 4 * DT)
    np.testing.assert_allclose(info.xdd_e, np.array([0.02, -0.01]) / (4 * DT), rtol=1e-12)
    # X_o'' too: the one-step call from velocities a quarter of the way back gives the same F_o
    quarter = st0._replace(
        xd_e_prev=obs.xd_e - jnp.array([0.02, -0.01]) / 4,
        xd_o_prev=obs.xd_o - jnp.array([0.03, 0.04]) / 4,
    )
    _, _, info_quarter = apply(p, vp, tgt, quarter, obs)
    np.testing.assert_allclose(info.f_o, info_quarter.f_o, rtol=1e-9)
    one = apply(p, vp, tgt, st0, obs)
    same = apply(p, vp, tgt, st0, obs, DT)
    for a, b in zip(jax.tree.leaves(one), jax.tree.leaves(same), strict=True):
        np.testing.assert_array_equal(a, b)
    assert np.all(np.asarray(one[2].f_o) != np.asarray(info.f_o))
