"""What the batch tests share: short streams cut from a sample, a second head, frame counts."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import imageio_ffmpeg
import numpy as np

REPO = Path(__file__).resolve().parent.parent
SAMPLE = REPO / "fap_streams" / "visemes.fap"  # 25 fps, a frame on every frame number


def short_stream(path: Path, frames: int) -> Path:
    """The first `frames` frames of the visemes sample, as a stream of its own."""
    lines = SAMPLE.read_text().splitlines()
    header = lines[0].split()
    header[-1] = str(frames)
    path.write_text(" ".join(header) + "\n" + "\n".join(lines[1:1 + 2 * frames]) + "\n")
    return path


def bad_stream(path: Path) -> Path:
    path.write_text("2.1 broken 25 3\n1 0 0 nonsense\n")
    return path


def tinted_head(path: Path) -> Path:
    """The shipped head with a paler skin: other bytes (another head to set up), same calibration."""
    from fae.data import shipped_head_path
    from fae.io.facemodel_gltf import read_facemodel, write_facemodel

    model = read_facemodel(shipped_head_path())
    tint = np.array([0.8, 0.9, 1.0, 1.0], dtype=model.skin_color.dtype)
    write_facemodel(dataclasses.replace(model, skin_color=model.skin_color * tint), path)
    return path


def video_frames(path: Path) -> int:
    return imageio_ffmpeg.count_frames_and_secs(str(path))[0]
