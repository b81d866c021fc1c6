"""The paper's motion estimation (Eqs. 7-38) against synthetic ground truth."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hec_jax.geometry import estimate_motion, make_cube_scenes, rotation_error_deg
from hec_jax.geometry import parallel_motion as pm
from hec_jax.geometry.synthetic import random_rotation, rotation_from_axis_angle

N_SCENES = 2000
EDGE = 0.1  # [m]


@pytest.fixture(scope="module")
def scenes():
    return make_cube_scenes(np.random.default_rng(0), N_SCENES, motion="mixed")


def _truth(scenes):
    """Ground-truth 3D A, B, C, D before/after (n, 4, 3)."""
    idx = (np.arange(len(scenes.pair))[:, None], scenes.pair)
    return scenes.corners_before[idx], scenes.corners_after[idx]


def _true_t(p):
    """t = m3 / (Z + m3) (Eq. 7) of l1 (A->B) and l2 (C->D) from 3D points (n, 4, 3)."""
    z = p[..., 2]
    return (z[:, 1] - z[:, 0]) / z[:, 1], (z[:, 3] - z[:, 2]) / z[:, 3]


# --- each equation on its own -------------------------------------------------------------------


def test_eq20_21_corrected_t_matches_truth_and_printed_eq20_does_not(scenes):
    pb, _ = _truth(scenes)
    t1, t2, ok = pm.parallel_t(jnp.asarray(scenes.points_before))
    t1_true, t2_true = _true_t(pb)
    assert np.all(ok)
    np.testing.assert_allclose(t1, t1_true, atol=1e-10)
    np.testing.assert_allclose(t2, t2_true, atol=1e-10)
    # Eq. 20 as printed (denominator "- r1 y1") is wrong.
    (x1, y1), (r1, s1), (x2, y2), (r2, s2) = (
        (np.asarray(v[..., 0]), np.asarray(v[..., 1]))
        for v in pm.segment_parameters(jnp.asarray(scenes.points_before))
    )
    t1_printed = (r2 * s1 - r1 * s2) / (s2 * x1 - s2 * x2 + r2 * y2 - r1 * y1)
    assert np.median(np.abs(t1_printed - t1_true)) > 1e-3


def test_eq8_eq13_eq14_direction_vectors_and_k(scenes):
    pb, pa = _truth(scenes)
    before, after = jnp.asarray(scenes.points_before), jnp.asarray(scenes.points_after)
    for seg, (i, j) in enumerate(((0, 1), (2, 3))):
        base, delta = pm.segment_parameters(before)[2 * seg : 2 * seg + 2]
        base_a, delta_a = pm.segment_parameters(after)[2 * seg : 2 * seg + 2]
        t = pm.parallel_t(before)[seg]
        t_a = pm.parallel_t(after)[seg]
        n, n_a = pm.direction_vector(base, delta, t), pm.direction_vector(base_a, delta_a, t_a)
        m, m_a = pb[:, j] - pb[:, i], pa[:, j] - pa[:, i]
        np.testing.assert_allclose(n, m / pb[:, j, 2:], atol=1e-10)  # Eq. 8: N = M / (Z + m3)
        np.testing.assert_allclose(n_a, m_a / pa[:, j, 2:], atol=1e-10)  # Eq. 9
        np.testing.assert_allclose(m_a, np.einsum("nij,nj->ni", scenes.rotation, m), atol=1e-12)
        k = pm.length_ratio(n, n_a)
        np.testing.assert_allclose(k, pa[:, j, 2] / pb[:, j, 2], rtol=1e-9)  # Eq. 13
        lhs = np.asarray(k)[:, None] * np.asarray(n_a)  # Eq. 14: K N' = Phi N
        rhs = np.einsum("nij,nj->ni", scenes.rotation, np.asarray(n))
        np.testing.assert_allclose(lhs, rhs, atol=1e-10)


def test_virtual_lines_eqs25_28_and_k3_k4_eqs29_33(scenes):
    pb, pa = _truth(scenes)
    before, after = jnp.asarray(scenes.points_before), jnp.asarray(scenes.points_after)
    v = pm.virtual_lines(before)
    np.testing.assert_array_equal(v[:, 0], before[:, 2])  # l3 from C ...
    np.testing.assert_array_equal(v[:, 1], before[:, 0])  # ... to A
    np.testing.assert_array_equal(v[:, 2], before[:, 3])  # l4 from D ...
    np.testing.assert_array_equal(v[:, 3], before[:, 1])  # ... to B
    # Eq. 29 with primes restored: K3 = (Z3' + mu3') / (Z3 + mu3) = Z_A' / Z_A (end of l3 is A).
    k3_true = pa[:, 0, 2] / pb[:, 0, 2]
    t1, _, _ = pm.parallel_t(before)
    t1_a, _, _ = pm.parallel_t(after)
    k1 = pa[:, 1, 2] / pb[:, 1, 2]
    np.testing.assert_allclose(pm.virtual_k3(t1, t1_a, jnp.asarray(k1)), k3_true, rtol=1e-9)
    # Eq. 33: K4 = K1. K4 from l4's own image points (D -> B) and its true t4 = (Z_B - Z_D) / Z_B
    # through Eq. 13, against K1 as the code forms it from l1 (image points and Eq. 20's t1).
    _, _, b4, d4 = pm.segment_parameters(v)
    _, _, b4_a, d4_a = pm.segment_parameters(pm.virtual_lines(after))
    t4 = (pb[:, 1, 2] - pb[:, 3, 2]) / pb[:, 1, 2]
    t4_a = (pa[:, 1, 2] - pa[:, 3, 2]) / pa[:, 1, 2]
    k4 = pm.length_ratio(pm.direction_vector(b4, d4, t4), pm.direction_vector(b4_a, d4_a, t4_a))
    a, ab, _, _ = pm.segment_parameters(before)
    a_a, ab_a, _, _ = pm.segment_parameters(after)
    k1_code = pm.length_ratio(pm.direction_vector(a, ab, t1), pm.direction_vector(a_a, ab_a, t1_a))
    np.testing.assert_allclose(k4, k1_code, rtol=1e-9)
    np.testing.assert_allclose(k4, k1, rtol=1e-9)  # both the end point's depth ratio Z_B'/Z_B


def test_eqs37_38_true_t3_is_one_of_the_two_roots(scenes):
    pb, pa = _truth(scenes)
    before, after = jnp.asarray(scenes.points_before), jnp.asarray(scenes.points_after)
    t1, t2, _ = pm.parallel_t(before)
    t1_a, _, _ = pm.parallel_t(after)
    a, ab, _, _ = pm.segment_parameters(before)
    a_a, ab_a, _, _ = pm.segment_parameters(after)
    n1, n1_a = pm.direction_vector(a, ab, t1), pm.direction_vector(a_a, ab_a, t1_a)
    k1 = pm.length_ratio(n1, n1_a)
    beta = (1.0 - t1_a) / (1.0 - t1)
    b3, d3, _, _ = pm.segment_parameters(pm.virtual_lines(before))
    b3_a, d3_a, _, _ = pm.segment_parameters(pm.virtual_lines(after))
    roots = pm.solve_virtual_t3(n1, n1_a, k1, beta, b3, d3, b3_a, d3_a)
    # l3 runs from C to A: t3 = (Z_A - Z_C) / Z_A.
    t3_true = (pb[:, 0, 2] - pb[:, 2, 2]) / pb[:, 0, 2]
    t3a_true = (pa[:, 0, 2] - pa[:, 2, 2]) / pa[:, 0, 2]
    gap = np.min(
        np.abs(np.asarray(roots.t3) - t3_true[:, None])
        + np.abs(np.asarray(roots.t3_after) - t3a_true[:, None]),
        axis=-1,
    )
    assert np.percentile(gap, 99) < 1e-8
    assert np.all(roots.discriminant > 0)
    # Both roots satisfy Eqs. 37 and 38 (the quadratic is exact).
    for i in range(2):
        n3 = pm.direction_vector(b3, d3, roots.t3[:, i])
        n3_a = pm.direction_vector(b3_a, d3_a, roots.t3_after[:, i])
        k3 = beta * k1
        eq37 = (k3**2) * jnp.sum(n3_a**2, -1) - jnp.sum(n3**2, -1)
        eq38 = k1 * k3 * jnp.sum(n1_a * n3_a, -1) - jnp.sum(n1 * n3, -1)
        assert np.percentile(np.abs(eq37), 99) < 1e-9
        assert np.percentile(np.abs(eq38), 99) < 1e-9


def test_procrustes_recovers_rotation():
    rng = np.random.default_rng(3)
    rot = random_rotation(rng, (50,))
    x = rng.normal(size=(50, 5, 3))
    y = np.einsum("nij,nkj->nki", rot, x)
    np.testing.assert_allclose(
        pm.procrustes_rotation(jnp.asarray(x), jnp.asarray(y)), rot, atol=1e-12
    )


# --- the whole estimate -------------------------------------------------------------------------


def test_noise_free_float64_exact_and_root_choice_always_right(scenes):
    pb, pa = _truth(scenes)
    est = estimate_motion(scenes.points_before, scenes.points_after, EDGE)
    assert np.all(est.valid)
    err = rotation_error_deg(np.asarray(est.rotation), scenes.rotation)
    assert np.percentile(err, 99) < 1e-6
    # Root choice: every scene reconstructs the true metric points (a wrong root moves C, D by cm).
    np.testing.assert_allclose(est.points_before, pb, atol=1e-7)
    np.testing.assert_allclose(est.points_after, pa, atol=1e-7)
    np.testing.assert_allclose(est.translation, scenes.translation, atol=1e-7)
    assert not np.any(est.ambiguous)
    assert np.max(est.residual) < 1e-9


def test_without_length_units_are_ab(scenes):
    pb, _ = _truth(scenes)
    est = estimate_motion(scenes.points_before, scenes.points_after)
    np.testing.assert_allclose(est.points_before, pb / EDGE, atol=1e-6)
    np.testing.assert_allclose(est.translation, scenes.translation / EDGE, atol=1e-6)


def test_per_element_length(scenes):
    lengths = np.full(N_SCENES, EDGE) * np.where(np.arange(N_SCENES) % 2 == 0, 1.0, 2.0)
    est = estimate_motion(scenes.points_before, scenes.points_after, lengths)
    pb, _ = _truth(scenes)
    np.testing.assert_allclose(est.points_before, pb * (lengths / EDGE)[:, None, None], atol=1e-7)


def test_noise_free_float32_is_limited_by_input_rounding_only(scenes):
    """float32: the paper's method loses ~100 deg of rotation per pixel of image noise, and rounding
    normalised coordinates to float32 is ~2e-5 px of noise, so no float32 computation can beat the
    float64 computation on the same float32-rounded inputs. We require the float32 computation to stay
    within 1.5x of that floor (median and 99th percentile)."""
    b32 = scenes.points_before.astype(np.float32)
    a32 = scenes.points_after.astype(np.float32)
    est32 = estimate_motion(b32, a32, np.float32(EDGE), residual_tol=None)
    assert est32.rotation.dtype == jnp.float32
    floor = estimate_motion(b32.astype(np.float64), a32.astype(np.float64), EDGE, residual_tol=None)
    err32 = rotation_error_deg(np.asarray(est32.rotation), scenes.rotation)
    err_floor = rotation_error_deg(np.asarray(floor.rotation), scenes.rotation)
    assert np.mean(est32.valid) > 0.99
    assert np.median(err32) < 1e-3
    assert np.median(err32) < 1.5 * np.median(err_floor)
    assert np.percentile(err32, 99) < 1.5 * np.percentile(err_floor, 99)


POLISH_STEPS = 4  # Gauss-Newton steps of the reprojection polish (converged on noise-free data)


def test_noise_free_float32_with_polish_meets_0_01_deg_at_p99(scenes):
    """The issue's float32 point (noise-free rotation error p99 < 0.01 deg) holds for the closed form
    followed by the reprojection polish (``polish_steps``), not for the closed form alone: its floor
    (float64 arithmetic on the same float32-rounded inputs) is 0.03 deg, because it ignores the one
    image constraint it does not use and amplifies rounding along it; the polish (maximum
    likelihood over all 16 image numbers) removes that."""
    b32 = scenes.points_before.astype(np.float32)
    a32 = scenes.points_after.astype(np.float32)
    est = estimate_motion(b32, a32, np.float32(EDGE), residual_tol=None, polish_steps=POLISH_STEPS)
    assert est.rotation.dtype == jnp.float32
    assert np.mean(est.valid) > 0.99
    err = rotation_error_deg(np.asarray(est.rotation), scenes.rotation)
    assert np.percentile(err, 99) < 0.01
    assert np.median(err) < 1e-3
    closed_floor = estimate_motion(
        b32.astype(np.float64), a32.astype(np.float64), EDGE, residual_tol=None
    )
    assert (
        np.percentile(rotation_error_deg(np.asarray(closed_floor.rotation), scenes.rotation), 99)
        > 0.01
    )


def test_polish_float64_exact_and_model_consistent(scenes):
    pb, pa = _truth(scenes)
    est = estimate_motion(
        scenes.points_before, scenes.points_after, EDGE, polish_steps=POLISH_STEPS
    )
    closed = estimate_motion(scenes.points_before, scenes.points_after, EDGE)
    np.testing.assert_array_equal(est.valid, closed.valid)
    np.testing.assert_array_equal(est.residual, closed.residual)  # the closed form's, kept
    err = rotation_error_deg(np.asarray(est.rotation), scenes.rotation)
    assert np.percentile(err, 99) < 1e-6
    np.testing.assert_allclose(est.points_before, pb, atol=1e-7)
    np.testing.assert_allclose(est.points_after, pa, atol=1e-7)
    np.testing.assert_allclose(est.translation, scenes.translation, atol=1e-7)
    # The polished points are the model: |AB| = L, CD parallel to AB, P' = Phi P + Gamma.
    p, p_a = np.asarray(est.points_before), np.asarray(est.points_after)
    ab, cd = p[:, 1] - p[:, 0], p[:, 3] - p[:, 2]
    np.testing.assert_allclose(np.linalg.norm(ab, axis=-1), EDGE, rtol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(np.cross(ab, cd), axis=-1), 0.0, atol=1e-14)
    moved = (
        np.einsum("nij,nkj->nki", np.asarray(est.rotation), p)
        + np.asarray(est.translation)[:, None]
    )
    np.testing.assert_allclose(moved, p_a, atol=1e-12)


def test_procrustes_gradient_with_equal_singular_values():
    """On exact data h = R S with S symmetric, often with equal singular values; the rotation's
    derivative must still be the exact one (the SVD's own derivative divides by s_i^2 - s_j^2)."""
    rot = jnp.asarray(rotation_from_axis_angle([1.0, 2.0, 3.0], 0.4))
    x = jnp.eye(3)  # S = I: all three singular values equal
    y = x @ rot.T

    def f(y):
        return jnp.sum(pm.procrustes_rotation(x, y) * jnp.arange(9.0).reshape(3, 3))

    g = jax.grad(f)(y)
    h = 1e-6
    fd = np.zeros((3, 3))
    for i in range(3):
        for j in range(3):
            e = jnp.zeros((3, 3)).at[i, j].set(h)
            fd[i, j] = (f(y + e) - f(y - e)) / (2 * h)
    assert np.all(np.isfinite(np.asarray(g)))
    np.testing.assert_allclose(g, fd, atol=1e-7)


def test_axis_parallel_to_segments():
    """Pure rotation about an axis parallel to AB (docs/paper_readings.md#eq-37-38: the second root is exactly Phi = I).

    Measured here: the Phi = I root puts points behind the camera, so the depth rule rejects it and
    the estimate is right and not ambiguous; a prior does not override an unambiguous choice."""
    a, b = np.array([-0.05, 0.02, 1.0]), np.array([0.05, 0.03, 1.02])
    c = a + np.array([0.0, 0.1, 0.01])
    pts = np.stack([a, b, c, c + (b - a)])
    rot = rotation_from_axis_angle(b - a, 0.2)
    centre = pts.mean(0)
    pts_a = (pts - centre) @ rot.T + centre
    proj = lambda p: jnp.asarray(p[:, :2] / p[:, 2:])  # noqa: E731
    before, after = proj(pts), proj(pts_a)
    t1, t2, _ = pm.parallel_t(before)
    t1_a, t2_a, _ = pm.parallel_t(after)
    n1 = pm.direction_vector(before[0], before[1] - before[0], t1)
    n1_a = pm.direction_vector(after[0], after[1] - after[0], t1_a)
    k1 = pm.length_ratio(n1, n1_a)
    b3, d3, _, _ = pm.segment_parameters(pm.virtual_lines(before))
    b3_a, d3_a, _, _ = pm.segment_parameters(pm.virtual_lines(after))
    roots = pm.solve_virtual_t3(n1, n1_a, k1, (1 - t1_a) / (1 - t1), b3, d3, b3_a, d3_a)
    cands = [
        pm._candidate(
            before, after, t1, t2, t1_a, t2_a, roots.t3[i], roots.t3_after[i], k1, jnp.asarray(EDGE)
        )
        for i in range(2)
    ]
    identity_root = [rotation_error_deg(np.asarray(c[0]), np.eye(3)) < 1e-6 for c in cands]
    assert sum(identity_root) == 1
    assert not bool(cands[identity_root.index(True)][5])  # negative depth
    for prior in (None, np.eye(3)):
        est = estimate_motion(before, after, EDGE, prior_rotation=prior)
        assert bool(est.valid) and not bool(est.ambiguous)
        assert rotation_error_deg(np.asarray(est.rotation), rot) < 1e-9


# --- degenerate configurations ------------------------------------------------------------------


def _assert_finite(est):
    for leaf in jax.tree_util.tree_leaves(est):
        assert np.all(np.isfinite(np.asarray(leaf, dtype=float)))


def _single(scenes, i=0):
    return scenes.points_before[i], scenes.points_after[i]


def test_plane_through_camera_centre_is_invalid():
    # A, B, C, D on the plane y = 0.1 z: image lines collinear.
    pts = np.array([[0.0, 0.1, 1.0], [0.1, 0.11, 1.1], [0.05, 0.1, 1.0], [0.15, 0.11, 1.1]])
    rot = rotation_from_axis_angle([1.0, 2.0, 3.0], 0.1)
    pts_a = pts @ rot.T + np.array([0.01, 0.0, 0.02])
    est = estimate_motion(pts[:, :2] / pts[:, 2:], pts_a[:, :2] / pts_a[:, 2:], EDGE)
    assert not bool(est.valid)
    _assert_finite(est)


def test_zero_motion_is_invalid(scenes):
    before, _ = _single(scenes)
    est = estimate_motion(before, before, EDGE)
    assert not bool(est.valid)
    _assert_finite(est)


def test_zero_length_segment_is_invalid(scenes):
    before, after = (x.copy() for x in _single(scenes))
    before[1] = before[0]
    after[1] = after[0]
    est = estimate_motion(before, after, EDGE)
    assert not bool(est.valid)
    _assert_finite(est)


def test_non_parallel_segments_are_detected(scenes):
    """Two views of four points carry one constraint beyond Eqs. 18-38 (the rigidity residual), so
    a non-parallel pair shows up only as a residual, in proportion to how much the motion reveals.
    With a tolerance suited to noise-free data every tilted pair is rejected; the default tolerance
    (0.05, sized for image noise) rejects most of them."""
    pb, _ = _truth(scenes)
    rng = np.random.default_rng(7)
    residuals, valid_default = [], []
    for i in range(20):
        tilt = rotation_from_axis_angle(rng.normal(size=3), np.radians(20.0))
        q = pb[i].copy()
        q[3] = q[2] + tilt @ (q[3] - q[2])  # D off the parallel direction
        q_a = q @ scenes.rotation[i].T + scenes.translation[i]
        before, after = q[:, :2] / q[:, 2:], q_a[:, :2] / q_a[:, 2:]
        strict = estimate_motion(before, after, EDGE, residual_tol=1e-6)
        _assert_finite(strict)
        assert not bool(strict.valid)
        residuals.append(float(estimate_motion(before, after, EDGE, residual_tol=None).residual))
        valid_default.append(bool(estimate_motion(before, after, EDGE).valid))
    assert min(residuals) > 1e-4  # vs < 1e-9 for parallel pairs
    assert sum(valid_default) <= 10


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_polish_on_degenerate_input_stays_invalid_and_finite(scenes, dtype):
    before, after = (np.asarray(x, dtype) for x in _single(scenes))
    zero_len_b, zero_len_a = before.copy(), after.copy()
    zero_len_b[1], zero_len_a[1] = zero_len_b[0], zero_len_a[0]
    for b, a in ((before, before), (zero_len_b, zero_len_a)):
        est = estimate_motion(b, a, dtype(EDGE), polish_steps=POLISH_STEPS)
        assert not bool(est.valid)
        _assert_finite(est)


def test_point_behind_camera_is_invalid(scenes):
    pb, _ = _truth(scenes)
    # Put B behind the camera (negative depth): its projection flips through the origin.
    q = pb[0].copy()
    q[1] = q[0] + np.array([0.0, 0.0, -3.0])
    q[3] = q[2] + np.array([0.0, 0.0, -3.0])
    rot = rotation_from_axis_angle([0.3, 1.0, 0.2], 0.05)
    q_a = q @ rot.T + np.array([0.01, 0.02, 0.0])
    est = estimate_motion(q[:, :2] / q[:, 2:], q_a[:, :2] / q_a[:, 2:], EDGE)
    assert not bool(est.valid)
    _assert_finite(est)


def _project(p):
    return p[..., :2] / p[..., 2:]


def _no_real_root(before, after):
    """(n,) bool: the quadratic of Eqs. 37-38 has no real root (negative discriminant)."""
    before, after = jnp.asarray(before), jnp.asarray(after)
    t1, _, _ = pm.parallel_t(before)
    t1_a, _, _ = pm.parallel_t(after)
    a, ab, _, _ = pm.segment_parameters(before)
    a_a, ab_a, _, _ = pm.segment_parameters(after)
    n1, n1_a = pm.direction_vector(a, ab, t1), pm.direction_vector(a_a, ab_a, t1_a)
    b3, d3, _, _ = pm.segment_parameters(pm.virtual_lines(before))
    b3_a, d3_a, _, _ = pm.segment_parameters(pm.virtual_lines(after))
    roots = pm.solve_virtual_t3(
        n1, n1_a, pm.length_ratio(n1, n1_a), (1 - t1_a) / (1 - t1), b3, d3, b3_a, d3_a
    )
    c2, c1, c0 = (np.asarray(roots.coefficients[:, i]) for i in range(3))
    return c1**2 - 4 * c2 * c0 < -1e-6 * (c1**2 + 4 * np.abs(c2 * c0))


def test_no_real_root_is_invalid():
    """Under heavy noise the quadratic often has no real root: those must be invalid and finite."""
    noisy = make_cube_scenes(np.random.default_rng(11), N_SCENES, motion="small", noise_px=2.0)
    before, after = jnp.asarray(noisy.points_before), jnp.asarray(noisy.points_after)
    est = estimate_motion(before, after, EDGE, residual_tol=None)
    no_root = _no_real_root(before, after)
    assert no_root.sum() > 10  # the case occurs
    assert not np.any(np.asarray(est.valid)[no_root])
    _assert_finite(est)


def test_discriminant_tol_accepts_the_clamped_roots_and_changes_nothing_else():
    """``discriminant_tol`` (not the paper; ``--eye paper``): with it most scenes without a real
    root get the clamped candidates; every estimate valid without it is unchanged."""
    noisy = make_cube_scenes(np.random.default_rng(11), N_SCENES, motion="small", noise_px=0.5)
    before, after = jnp.asarray(noisy.points_before), jnp.asarray(noisy.points_after)
    strict = estimate_motion(before, after, EDGE, residual_tol=None)
    loose = estimate_motion(before, after, EDGE, residual_tol=None, discriminant_tol=1.0)
    no_root = _no_real_root(before, after)
    assert no_root.sum() > 10
    v_strict, v_loose = np.asarray(strict.valid), np.asarray(loose.valid)
    assert not v_strict[no_root].any() and v_loose[no_root].mean() > 0.9  # measured: 0.996
    assert v_loose[v_strict].all()  # only more scenes valid, the same estimates
    for a, b in zip(strict, loose, strict=True):
        np.testing.assert_array_equal(np.asarray(a)[v_strict], np.asarray(b)[v_strict])
    with pytest.raises(ValueError, match="discriminant_tol"):
        estimate_motion(before, after, EDGE, discriminant_tol=-1.0)


# --- malformed input ----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("before", "after", "length", "match"),
    [
        (np.zeros((3, 2)), np.zeros((3, 2)), None, "shape"),
        (np.zeros((4, 3)), np.zeros((4, 3)), None, "shape"),
        (np.zeros((4, 2)), np.zeros((2, 4, 2)), None, "same shape"),
        (np.zeros((4, 2), np.int32), np.zeros((4, 2), np.int32), None, "float"),
        (np.full((4, 2), np.nan), np.zeros((4, 2)), None, "non-finite"),
        (np.zeros((4, 2)), np.full((4, 2), np.inf), None, "non-finite"),
        (np.zeros((4, 2)), np.zeros((4, 2)), -1.0, "positive"),
        (np.zeros((5, 4, 2)), np.zeros((5, 4, 2)), np.ones(3), "length"),
    ],
)
def test_malformed_input_raises(before, after, length, match):
    with pytest.raises(ValueError, match=match):
        estimate_motion(before, after, length)


def test_mismatched_dtype_raises():
    with pytest.raises(ValueError, match="dtype"):
        estimate_motion(np.zeros((4, 2), np.float32), np.zeros((4, 2)))


@pytest.mark.parametrize("steps", [2.5, -1, True, "3"])
def test_polish_steps_must_be_a_count(steps):
    with pytest.raises(ValueError, match="polish_steps"):
        estimate_motion(np.zeros((4, 2)), np.zeros((4, 2)), polish_steps=steps)


# --- properties ---------------------------------------------------------------------------------


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 2**31 - 1),
    noise=st.sampled_from([0.0, 0.25, 1.0, 5.0]),
    motion=st.sampled_from(["small", "large"]),
)
def test_property_random_scenes(seed, noise, motion):
    s = make_cube_scenes(np.random.default_rng(seed), 64, motion=motion, noise_px=noise)
    est = estimate_motion(s.points_before, s.points_after, EDGE)
    _assert_finite(est)
    valid = np.asarray(est.valid)
    rot = np.asarray(est.rotation)[valid]
    np.testing.assert_allclose(
        rot @ np.swapaxes(rot, -1, -2), np.broadcast_to(np.eye(3), rot.shape), atol=1e-9
    )
    np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-9)
    assert np.all(np.asarray(est.points_before)[valid][..., 2] > 0)
    assert np.all(np.asarray(est.points_after)[valid][..., 2] > 0)
    assert np.all(np.asarray(est.residual)[valid] < 0.05)
    assert not np.any(np.asarray(est.ambiguous)[~valid])
    # Metric: |AB| = L on every valid estimate.
    ab = np.linalg.norm(
        np.asarray(est.points_before)[valid][:, 1] - np.asarray(est.points_before)[valid][:, 0],
        axis=-1,
    )
    np.testing.assert_allclose(ab, EDGE, rtol=1e-9)
    if noise == 0.0:
        assert valid.mean() > 0.95


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), scale=st.sampled_from([1e-6, 1e-2, 1.0, 1e3]))
def test_property_arbitrary_points_never_nan(seed, scale):
    rng = np.random.default_rng(seed)
    pts = rng.normal(size=(2, 64, 4, 2)) * scale
    pts[:, :8, 1] = pts[:, :8, 0]  # some zero-length segments
    pts[1, 8:16] = pts[0, 8:16]  # some zero motions
    for steps in (0, POLISH_STEPS):
        _assert_finite(estimate_motion(pts[0], pts[1], polish_steps=steps))


# --- transformations ----------------------------------------------------------------------------


# slow: polish 0 (the closed form alone; the default suite runs it under the polish)
@pytest.mark.parametrize("polish_steps", [pytest.param(0, marks=pytest.mark.slow), POLISH_STEPS])
def test_jit_vmap_agree_with_batched_call(scenes, polish_steps):
    b, a = jnp.asarray(scenes.points_before[:64]), jnp.asarray(scenes.points_after[:64])
    length = jnp.full((64,), EDGE)
    core = functools.partial(pm.estimate_motion_core, polish_steps=polish_steps)
    batched = jax.jit(core)(b, a, length)
    vmapped = jax.jit(jax.vmap(core))(b, a, length)
    for x, y in zip(
        jax.tree_util.tree_leaves(batched), jax.tree_util.tree_leaves(vmapped), strict=True
    ):
        np.testing.assert_allclose(np.asarray(x, float), np.asarray(y, float), atol=1e-12)
    nested = estimate_motion(
        b.reshape(8, 8, 4, 2), a.reshape(8, 8, 4, 2), EDGE, polish_steps=polish_steps
    )
    np.testing.assert_allclose(nested.rotation.reshape(64, 3, 3), batched.rotation, atol=1e-12)


PER_KIND = 20  # degenerate scenes of each kind in the gradient test


@pytest.fixture(scope="module")
def degenerate_scenes():
    """PER_KIND scenes of each degenerate kind, from cube scenes of a fixed seed: a dict
    kind -> (before, after), (PER_KIND, 4, 2) float64 each."""
    rng = np.random.default_rng(21)
    s = make_cube_scenes(rng, PER_KIND, motion="mixed")
    pb, pa = _truth(s)

    def rigid(q):
        return np.einsum("nij,nkj->nki", s.rotation, q) + s.translation[:, None]

    kinds = {"zero motion": (s.points_before, s.points_before.copy())}
    b, a = s.points_before.copy(), s.points_after.copy()
    b[:, 1], a[:, 1] = b[:, 0], a[:, 0]
    kinds["zero-length AB"] = (b, a)

    # Each view's C, D moved onto the plane through the camera centre, A and B (CD stays
    # parallel to AB): the image lines are collinear.
    def collapse(p):
        normal = np.cross(p[:, 0], p[:, 1])
        normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
        return p - np.einsum("nki,ni->nk", p, normal)[..., None] * normal[:, None]

    kinds["plane through camera centre"] = (_project(collapse(pb)), _project(collapse(pa)))
    q = pb.copy()
    down = q[:, 1] - q[:, 0] + np.array([0.0, 0.0, -3.0])  # B and D behind the camera
    q[:, 1], q[:, 3] = q[:, 0] + down, q[:, 2] + down
    kinds["points behind camera"] = (_project(q), _project(rigid(q)))
    q = pb.copy()
    for i in range(PER_KIND):
        tilt = rotation_from_axis_angle(rng.normal(size=3), np.radians(20.0))
        q[i, 3] = q[i, 2] + tilt @ (q[i, 3] - q[i, 2])  # D off the parallel direction
    kinds["non-parallel segments"] = (_project(q), _project(rigid(q)))
    noisy = make_cube_scenes(rng, 4 * PER_KIND, motion="small", noise_px=2.0)
    no_root = np.nonzero(_no_real_root(noisy.points_before, noisy.points_after))[0][:PER_KIND]
    assert len(no_root) == PER_KIND
    kinds["no real root"] = (noisy.points_before[no_root], noisy.points_after[no_root])
    return kinds


def _objective(before, after, length, polish_steps):
    """Rotation angle plus the sum of every metric output of the core; the estimate as aux."""
    est = pm.estimate_motion_core(before, after, length, polish_steps=polish_steps)
    leaves = (est.rotation, est.translation, est.points_before, est.points_after)
    return pm.rotation_angle(est.rotation) + sum(jnp.sum(x) for x in leaves), est


@functools.cache
def _batched_grad(polish_steps):
    """Jitted vmapped gradient w.r.t. (before, after, length) and the estimate, per polish_steps
    (shared by the gradient tests: one compile per dtype and polish_steps)."""
    grad = jax.grad(
        functools.partial(_objective, polish_steps=polish_steps), argnums=(0, 1, 2), has_aux=True
    )
    return jax.jit(jax.vmap(grad))


@pytest.fixture(scope="module")
def gradient_batch(scenes, degenerate_scenes):
    """Scene 1 of ``scenes`` (valid) followed by the degenerate scenes, and a function
    (dtype, polish_steps) -> (gradients, estimate) of :func:`_objective` over that batch (cached)."""
    names = list(degenerate_scenes)
    before = np.concatenate([scenes.points_before[1:2]] + [degenerate_scenes[k][0] for k in names])
    after = np.concatenate([scenes.points_after[1:2]] + [degenerate_scenes[k][1] for k in names])
    cache = {}

    def grads(dtype, polish_steps):
        key = (np.dtype(dtype).name, polish_steps)
        if key not in cache:
            length = np.full(len(before), EDGE, dtype)
            cache[key] = _batched_grad(polish_steps)(
                before.astype(dtype), after.astype(dtype), length
            )
        return cache[key]

    return before, after, names, grads


# One compile per (dtype, polish_steps), shared with the degenerate test below; the default suite
# keeps float64 with the polish (its gradient goes through the closed form); the rest are slow.
GRADIENT_CASES = [
    pytest.param(jnp.float64, 0, marks=pytest.mark.slow),
    (jnp.float64, POLISH_STEPS),
    pytest.param(jnp.float32, 0, marks=pytest.mark.slow),
    pytest.param(jnp.float32, POLISH_STEPS, marks=pytest.mark.slow),
]


@pytest.mark.parametrize(("dtype", "polish_steps"), GRADIENT_CASES)
def test_grad_finite_and_matches_central_differences(gradient_batch, dtype, polish_steps):
    before_all, after_all, _, grads = gradient_batch
    (_, g_after, _), _ = grads(dtype, polish_steps)
    g = g_after[0]  # scene 1 of `scenes`
    assert g.dtype == dtype
    assert np.all(np.isfinite(np.asarray(g)))
    if dtype == jnp.float64:
        before, after = jnp.asarray(before_all[0]), jnp.asarray(after_all[0])
        h = 1e-7
        value = jax.jit(lambda a: _objective(before, a, jnp.asarray(EDGE), polish_steps)[0])
        fd = np.zeros((4, 2))
        for i in range(4):
            for j in range(2):
                e = jnp.zeros((4, 2)).at[i, j].set(h)
                fd[i, j] = (value(after + e) - value(after - e)) / (2 * h)
        np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-6 * np.max(np.abs(fd)))


@pytest.mark.parametrize(("dtype", "polish_steps"), GRADIENT_CASES)
def test_grad_finite_on_degenerate_input(gradient_batch, dtype, polish_steps):
    """Degenerate input gives finite values AND finite derivatives (w.r.t. before, after and
    length), for every kind of degeneracy, both dtypes, with and without the polish."""
    _, _, names, grads = gradient_batch
    (g_before, g_after, g_length), est = grads(dtype, polish_steps)
    est = jax.tree_util.tree_map(lambda x: np.asarray(x)[1:], est)  # drop the valid scene
    finite = (
        np.all(np.isfinite(np.asarray(g_before)), axis=(1, 2))
        & np.all(np.isfinite(np.asarray(g_after)), axis=(1, 2))
        & np.isfinite(np.asarray(g_length))
    )[1:].reshape(len(names), PER_KIND)
    bad = {k: int(np.sum(~f)) for k, f in zip(names, finite, strict=True) if not np.all(f)}
    assert not bad, f"non-finite gradients (scenes per kind): {bad}"
    _assert_finite(est)
    valid = est.valid.reshape(len(names), PER_KIND)
    exact = [i for i, k in enumerate(names) if k not in ("non-parallel segments", "no real root")]
    assert not np.any(valid[exact])
    if np.dtype(dtype) == np.float64:  # non-parallel pairs show up in the rigidity residual only
        assert not np.any(pm.consistency_check(est, 1e-6))


def test_rotation_angle_derivative_finite_at_0_and_pi():
    for angle in (0.0, np.pi):
        rot = jnp.asarray(rotation_from_axis_angle([1.0, 2.0, 3.0], angle))
        for dtype in (jnp.float64, jnp.float32):
            r = rot.astype(dtype)
            for scale in (1.0, 1.0 + 1e-6, 1.0 - 1e-6):  # cos exactly, beyond and within +-1
                g = jax.grad(pm.rotation_angle)(r * scale)
                assert np.all(np.isfinite(np.asarray(g)))
            np.testing.assert_allclose(pm.rotation_angle(r), angle, atol=1e-3)


def test_special_polar_matches_svd_with_reflections():
    """The SVD-free special polar (Horn's quaternion form) against U diag(1, 1, det(U V^T)) V^T
    from NumPy's SVD, on random 3 x 3 matrices (about half with det < 0), and its derivative
    against central differences."""
    h = np.random.default_rng(7).normal(size=(500, 3, 3))
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(u @ vt))
    ref = np.einsum("nij,nj,njk->nik", u, np.stack([np.ones(500), np.ones(500), d], -1), vt)
    got = np.asarray(pm._special_polar(jnp.asarray(h)))
    np.testing.assert_allclose(got, ref, atol=1e-12)
    dh = np.random.default_rng(8).normal(size=(3, 3))
    for x in h[:5]:
        _, tangent = jax.jvp(pm._special_polar, (jnp.asarray(x),), (jnp.asarray(dh),))
        eps = 1e-6
        fd = (
            pm._special_polar(jnp.asarray(x + eps * dh))
            - pm._special_polar(jnp.asarray(x - eps * dh))
        ) / (2 * eps)
        np.testing.assert_allclose(tangent, fd, atol=1e-6)
