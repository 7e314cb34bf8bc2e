"""The play pipeline (frames -> rendered mp4) and the `fae render` / `fae play` commands."""

from __future__ import annotations

import argparse
import importlib
from pathlib import Path

import imageio_ffmpeg
import numpy as np
import pytest

from fae.io.facemodel_gltf import write_facemodel
from fae.render.play import render_video
from fae.render.renderer import BACKGROUND, FaceRenderer
from test_render_support import jaw_frames, synthetic_head

REPO = Path(__file__).resolve().parent.parent
SIZE = (160, 120)


def decode(path):
    reader = imageio_ffmpeg.read_frames(str(path))
    meta = next(reader)
    w, h = meta["size"]
    return meta, [np.frombuffer(b, dtype=np.uint8).reshape(h, w, 3) for b in reader]


def run_command(name: str, argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="fae")
    importlib.import_module(f"fae.commands.{name}").register(parser.add_subparsers())
    args = parser.parse_args([name, *argv])
    return args.func(args)


@pytest.fixture(scope="module")
def head():
    return synthetic_head(subdivisions=4)


@pytest.fixture(scope="module")
def renderer(head):
    with FaceRenderer(head, size=SIZE) as r:
        yield r


@pytest.fixture(scope="module")
def head_glb(tmp_path_factory):
    path = tmp_path_factory.mktemp("heads") / "synthetic.glb"
    write_facemodel(synthetic_head(subdivisions=4), path)
    return path


ANGLES = 0.3 * np.sin(np.linspace(0, np.pi, 20)) ** 2  # closed, open, closed


@pytest.mark.parametrize("overlap", [True, False])
def test_frames_become_a_video_whose_mouth_moves(tmp_path, head, renderer, overlap):
    out = tmp_path / "jaw.mp4"
    timings = render_video(jaw_frames(head, ANGLES), renderer, out, fps=25, overlap=overlap)
    assert timings.frames == len(ANGLES) and timings.wall > 0
    meta, frames = decode(out)
    assert len(frames) == len(ANGLES) and meta["size"] == SIZE and meta["fps"] == pytest.approx(25)
    mouth = 0.5 * (head.feature_point_positions()["2.2"] + head.feature_point_positions()["2.3"])
    x, y = (int(v) for v in renderer.camera.project(mouth, SIZE)[0])
    region = (slice(y - 4, y + 5), slice(x - 6, x + 7))
    change = [np.abs(f[region].astype(int) - frames[0][region]).mean() for f in frames]
    assert max(change) > 15, "the mouth should change while the jaw opens"
    assert change[-1] < 0.3 * max(change), "and come back when it closes"
    assert frames[len(frames) // 2].mean() > 40  # not blank


def test_a_still_stream_gives_identical_mouth_pixels(tmp_path, head, renderer):
    out = tmp_path / "still.mp4"
    render_video(jaw_frames(head, np.zeros(10)), renderer, out, fps=25)
    _, frames = decode(out)
    assert len(frames) == 10
    assert max(np.abs(f.astype(int) - frames[0]).mean() for f in frames) < 1.0


class StreamBroke(ValueError):
    pass


def breaking_source(head, good_frames: int):
    yield from jaw_frames(head, ANGLES[:good_frames])
    raise StreamBroke("stream.fap:42: expected 68 mask tokens")


@pytest.mark.parametrize("overlap", [True, False])
def test_a_source_failing_part_way_leaves_no_video(tmp_path, head, renderer, overlap):
    out = tmp_path / "broken.mp4"
    with pytest.raises(StreamBroke, match="stream.fap:42"):
        render_video(breaking_source(head, 6), renderer, out, fps=25, overlap=overlap)
    assert list(tmp_path.iterdir()) == []


def test_frames_dir_gets_one_png_per_frame(tmp_path, head, renderer):
    frames_dir = tmp_path / "frames"
    frames_dir.mkdir()
    render_video(jaw_frames(head, ANGLES[:5]), renderer, tmp_path / "a.mp4", fps=10, frames_dir=frames_dir)
    from PIL import Image

    names = sorted(p.name for p in frames_dir.iterdir())
    assert names == [f"frame_{i:05d}.png" for i in range(5)]
    assert Image.open(frames_dir / names[0]).size == SIZE


def test_fae_render_writes_a_png_of_the_head(tmp_path, head_glb):
    from PIL import Image

    out = tmp_path / "still.png"
    assert run_command("render", [str(head_glb), "-o", str(out), "--size", "200x150", "--view", "three-quarter"]) == 0
    image = np.asarray(Image.open(out))
    assert image.shape == (150, 200, 3)
    assert image.std() > 10  # a head on a plain background, not a blank image


def test_fae_render_reports_bad_input(tmp_path, head_glb, capsys):
    bad = tmp_path / "bad.glb"
    bad.write_bytes(b"not a glb at all")
    assert run_command("render", [str(bad), "-o", str(tmp_path / "x.png")]) == 2
    assert "bad.glb" in capsys.readouterr().err
    assert run_command("render", [str(head_glb), "-o", str(tmp_path / "no" / "x.png")]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert run_command("render", [str(head_glb), "-o", str(tmp_path / "x.jpg")]) == 2
    with pytest.raises(SystemExit) as exc:
        run_command("render", [str(head_glb), "-o", str(tmp_path / "x.png"), "--size", "big"])
    assert exc.value.code == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.glb"]


def test_fae_play_rejects_bad_arguments_before_doing_work(tmp_path, head_glb, capsys):
    stream = REPO / "fap_streams" / "expressions.fap"
    out = tmp_path / "o.mp4"
    assert run_command("play", [str(stream), "--head", str(head_glb), "-o", str(out), "--size", "641x480"]) == 2
    assert "even" in capsys.readouterr().err
    assert run_command("play", [str(stream), "--head", str(head_glb), "-o", str(tmp_path / "o.avi")]) == 2
    assert run_command("play", [str(tmp_path / "missing.fap"), "--head", str(head_glb), "-o", str(out)]) == 2
    assert "missing.fap" in capsys.readouterr().err
    assert run_command("play", [str(stream), "--head", str(tmp_path / "nohead.glb"), "-o", str(out)]) == 2
    assert "nohead.glb" in capsys.readouterr().err
    from fae.warp_setup import wp

    if not wp.is_cuda_available():
        assert run_command("play", [str(stream), "--head", str(head_glb), "-o", str(out), "--device", "cuda"]) == 2
        assert "--device cuda: no CUDA device found" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


# --- end to end through the animation runtime, on the shipped head -----------------


_TEMPLATE_STATE: dict = {}


def shipped_head() -> Path:
    """The head `fae play` uses by default (it ships calibrated: playing it calibrates nothing)."""
    from fae.data import shipped_head_path

    path = shipped_head_path()
    if path not in _TEMPLATE_STATE:
        from fae.io.facemodel_gltf import read_facemodel

        _TEMPLATE_STATE[path] = read_facemodel(path)
    assert _TEMPLATE_STATE[path].fap_mapping, f"{path} carries no fap_mapping"
    return path


def short_stream(tmp_path, frames: int = 25, break_at: int | None = None) -> Path:
    """The first `frames` frames of fap_streams/expressions.fap (optionally with a bad line)."""
    lines = (REPO / "fap_streams" / "expressions.fap").read_text().splitlines()
    body = lines[1:1 + 2 * frames]
    if break_at is not None:
        body[2 * break_at + 1] = "this is not a values line"
    head = lines[0].split()
    head[-1] = str(frames)
    path = tmp_path / ("broken.fap" if break_at is not None else "short.fap")
    path.write_text("\n".join([" ".join(head), *body]) + "\n")
    return path


def jaw_stream(path: Path, open_jaw) -> Path:
    """A 25 fps stream sending only FAP 3 (open_jaw, MNS units) with the given values;
    None in place of the values: a stream that sends nothing at all."""
    from fae.io.fap import FapFrame, FapHeader, write_fap

    frames = []
    for i, value in enumerate(open_jaw):
        mask = np.zeros(68, dtype=bool)
        values = np.zeros(68)
        if value is not None:
            mask[2], values[2] = True, value
        frames.append(FapFrame(number=i, mask=mask, values=values))
    write_fap(path, FapHeader("2.1", path.stem, 25.0, len(frames)), frames)
    return path


def mouth_box(head: Path, size, half: tuple[int, int]) -> tuple[slice, slice]:
    """Pixels around the lips of the shipped head in a front view of `size`."""
    from fae.render.framing import camera_view

    model = _TEMPLATE_STATE[head]
    fp = model.feature_point_positions()
    x, y = camera_view(model, "front", aspect=size[0] / size[1]).project(0.5 * (fp["2.2"] + fp["2.3"]), size)[0]
    return slice(int(y) - half[1], int(y) + half[1] + 1), slice(int(x) - half[0], int(x) + half[0] + 1)


@pytest.mark.slow
def test_fae_play_renders_the_shipped_head_centred_at_the_streams_rate(tmp_path):
    shipped_head()
    from PIL import Image

    stream = short_stream(tmp_path, 25)
    out = tmp_path / "expressions.mp4"
    frames_dir = tmp_path / "frames"
    assert run_command("play", [str(stream), "-o", str(out), "--size", "160x120", "--frames-dir", str(frames_dir)]) == 0
    meta, frames = decode(out)
    assert meta["fps"] == pytest.approx(25) and meta["size"] == (160, 120)
    assert len(frames) == 25
    background = np.round(np.asarray(BACKGROUND) * 255)
    for frame in frames[::8]:
        face = np.abs(frame.astype(int) - background).max(axis=2) > 25
        assert 0.1 < face.mean() < 0.7, "the head should fill a good part of the frame"
        ys, xs = np.nonzero(face)
        assert abs(xs.mean() - 80) < 8 and abs(ys.mean() - 60) < 10, "the head should be centred"
    # The expressions move the face.
    assert max(np.abs(f.astype(int) - frames[0]).mean() for f in frames) > 0.5
    # One PNG per frame, the same pictures the video holds (up to H.264 loss).
    names = sorted(p.name for p in frames_dir.iterdir())
    assert names == [f"frame_{i:05d}.png" for i in range(25)]
    png = np.asarray(Image.open(frames_dir / names[12]).convert("RGB")).astype(int)
    assert png.shape == (120, 160, 3) and np.abs(png - frames[12]).mean() < 4
    assert sorted(p.name for p in tmp_path.iterdir()) == ["expressions.mp4", "frames", "short.fap"]


@pytest.mark.slow
def test_the_mouth_opens_with_fap3_and_stays_still_without_faps(tmp_path):
    head = shipped_head()
    size = (160, 120)
    ramp = list(np.linspace(0.0, 600.0, 10)) + [600.0] * 10
    videos = {}
    for name, values in (("jaw", ramp), ("still", [None] * 20)):
        stream = jaw_stream(tmp_path / f"{name}.fap", values)
        assert run_command("play", [str(stream), "-o", str(tmp_path / f"{name}.mp4"), "--size", "160x120"]) == 0
        videos[name] = decode(tmp_path / f"{name}.mp4")[1]
    mouth = mouth_box(head, size, (8, 7))
    opened = np.abs(videos["jaw"][-1][mouth].astype(int) - videos["jaw"][0][mouth]).mean()
    assert opened > 15, f"the mouth should change as the jaw opens ({opened:.1f})"
    # The open mouth shows its dark inside.
    assert (videos["jaw"][-1][mouth].sum(axis=2) < 200).sum() > 5
    still = max(np.abs(f[mouth].astype(int) - videos["still"][0][mouth]).mean() for f in videos["still"])
    assert still < 1.0, f"with no FAPs sent the mouth should not move ({still:.2f})"
    assert np.abs(videos["still"][0].astype(int) - videos["jaw"][0]).mean() < 1.0, "both start at rest"


@pytest.mark.slow
def test_fae_play_resamples_to_the_requested_rate(tmp_path):
    shipped_head()
    stream = short_stream(tmp_path, 25)
    out = tmp_path / "half.mp4"
    assert run_command("play", [str(stream), "-o", str(out), "--size", "160x120", "--fps", "12.5"]) == 0
    meta, frames = decode(out)
    assert meta["fps"] == pytest.approx(12.5) and abs(len(frames) - 13) <= 1


@pytest.mark.slow
def test_fae_play_leaves_no_video_for_a_stream_broken_part_way(tmp_path, capsys):
    shipped_head()
    broken = short_stream(tmp_path, 25, break_at=15)
    out = tmp_path / "broken.mp4"
    assert run_command("play", [str(broken), "-o", str(out), "--size", "160x120"]) == 2
    assert "broken.fap" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["broken.fap"]
