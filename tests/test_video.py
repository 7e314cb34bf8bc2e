"""VideoWriter: decodable H.264 mp4 with the right frame count, size and rate; atomic."""

from __future__ import annotations

import numpy as np
import imageio_ffmpeg
import pytest

from fae.render.video import VideoWriter


def decode(path):
    reader = imageio_ffmpeg.read_frames(str(path))
    meta = next(reader)
    w, h = meta["size"]
    frames = [np.frombuffer(b, dtype=np.uint8).reshape(h, w, 3) for b in reader]
    return meta, frames


def gradient_frames(n, size=(96, 64)):
    w, h = size
    x = np.linspace(0, 255, w)[None, :, None]
    for i in range(n):
        img = np.empty((h, w, 3))
        img[..., 0] = x[..., 0]
        img[..., 1] = 255.0 * i / max(n - 1, 1)
        img[..., 2] = 90.0
        yield img.astype(np.uint8)


def test_mp4_decodes_to_the_frames_written(tmp_path):
    out = tmp_path / "clip.mp4"
    frames = list(gradient_frames(30))
    with VideoWriter(out, (96, 64), fps=25) as video:
        for f in frames:
            video.write(f)
    meta, decoded = decode(out)
    assert meta["codec"] == "h264" and meta["pix_fmt"].startswith("yuv420p")
    assert meta["size"] == (96, 64) and meta["fps"] == pytest.approx(25.0)
    assert len(decoded) == 30
    for got, want in zip(decoded[::7], frames[::7]):
        assert np.abs(got.astype(int) - want).mean() < 6
    assert [p.name for p in tmp_path.iterdir()] == ["clip.mp4"]


def test_fractional_frame_rate_is_kept(tmp_path):
    out = tmp_path / "ntsc.mp4"
    with VideoWriter(out, (96, 64), fps=30000 / 1001) as video:
        for f in gradient_frames(12):
            video.write(f)
    meta, decoded = decode(out)
    assert meta["fps"] == pytest.approx(29.97, abs=0.01) and len(decoded) == 12


def test_an_error_part_way_leaves_no_file_and_keeps_an_old_one(tmp_path):
    out = tmp_path / "clip.mp4"
    out.write_bytes(b"previous video")
    with pytest.raises(RuntimeError, match="stream broke"):
        with VideoWriter(out, (96, 64), fps=25) as video:
            for i, f in enumerate(gradient_frames(10)):
                if i == 5:
                    raise RuntimeError("stream broke")
                video.write(f)
    assert out.read_bytes() == b"previous video"
    assert [p.name for p in tmp_path.iterdir()] == ["clip.mp4"]


def test_bad_sizes_frames_and_paths_are_rejected(tmp_path):
    with pytest.raises(ValueError, match="even"):
        VideoWriter(tmp_path / "odd.mp4", (95, 64), fps=25)
    with pytest.raises(ValueError, match="frame rate"):
        VideoWriter(tmp_path / "rate.mp4", (96, 64), fps=0)
    with pytest.raises(FileNotFoundError, match="does not exist"):
        VideoWriter(tmp_path / "missing" / "x.mp4", (96, 64), fps=25)
    with pytest.raises(ValueError, match=r"expected \(64, 96, 3\) uint8"):
        with VideoWriter(tmp_path / "shape.mp4", (96, 64), fps=25) as video:
            video.write(np.zeros((64, 95, 3), dtype=np.uint8))
    assert list(tmp_path.iterdir()) == []


def test_rgba_frames_encode_like_rgb_frames(tmp_path):
    """GL colour buffers are RGBA: they go to ffmpeg as they are, alpha ignored."""
    frames = list(gradient_frames(8))
    for name, channels in (("rgb.mp4", 3), ("rgba.mp4", 4)):
        with VideoWriter(tmp_path / name, (96, 64), fps=25, channels=channels) as video:
            for f in frames:
                video.write(f if channels == 3 else np.concatenate([f, np.full(f.shape[:2] + (1,), 255, np.uint8)], 2))
    _, rgb = decode(tmp_path / "rgb.mp4")
    _, rgba = decode(tmp_path / "rgba.mp4")
    assert len(rgba) == 8 and all(np.array_equal(a, b) for a, b in zip(rgb, rgba))
    with pytest.raises(ValueError, match=r"expected \(64, 96, 4\) uint8"):
        with VideoWriter(tmp_path / "x.mp4", (96, 64), fps=25, channels=4) as video:
            video.write(frames[0])
    with pytest.raises(ValueError, match="channels"):
        VideoWriter(tmp_path / "y.mp4", (96, 64), fps=25, channels=2)
