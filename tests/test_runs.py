"""Run-folder writers: the one video writer (H.264 through imageio-ffmpeg, OpenCV mp4v without)."""

import sys

import cv2
import numpy as np
import pytest

from hec_jax import runs


def _frames(n=6, h=48, w=64):
    """Frames with a red left half and a blue right half (RGB), brightness rising per frame."""
    out = np.zeros((n, h, w, 3), np.uint8)
    out[:, :, : w // 2, 0] = 200
    out[:, :, w // 2 :, 2] = 200
    out[:, :4] += (np.arange(n, dtype=np.uint8) * 10)[:, None, None, None]
    return out


def _read(path):
    cap = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, f = cap.read()
        if not ok:
            break
        frames.append(f[..., ::-1])  # BGR -> RGB
    cap.release()
    return np.array(frames)


def _check(path, frames):
    back = _read(path)
    assert back.shape == frames.shape
    # lossy, but the colours stay where they were (RGB order kept: red left, blue right)
    left, right = back[:, 8:, : frames.shape[2] // 2 - 4], back[:, 8:, frames.shape[2] // 2 + 4 :]
    assert left[..., 0].mean() > 150 and left[..., 2].mean() < 50
    assert right[..., 2].mean() > 150 and right[..., 0].mean() < 50
    assert [p.name for p in path.parent.iterdir()] == [path.name]  # no temporary file left


def test_h264(tmp_path):
    pytest.importorskip("imageio_ffmpeg")
    frames = _frames()
    path = tmp_path / "v.mp4"
    assert runs.write_video(path, list(frames), 30.0) == "h264"
    _check(path, frames)
    assert b"avc1" in path.read_bytes()[:4096]  # H.264, index (moov) at the front


def test_mp4v_without_imageio_ffmpeg(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)  # import fails
    frames = _frames()
    path = tmp_path / "v.mp4"
    assert runs.write_video(path, iter(frames), 30) == "mp4v"
    _check(path, frames)


def test_odd_size_is_padded(tmp_path):
    frames = _frames(3, 47, 63)
    path = tmp_path / "v.mp4"
    runs.write_video(path, frames, 10.0)
    assert _read(path).shape == (3, 48, 64, 3)


@pytest.mark.parametrize(
    "frames, fps, message",
    [
        ([], 30.0, "no frames"),
        (_frames().astype(np.float32), 30.0, "uint8"),
        ([_frames()[0], _frames(1, 32, 32)[0]], 30.0, "uint8 RGB, got"),
        (_frames()[..., 0], 30.0, "(H, W, 3)"),
        (_frames(), 0.0, "fps"),
    ],
)
def test_bad_input(tmp_path, frames, fps, message):
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        runs.write_video(tmp_path / "v.mp4", frames, fps)
    assert list(tmp_path.iterdir()) == []
