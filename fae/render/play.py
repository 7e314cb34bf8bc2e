"""Frames -> video: simulation and rendering overlap.

The frame source (normally `fae.animate.player.Player.play(stream)`) runs in a producer
thread and feeds a small bounded queue; the calling thread renders each frame and pipes
it to ffmpeg, which encodes in its own process. Warp kernel launches and OSMesa's
rasterizer release the GIL, so on a 2-core machine simulation, rendering and encoding
proceed side by side (tools/bench_play.py measures the gain against the serial loop).
"""

from __future__ import annotations

import os
import queue
import re
import shutil
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable

import numpy as np

from fae.io.atomic import staging_folder
from fae.render.png import write_png
from fae.render.renderer import FaceRenderer
from fae.render.video import VideoWriter

_DONE = object()


FRAME_NAME = re.compile(r"frame_\d{5,}\.png")  # what frames_dir receives: frame_00000.png, ...


class EmptyStreamError(ValueError):
    """The frames to render were none (a stream without a frame line)."""


@dataclass
class PlayTimings:
    """What one run cost, in seconds of wall-clock time.

    frames    frames written
    wall      whole run, first frame requested to file in place
    simulate  inside the frame source (the simulation), summed over frames
    render    inside FaceRenderer.render, summed
    encode    handing frames to ffmpeg and waiting for it to finish, summed
    """

    frames: int
    wall: float
    simulate: float
    render: float
    encode: float

    @property
    def fps(self) -> float:
        return self.frames / self.wall if self.wall > 0 else 0.0


def _snapshot(frame) -> tuple[np.ndarray | None, dict, dict]:
    """(skin_vertices, bone_transforms, pupil_scale) copied from a frame: a source may
    reuse its buffers for the next frame."""
    skin = getattr(frame, "skin_vertices", None)
    bones = getattr(frame, "bone_transforms", None) or {}
    pupils = getattr(frame, "pupil_scale", None) or {}
    return (None if skin is None else np.array(skin, dtype=np.float64, copy=True),
            {k: np.array(v, dtype=np.float64, copy=True) for k, v in bones.items()},
            {k: float(v) for k, v in pupils.items()})


class _Producer(threading.Thread):
    """Pulls frames from `source` into `out` until it ends, fails or `stop` is set."""

    def __init__(self, source: Iterable, out: queue.Queue, stop: threading.Event):
        super().__init__(name="fae-simulation", daemon=True)
        self.source, self.out, self.stop = source, out, stop
        self.seconds = 0.0

    def _put(self, item) -> bool:
        while not self.stop.is_set():
            try:
                self.out.put(item, timeout=0.05)
                return True
            except queue.Full:
                continue
        return False

    def run(self) -> None:
        it = iter(self.source)
        try:
            while not self.stop.is_set():
                t = time.perf_counter()
                try:
                    frame = next(it)
                except StopIteration:
                    break
                item = _snapshot(frame)
                self.seconds += time.perf_counter() - t
                if not self._put(item):
                    break
        except BaseException as exc:  # handed to the consumer, raised there
            self._put(exc)
            return
        finally:
            close = getattr(it, "close", None)
            if self.stop.is_set() and close is not None:
                try:
                    close()
                except Exception:
                    pass
        self._put(_DONE)


def _frames_overlapped(source: Iterable, timings: dict, queue_size: int):
    q: queue.Queue = queue.Queue(maxsize=queue_size)
    stop = threading.Event()
    producer = _Producer(source, q, stop)
    producer.start()
    try:
        while True:
            item = q.get()
            if item is _DONE:
                break
            if isinstance(item, BaseException):
                raise item
            yield item
    finally:
        stop.set()
        while producer.is_alive():
            try:
                q.get(timeout=0.05)
            except queue.Empty:
                pass
        producer.join()
        timings["simulate"] = producer.seconds


def _frames_serial(source: Iterable, timings: dict):
    it = iter(source)
    timings["simulate"] = 0.0
    while True:
        t = time.perf_counter()
        try:
            frame = next(it)
        except StopIteration:
            return
        item = _snapshot(frame)
        timings["simulate"] += time.perf_counter() - t
        yield item


def render_video(source: Iterable, renderer: FaceRenderer, path: str | os.PathLike, fps: float,
                 frames_dir: str | os.PathLike | None = None, overlap: bool = True,
                 on_frame: Callable[[int], None] | None = None, queue_size: int = 4,
                 crf: int = 20, preset: str = "veryfast") -> PlayTimings:
    """Render every frame of `source` with `renderer` into the H.264 mp4 `path` at `fps`.

    source      iterable of frames with `skin_vertices` (V, 3) metres, `bone_transforms`
                {bone: (4, 4)} and optionally `pupil_scale` {eye: float}
                (fae.animate.player.PlayedFrame)
    frames_dir  also write each frame as `frame_00000.png`, ... into this existing folder
                (its earlier frame_*.png replaced, and only when the video is written)
    overlap     run the source in a producer thread (False: one thread, for comparison)
    on_frame    called with the number of frames done after each frame (progress bars)

    The video appears at `path` only when every frame is written; an exception from the
    source (e.g. a malformed stream part-way) or anywhere else leaves no file behind and
    propagates.
    """
    if frames_dir is not None and not Path(frames_dir).is_dir():
        raise FileNotFoundError(f"{frames_dir}: frames folder does not exist")
    timings = {"simulate": 0.0}
    render_s = 0.0
    count = 0
    t0 = time.perf_counter()
    # the frames go to a hidden folder inside frames_dir and replace its frame_NNNNN.png
    # only when the video is written: a failed run leaves the folder as it was
    staging = None if frames_dir is None else staging_folder(frames_dir, "frames")
    frames = _frames_overlapped(source, timings, queue_size) if overlap else _frames_serial(source, timings)
    try:
        with VideoWriter(path, renderer.size, fps, crf=crf, preset=preset, channels=4) as video:
            for skin, bones, pupils in frames:
                t = time.perf_counter()
                image = renderer.render_rgba(skin, bones, pupils)
                render_s += time.perf_counter() - t
                video.write(image)
                if staging is not None:
                    write_png(staging / f"frame_{count:05d}.png", image[:, :, :3], compress_level=1)
                count += 1
                if on_frame is not None:
                    on_frame(count)
            if count == 0:
                raise EmptyStreamError("the stream produced no frames")
        if staging is not None:
            for old in Path(frames_dir).glob("frame_*.png"):  # an earlier, longer run's (not frame_cover.png)
                if FRAME_NAME.fullmatch(old.name):
                    old.unlink()
            for new in sorted(staging.iterdir()):
                new.replace(Path(frames_dir) / new.name)
    finally:
        frames.close()
        if staging is not None:
            shutil.rmtree(staging, ignore_errors=True)
    return PlayTimings(frames=count, wall=time.perf_counter() - t0, simulate=timings["simulate"],
                       render=render_s, encode=video.encode_seconds)
