"""H.264 mp4 files from RGB frames, through the ffmpeg that imageio-ffmpeg bundles.

The file appears at its path only when the video is complete: frames go to a temporary
file beside it (fae.io.atomic), which is renamed when ffmpeg has finished successfully and
removed on any error. ffmpeg runs as its own process (it encodes while the caller renders
the next frame); its exit status is checked, which `imageio_ffmpeg.write_frames` does not
do, so a failed encode never replaces the target.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import tempfile
import time
from fractions import Fraction
from pathlib import Path

import imageio_ffmpeg
import numpy as np

from fae.io.atomic import atomic_path


class VideoError(RuntimeError):
    """ffmpeg could not write the video."""


def _rate(fps: float) -> str:
    if not np.isfinite(fps) or fps <= 0:
        raise ValueError(f"frame rate {fps!r}: expected a positive number of frames per second")
    r = Fraction(float(fps)).limit_denominator(1001)
    return f"{r.numerator}/{r.denominator}"


class VideoWriter:
    """Write (H, W, 3) uint8 RGB (or (H, W, 4) RGBA) frames to an H.264 (yuv420p) mp4 at `path`.

    path    the .mp4 to create (its folder must exist); replaced only on success
    size    (width, height) in pixels, both even (yuv420p halves the chroma planes)
    fps     frames per second (may be fractional, e.g. 29.97)
    crf     x264 constant rate factor (0 lossless .. 51 worst; 18-23 looks clean)
    preset  x264 speed preset ("ultrafast" .. "veryslow")
    channels  3: frames are RGB; 4: RGBA (alpha ignored), as a GL colour buffer comes

    Use as a context manager: leaving the block normally finishes the file, an exception
    discards it. `encode_seconds` accumulates the time spent handing frames to ffmpeg and
    waiting for it to finish.
    """

    def __init__(self, path: str | os.PathLike, size: tuple[int, int], fps: float,
                 crf: int = 20, preset: str = "veryfast", channels: int = 3):
        width, height = (int(s) for s in size)
        if width <= 0 or height <= 0 or width % 2 or height % 2:
            raise ValueError(f"video size {width}x{height}: H.264 yuv420p needs positive, even width and height")
        if channels not in (3, 4):
            raise ValueError(f"channels {channels!r}: expected 3 (RGB) or 4 (RGBA)")
        self.channels = int(channels)
        self.path = Path(path)
        self.size = (width, height)
        self.fps = float(fps)
        self.frame_count = 0
        self.encode_seconds = 0.0
        rate = _rate(fps)
        self._stack = contextlib.ExitStack()
        self._tmp = self._stack.enter_context(atomic_path(self.path, suffix=".mp4"))
        self._log = tempfile.TemporaryFile()
        cmd = [
            imageio_ffmpeg.get_ffmpeg_exe(), "-y", "-nostdin", "-v", "error",
            "-f", "rawvideo", "-pix_fmt", "rgb24" if channels == 3 else "rgba", "-s", f"{width}x{height}", "-framerate", rate, "-i", "-",
            "-an", "-c:v", "libx264", "-preset", preset, "-crf", str(int(crf)), "-pix_fmt", "yuv420p",
            "-r", rate, "-movflags", "+faststart", str(self._tmp),
        ]
        try:
            # its own session: a terminal's Ctrl-C reaches fae alone, which ends the video or drops it (ffmpeg
            # stopped by it too failed with status 255, and `fae serve --record` lost its recording)
            self._proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=self._log,
                                          start_new_session=True)
        except BaseException as exc:
            self._log.close()
            self._stack.__exit__(type(exc), exc, exc.__traceback__)
            raise
        self._open = True

    def write(self, image: np.ndarray) -> None:
        """Append one frame: (H, W, channels) uint8, H and W matching `size`."""
        if not self._open:
            raise VideoError(f"{self.path}: the video is already closed")
        image = np.asarray(image)
        w, h = self.size
        if image.shape != (h, w, self.channels) or image.dtype != np.uint8:
            raise ValueError(f"{self.path}: frame {self.frame_count}: expected ({h}, {w}, {self.channels}) uint8, "
                             f"got {image.shape} {image.dtype}")
        t = time.perf_counter()
        try:
            self._proc.stdin.write(np.ascontiguousarray(image).data)
        except (BrokenPipeError, OSError) as exc:
            raise VideoError(f"{self.path}: ffmpeg stopped accepting frames: {self._stderr() or exc}") from exc
        finally:
            self.encode_seconds += time.perf_counter() - t
        self.frame_count += 1

    def _stderr(self) -> str:
        self._log.seek(0)
        return self._log.read().decode("utf-8", "replace").strip()

    def close(self) -> None:
        """Finish encoding and move the file into place (raises VideoError if ffmpeg failed)."""
        if not self._open:
            return
        self._open = False
        t = time.perf_counter()
        try:
            with contextlib.suppress(BrokenPipeError, OSError):
                self._proc.stdin.close()
            status = self._proc.wait()
            self.encode_seconds += time.perf_counter() - t
            if self.frame_count == 0:
                raise VideoError(f"{self.path}: no frames were written")
            if status != 0:
                raise VideoError(f"{self.path}: ffmpeg failed with status {status}: {self._stderr()}")
        except BaseException as exc:
            self._log.close()
            self._stack.__exit__(type(exc), exc, exc.__traceback__)
            raise
        self._log.close()
        self._stack.close()  # renames the finished file onto self.path

    def abort(self) -> None:
        """Stop ffmpeg and discard the partial file; `path` is left untouched."""
        if not self._open:
            return
        self._open = False
        with contextlib.suppress(Exception):
            self._proc.kill()
        with contextlib.suppress(Exception):
            self._proc.wait()
        with contextlib.suppress(Exception):
            self._proc.stdin.close()
        self._log.close()
        exc = VideoError(f"{self.path}: aborted")
        self._stack.__exit__(type(exc), exc, None)

    def __enter__(self) -> "VideoWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    def __del__(self):
        if getattr(self, "_open", False):
            self.abort()
