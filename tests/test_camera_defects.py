"""An imperfect camera in the hand-eye loop (issue 24, point 5): sensor noise, defocus, motion
blur, intrinsics known to the eye with an error, jittered time stamps (``CameraDefects``, all
off by default). Small renders, no loop compile."""

import dataclasses

import numpy as np
import pytest

from hec_jax import loop as tl
from hec_jax.cli import parse
from hec_jax.loop import camera_loop as he
from hec_jax.loop.cli import TaskRun
from hec_jax.mjx_scene import load_mj_model
from hec_jax.mjx_scene.camera import camera_intrinsics
from hec_jax.mjx_scene.randomized import draw_scene, post_process
from hec_jax.mjx_scene.render import SceneCamera, sensor

W, H = 160, 120


@pytest.fixture(scope="module")
def camera():
    m = load_mj_model()
    with SceneCamera(m, "eye", W, H) as cam:
        yield cam, m.qpos0.copy()


def test_the_perfect_camera_has_no_defects():
    # the loop's default is the industrial camera (tests/test_mjx_scene_lab.py); "perfect" is off
    assert tl.CameraDefects() == tl.CameraConfig(camera_model="perfect").applied_defects
    assert tl.CameraConfig.void_perfect().applied_defects == tl.CameraDefects()
    # one render at mid-exposure, as the loop took it before defects existed
    np.testing.assert_array_equal(he.exposure_offsets(tl.CameraConfig.void_perfect(), 1e-3), [2])


def test_defects_off_give_the_rendered_frame_bit_for_bit(camera):
    cam, q = camera
    rng = np.random.default_rng(0)
    state = rng.bit_generator.state
    frame = he.camera_frame(cam, q[None], tl.CameraDefects(), rng)
    np.testing.assert_array_equal(frame, cam.render(q))
    assert frame.dtype == np.uint8
    assert rng.bit_generator.state == state  # nothing drawn
    np.testing.assert_array_equal(
        he.eye_intrinsics(cam.intrinsics, tl.CameraDefects()), cam.intrinsics
    )
    assert he.stamp_jitter(tl.CameraDefects(), rng) == 0.0


def test_randomized_benchmark_post_process_is_unchanged():
    """The randomized benchmark's camera now goes through the shared ``render.sensor``: the same
    numbers as its own code had."""
    scene = dataclasses.replace(draw_scene(3), gain=1.1, blur_px=0.7, noise_sigma=3.0)
    frame = np.random.default_rng(1).integers(0, 256, (40, 50, 3), dtype=np.uint8)
    img = frame.astype(np.float32) * scene.gain  # the code before the refactor
    import cv2

    img = cv2.GaussianBlur(img, (0, 0), scene.blur_px)
    img += np.random.default_rng(2).normal(0.0, 3.0, img.shape).astype(np.float32)
    before = np.clip(np.round(img), 0, 255).astype(np.uint8)
    np.testing.assert_array_equal(post_process(frame, scene, np.random.default_rng(2)), before)


def test_noise_has_the_requested_sigma_on_a_flat_image():
    flat = np.full((200, 200, 3), 128, np.uint8)
    for sigma in (2.0, 5.0):
        d = tl.CameraDefects(noise_grey=sigma)
        out = sensor(flat, he.defects_rng(d, 0, 0), d.noise_grey)
        diff = out.astype(float) - 128.0
        # rounding to grey levels adds 1/12 to the variance
        assert abs(diff.std() - np.sqrt(sigma**2 + 1 / 12)) < 0.03 * sigma
        assert abs(diff.mean()) < 0.05


def test_same_seed_same_frames(camera):
    cam, q = camera
    d = tl.CameraDefects(noise_grey=3.0, defocus_px=0.8)
    a = he.camera_frame(cam, q[None], d, he.defects_rng(d, 1, 2))
    b = he.camera_frame(cam, q[None], d, he.defects_rng(d, 1, 2))
    c = he.camera_frame(
        cam, q[None], d, he.defects_rng(dataclasses.replace(d, defect_seed=1), 1, 2)
    )
    np.testing.assert_array_equal(a, b)
    assert np.any(a != c)
    assert np.any(a != he.camera_frame(cam, q[None], d, he.defects_rng(d, 0, 2)))  # other seed


def test_motion_blur_averages_renders_over_the_exposure(camera):
    cam, q = camera
    cfg = tl.CameraConfig(exposure_s=0.01, defects=tl.CameraDefects(blur_renders=5))
    backs = he.exposure_offsets(cfg, 1e-3)
    assert sorted(backs) == [1, 3, 5, 7, 9] and backs[-1] == 5  # mid-exposure last
    q2 = q.copy()
    q2[0] += 0.3  # the pendulum's hinge swung
    one = cam.render(q).astype(int)
    other = cam.render(q2).astype(int)
    mean = he.camera_frame(cam, np.stack([q, q2]), tl.CameraDefects(blur_renders=2), None)
    assert np.all(mean >= np.minimum(one, other)) and np.all(mean <= np.maximum(one, other))
    assert np.any((mean != one) & (mean != other))
    np.testing.assert_array_equal(cam.data.qpos, q2)  # the last render's kinematics stay


def test_intrinsics_error_is_the_eye_s_not_the_renderer_s(monkeypatch):
    """The eye gets K with fx, fy times (1 + focal_error) and cx, cy moved; the renderer keeps the
    MJCF camera's K (checked on what ``run_camera`` hands the eye, stopped there)."""
    d = tl.CameraDefects(focal_error=0.015, centre_error_px=2.0)
    k = camera_intrinsics(load_mj_model(), "eye", W, H)
    k_eye = he.eye_intrinsics(k, d)
    np.testing.assert_allclose(np.diag(k_eye)[:2] / np.diag(k)[:2], 1.015, rtol=1e-12)
    np.testing.assert_allclose(k_eye[:2, 2] - k[:2, 2], 2.0, rtol=1e-12)
    assert k_eye[2, 2] == 1.0 and k_eye[0, 1] == k[0, 1]

    seen = {}

    class Stop(Exception):
        pass

    def fake_eye(eye, intrinsics, fps, cam, background):
        seen["k"] = np.array(intrinsics)
        raise Stop

    monkeypatch.setattr(he, "make_eye", fake_eye)
    loop = tl.build_loop(
        dataclasses.replace(tl.catching().task, swings=1, swing_s=0.1, settle_s=0.1)
    )
    m = load_mj_model()

    def start(ls, sw, conditions):
        return (type("D", (), {"qpos": np.asarray(m.qpos0)[None]}),)

    cam = tl.CameraConfig(width=W, height=H, defects=d)
    keys = np.zeros((1, 2), np.uint32)
    with pytest.raises(Stop):
        he.run_camera(
            loop,
            loop.config.pendulum.conditions(),
            keys,
            "learned",
            cam,
            progress=False,
            compiled=(start, None),
        )
    np.testing.assert_allclose(seen["k"], k_eye, rtol=1e-12)
    with SceneCamera(m, "eye", W, H) as renderer:  # the renderer's K: the true one
        np.testing.assert_array_equal(renderer.intrinsics, k)


def test_jitter_stays_within_its_bound_and_is_seeded():
    d = tl.CameraDefects(jitter_s=0.003)
    draws = [
        he.stamp_jitter(d, rng) for rng in [he.defects_rng(d, 0, 0, "jitter")] for _ in range(2000)
    ]
    draws = np.array(draws)
    assert np.all(np.abs(draws) <= 0.003) and np.abs(draws).max() > 0.0029
    assert abs(draws.mean()) < 2e-4
    again = he.defects_rng(d, 0, 0, "jitter")
    np.testing.assert_array_equal(draws[:10], [he.stamp_jitter(d, again) for _ in range(10)])
    other = he.defects_rng(d, 0, "final", "jitter")
    assert he.stamp_jitter(d, other) != draws[0]


def test_noise_and_jitter_draw_from_their_own_streams(camera):
    """Turning the stamp jitter on leaves the noisy frames as they were (the loop draws each
    frame's jitter between its frames); the noise stream is the single generator's of before
    (runs without jitter unchanged); the two streams differ."""
    cam, q = camera
    noisy = tl.CameraDefects(noise_grey=3.0)
    both = dataclasses.replace(noisy, jitter_s=0.003)

    def frames(d):
        noise, jitter = he.defects_rng(d, 1, 2), he.defects_rng(d, 1, 2, "jitter")
        out = []
        for _ in range(3):
            out.append(he.camera_frame(cam, q[None], d, noise))
            he.stamp_jitter(d, jitter)
        return out

    for a, b in zip(frames(noisy), frames(both), strict=True):
        np.testing.assert_array_equal(a, b)
    before = np.random.default_rng([noisy.defect_seed, 1, 2])  # the generator before streams
    np.testing.assert_array_equal(he.defects_rng(noisy, 1, 2).random(5), before.random(5))
    assert he.defects_rng(both, 1, 2, "jitter").random() != he.defects_rng(both, 1, 2).random()
    with pytest.raises(ValueError, match="stream"):
        he.defects_rng(noisy, 1, 2, "blur")


def test_defect_flags_reach_the_config():
    run = parse(
        TaskRun(experiment=tl.catching()),
        ["--camera-model", "perfect", "--noise-grey", "2", "--focal-error", "-0.01"]
        + ["--jitter-s", "0.002"],
    )
    want = tl.CameraDefects(noise_grey=2.0, focal_error=-0.01, jitter_s=0.002)
    assert run.experiment.camera.applied_defects == want


@pytest.mark.parametrize(
    ("kwargs", "says"),
    [
        (dict(noise_grey=-1.0), "--noise-grey: must be finite and >= 0"),
        (dict(defocus_px=float("nan")), "--defocus-px: must be finite and >= 0"),
        (dict(blur_renders=0), "--blur-renders: must be an integer >= 1"),
        (dict(focal_error=0.6), "--focal-error: must be finite and in (-0.5, 0.5)"),
        (dict(centre_error_px=float("inf")), "--centre-error-px: must be finite"),
        (dict(jitter_s=-0.001), "--jitter-s: must be finite and >= 0"),
        (dict(defect_seed=-1), "--defect-seed: must be an integer >= 0"),
    ],
)
def test_bad_defects_are_refused_in_one_line(kwargs, says):
    with pytest.raises(ValueError) as exc:
        tl.CameraDefects(**kwargs)
    assert says in str(exc.value) and "\n" not in str(exc.value)


def test_jitter_and_blur_are_checked_against_the_camera():
    with pytest.raises(ValueError, match="--jitter-s: must be below half the frame period"):
        tl.CameraConfig(defects=tl.CameraDefects(jitter_s=0.02))
    with pytest.raises(ValueError, match="--blur-renders above 1 needs --exposure-s > 0"):
        tl.CameraConfig(exposure_s=0.0, defects=tl.CameraDefects(blur_renders=3))


@pytest.mark.parametrize("msaa", [-1, 17, 2.0, "4"])
def test_bad_msaa_is_refused(msaa):
    with pytest.raises(ValueError, match="--msaa: must be None or an integer in 0..16"):
        tl.CameraConfig(msaa=msaa)
    assert tl.CameraConfig(msaa=0).msaa == 0 and tl.CameraConfig().msaa is None


def test_a_defect_flag_at_the_perfect_value_turns_that_defect_off_under_the_industrial_camera(
    tmp_path,
):
    """Under the industrial camera (the default) a flag given at the perfect camera's value
    (``--focal-error 0``) turns that one defect off; before, it read as unset and the run kept
    the industrial 1% (a main job asked for without it ran with it). Flags not given stay the
    industrial ones; a flag given at another value keeps it, as before."""
    from hec_jax.loop.cli import given_defect_fields, parse_task

    ind = tl.CameraDefects.industrial()
    argv = ["--focal-error", "0", "--jitter-s=0", "--seeds", "2", "--out", str(tmp_path / "r")]
    assert given_defect_fields(argv) == ("focal_error", "jitter_s")
    assert given_defect_fields(["--experiment.camera.defects.noise-grey", "1"]) == ("noise_grey",)
    run = parse_task("catching", argv)
    cam = run.experiment.camera
    assert cam.camera_model == "industrial" and cam.defects_given == ("focal_error", "jitter_s")
    assert cam.applied_defects == dataclasses.replace(ind, focal_error=0.0, jitter_s=0.0)
    # what a run folder records runs the same
    assert cam.resolved().applied_defects == cam.applied_defects
    # the same flags without the record: the old reading, the industrial values
    assert dataclasses.replace(cam, defects_given=()).applied_defects == ind
    # another value, and no defect flag at all
    other = parse_task("catching", ["--centre-error-px", "-1.5", "--out", str(tmp_path / "s")])
    assert other.experiment.camera.applied_defects == dataclasses.replace(ind, centre_error_px=-1.5)
    plain = parse_task("catching", ["--out", str(tmp_path / "t")])
    assert plain.experiment.camera.defects_given == ()
    assert plain.experiment.camera.applied_defects == ind
    # under the perfect camera the flags are as given, with or without the record
    argv = ["--camera-model", "perfect", "--focal-error", "0", "--out", str(tmp_path / "u")]
    perfect = parse_task("catching", argv)
    assert perfect.experiment.camera.applied_defects == tl.CameraDefects()
    with pytest.raises(ValueError, match="defects_given"):
        tl.CameraConfig(defects_given=("focal",))
