"""Synthetic tests of the box model, the refinement and the filter (no rendering)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hec_jax.geometry import SceneConfig, make_cube_scenes, rotation_error_deg
from hec_jax.geometry import filter as kf
from hec_jax.geometry.box_model import (
    EDGE_FACES,
    EDGES,
    Pose,
    face_visibility,
    image_face_visibility,
    project_corners,
)
from hec_jax.geometry.refine import (
    _corner_terms,
    corner_residuals,
    refine_edges,
    refine_edges_batched,
    retract,
    so3_exp,
    so3_log,
    two_frame_motion,
)

CFG = SceneConfig()
_two_frame = jax.jit(jax.vmap(two_frame_motion, in_axes=(0, 0, None, None)))


@pytest.fixture(scope="module")
def noisy():
    return make_cube_scenes(np.random.default_rng(1), 300, CFG, motion="mixed", noise_px=0.5)


def _run(scenes):
    return _two_frame(
        jnp.asarray(scenes.pixels_before),
        jnp.asarray(scenes.pixels_after),
        CFG.edge,
        jnp.asarray(CFG.intrinsics),
    )


def test_so3_roundtrip():
    w = np.random.default_rng(0).normal(size=(50, 3))
    w *= (np.random.default_rng(1).uniform(0, 3.0, 50) / np.linalg.norm(w, axis=-1))[:, None]
    np.testing.assert_allclose(np.asarray(so3_log(so3_exp(jnp.asarray(w)))), w, atol=1e-9)


def test_corner_jacobian_matches_autodiff():
    """The analytic reprojection Jacobian of the corner LM against forward-mode autodiff of the
    residuals under the same left perturbation (a camera with skew, an oblique pose)."""
    k = jnp.array([[500.0, 3.0, 310.0], [0.0, 480.0, 250.0], [0.0, 0.0, 1.0]])
    pose = Pose(so3_exp(jnp.array([0.4, -0.7, 0.3])), jnp.array([0.05, -0.08, 0.9]))
    pixels = jnp.asarray(np.random.default_rng(0).uniform(0, 500, (8, 2)))
    rows = [[pose.rotation[i, j] for j in range(3)] for i in range(3)]
    ru, rv, ju, jv = _corner_terms(rows, list(pose.translation), pixels, 0.1, k, True)
    analytic = jnp.stack([jnp.stack(ju, -1), jnp.stack(jv, -1)], 1).reshape(16, 6)
    auto = jax.jacfwd(lambda d: corner_residuals(retract(pose, d), pixels, 0.1, k))(jnp.zeros(6))
    np.testing.assert_allclose(
        jnp.stack([ru, rv], -1).reshape(-1), corner_residuals(pose, pixels, 0.1, k)
    )
    np.testing.assert_allclose(analytic, auto, rtol=1e-9, atol=1e-9)


def _edge_problem(seed: int, noise_px: float):
    """Segments on the visible edges of a cube at an oblique pose (a camera with skew), each
    end point moved by ``noise_px`` along the normal and 3 of them 6 px off (the Huber loss
    active), 4 zero-weight padding rows; 8 starts 6 deg and 2 cm off the true pose."""
    rng = np.random.default_rng(seed)
    k = jnp.array([[520.0, 2.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
    truth = Pose(so3_exp(jnp.asarray(rng.normal(size=3))), jnp.array([0.03, -0.02, 0.8]))
    corners = np.asarray(project_corners(truth, 0.1, k))
    vis = np.asarray(face_visibility(truth, 0.1))
    visible = np.flatnonzero(vis[np.asarray(EDGE_FACES)].any(-1))
    ids = rng.choice(visible, 20)
    a, b = corners[EDGES[ids, 0]], corners[EDGES[ids, 1]]
    s = np.sort(rng.uniform(0.05, 0.95, (20, 2)), axis=1)
    ends = a[:, None] + s[..., None] * (b - a)[:, None]
    d = (b - a) / np.linalg.norm(b - a, axis=-1, keepdims=True)
    normal = np.stack([-d[:, 1], d[:, 0]], -1)
    off = noise_px * rng.normal(size=(20, 2))
    off[:3] += 6.0
    ends = ends + off[..., None] * normal[:, None]
    ids = np.concatenate([ids, [0, 5, 11, 11]]).astype(np.int32)
    ends = np.concatenate([ends, np.zeros((4, 2, 2))])
    weights = np.concatenate([rng.uniform(5, 40, 20), np.zeros(4)])
    w = rng.normal(size=(8, 3))
    w *= np.deg2rad(6.0) / np.linalg.norm(w, axis=-1, keepdims=True)
    starts = Pose(
        so3_exp(jnp.asarray(w)) @ truth.rotation,
        truth.translation[None] + 0.02 * jnp.asarray(rng.normal(size=(8, 3))) / np.sqrt(3),
    )
    return truth, starts, jnp.asarray(ends), jnp.asarray(ids), jnp.asarray(weights), k


@jax.jit
def _edge_fits(starts, ends, ids, weights, k):
    """(refine_edges_batched, refine_edges) of each start (vmapped)."""

    def both(p):
        return (
            refine_edges_batched(p, ends, ids, weights, 0.1, k, 8, 1.0),
            refine_edges(p, ends, ids, weights, 0.1, k, 8, 1.0),
        )

    return jax.vmap(both)(starts)


def test_batched_edge_lm_is_the_generic_one():
    """The edge LM for vmapped batches (lines of the 12 edges, one-hot picks) against
    :func:`refine_edges` (:func:`levenberg_marquardt` on :func:`edge_residuals`; float64, a
    vmapped batch of starts, three problems): the same fit to round-off; without noise and
    outliers it finds the true pose."""
    for seed in range(3):
        truth, starts, ends, ids, weights, k = _edge_problem(seed, 0.3)
        batched, generic = _edge_fits(starts, ends, ids, weights, k)
        assert generic.rms.max() > 0.1  # the noise and the outliers are seen
        for got, want in zip(jax.tree.leaves(batched), jax.tree.leaves(generic), strict=True):
            np.testing.assert_allclose(got, want, rtol=1e-7, atol=1e-9 * np.abs(want).max())
        truth, starts, ends, ids, weights, k = _edge_problem(seed, 0.0)
        exact, _ = _edge_fits(starts, ends, ids, weights.at[:3].set(0.0), k)
        err_m = np.abs(np.asarray(exact.pose.translation - truth.translation[None])).max()
        assert err_m < 1e-7
        assert np.max(rotation_error_deg(exact.pose.rotation, truth.rotation)) < 1e-5


def test_image_visibility_matches_pose():
    sc = make_cube_scenes(np.random.default_rng(2), 200, CFG, noise_px=0.0)
    centre = sc.corners_before.mean(1)
    # rotation from corners: columns = directions of the x, y, z edge families / edge
    c = sc.corners_before
    rot = np.stack([c[:, 4] - c[:, 0], c[:, 2] - c[:, 0], c[:, 1] - c[:, 0]], -1) / CFG.edge
    pose = Pose(jnp.asarray(rot), jnp.asarray(centre))
    vis_pose = np.asarray(face_visibility(pose, CFG.edge))
    vis_img, _ = image_face_visibility(jnp.asarray(sc.pixels_before))
    np.testing.assert_array_equal(np.asarray(vis_img), vis_pose)
    np.testing.assert_allclose(
        np.asarray(project_corners(pose, CFG.edge, jnp.asarray(CFG.intrinsics))),
        sc.pixels_before,
        atol=1e-8,
    )


def test_face_pose_from_homography_exact_without_noise():
    """Pose from the 4 noise-free image corners of one visible face (the closed-form square
    homography) equals the true pose, for every visible face of 50 random scenes."""
    from hec_jax.geometry.box_model import FACES
    from hec_jax.geometry.refine import face_pose_from_homography

    sc = make_cube_scenes(np.random.default_rng(5), 50, CFG, noise_px=0.0)
    c = sc.corners_before
    rot = np.stack([c[:, 4] - c[:, 0], c[:, 2] - c[:, 0], c[:, 1] - c[:, 0]], -1) / CFG.edge
    pose = Pose(jnp.asarray(rot), jnp.asarray(c.mean(1)))
    visible = np.asarray(face_visibility(pose, CFG.edge))
    k = jnp.asarray(CFG.intrinsics)
    fn = jax.jit(face_pose_from_homography)
    checked = 0
    for n in range(len(rot)):
        for f in np.flatnonzero(visible[n]):
            ids = jnp.asarray(FACES[f])
            est = fn(jnp.asarray(sc.pixels_before[n])[ids], ids, CFG.edge, k)
            np.testing.assert_allclose(np.asarray(est.rotation), rot[n], atol=1e-9)
            np.testing.assert_allclose(np.asarray(est.translation), c[n].mean(0), atol=1e-9)
            checked += 1
    assert checked >= 50


def test_two_frame_exact_without_noise():
    # as many scenes as ``noisy``: the two-frame LM compiles once for both tests
    sc = make_cube_scenes(np.random.default_rng(3), 300, CFG, noise_px=0.0)
    out = _run(sc)
    assert np.all(np.asarray(out.valid))
    assert np.max(rotation_error_deg(np.asarray(out.rotation), sc.rotation)) < 1e-8
    np.testing.assert_allclose(np.asarray(out.translation), sc.translation, atol=1e-9)


def test_two_frame_beats_ippe_by_half(noisy):
    """Issue 5 target: median rotation error <= 0.5 x OpenCV IPPE_SQUARE on the most frontal face."""
    from hec_jax.geometry.baselines import pnp_rotation_errors

    out = _run(noisy)
    ours = rotation_error_deg(np.asarray(out.rotation), noisy.rotation)
    ippe = pnp_rotation_errors(noisy, CFG.intrinsics, CFG.edge)
    assert np.median(ours) <= 0.5 * np.median(ippe), (np.median(ours), np.median(ippe))


@pytest.mark.slow  # two compiles of the two-frame LM (gradient and value)
def test_two_frame_grad_finite(noisy):
    def loss(pb):
        return jnp.sum(
            two_frame_motion(
                pb, jnp.asarray(noisy.pixels_after[0]), CFG.edge, jnp.asarray(CFG.intrinsics)
            ).translation
        )

    x = jnp.asarray(noisy.pixels_before[0])
    g = np.asarray(jax.jit(jax.grad(loss))(x))
    assert np.all(np.isfinite(g))
    # against central differences of the forward map (the LM's derivative is the implicit one at
    # its optimum, not the unrolled iterations')
    f, h = jax.jit(loss), 1e-4  # [px]
    steps = np.eye(16).reshape(16, 8, 2) * h
    fd = np.array([(f(x + d) - f(x - d)) / (2 * h) for d in steps]).reshape(8, 2)
    np.testing.assert_allclose(g, fd, atol=2e-3 * np.abs(fd).max())


def test_filter_recovers_constant_acceleration():
    fc = kf.FilterConfig(dt=1 / 30, jerk_psd=1.0)
    t = np.arange(60) / 30
    acc = np.array([1.0, -2.0, 0.5])
    pos = 0.5 * acc[None] * t[:, None] ** 2 + np.array([0.1, 0.0, 1.0])
    noise = np.random.default_rng(0).normal(scale=1e-4, size=pos.shape)
    state = kf.init(fc, jnp.asarray(pos[0] + noise[0]))
    upd = jax.jit(lambda s, z: kf.update(fc, s, z, 1e-8 * jnp.eye(3), jnp.asarray(True)))
    for z in pos[1:] + noise[1:]:
        state = upd(state, jnp.asarray(z))
    np.testing.assert_allclose(np.asarray(state.mean[6:]), acc, atol=0.2)
    np.testing.assert_allclose(np.asarray(state.mean[3:6]), acc * t[-1], atol=0.02)


def test_best_parallel_pair_and_largest_face_match_sort_reference():
    """The select/argmax forms of the pair and face choices against the sort-based definition
    (NumPy, stable sort), on integer pixels (many ties and zero-length edges)."""
    from hec_jax.geometry.box_model import EDGES
    from hec_jax.geometry.refine import _best_parallel_pair, largest_visible_face

    rng = np.random.default_rng(4)
    pixels = rng.integers(0, 4, size=(3000, 8, 2)).astype(float)
    visible = rng.uniform(size=(3000, 12)) < 0.6
    got = np.asarray(jax.jit(jax.vmap(_best_parallel_pair))(pixels, visible))
    length = np.linalg.norm(pixels[:, EDGES[:, 1]] - pixels[:, EDGES[:, 0]], axis=-1)
    length = np.where(visible, length, 0.0).reshape(-1, 3, 4)
    for n in range(len(pixels)):
        fam = np.argmax(np.sort(length[n], axis=-1)[:, -2])
        order = np.argsort(-length[n, fam], kind="stable")
        i, j = fam * 4 + order[0], fam * 4 + order[1]
        np.testing.assert_array_equal(got[n], [*EDGES[i], *EDGES[j]])
    face, vis, area = jax.jit(jax.vmap(largest_visible_face))(jnp.asarray(pixels))
    ref_vis, ref_area = image_face_visibility(jnp.asarray(pixels))
    np.testing.assert_array_equal(np.asarray(vis), np.asarray(ref_vis))
    np.testing.assert_allclose(np.asarray(area), np.asarray(ref_area))
    ref_face = np.argmax(np.where(np.asarray(ref_vis), np.asarray(ref_area), -1.0), axis=-1)
    np.testing.assert_array_equal(np.asarray(face), ref_face)
