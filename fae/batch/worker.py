"""One batch job, where it runs: a .fap stream's bytes and a head's bytes in, an mp4's bytes out.

    render_job(spec, stream_bytes, head_bytes) -> dict(video, frames, seconds, setup_seconds,
                                                       head_reused, warnings)

A head's set-up (reading the .glb, building the skin simulation and its kernels, the GL
renderer) costs seconds, a short stream's frames less; so each worker thread keeps the
Players and renderers of the last heads it played, keyed by the head's checksum (the
same bytes under any path are the same head), and a job on a known head only resets the
Player to rest. The video is rendered exactly as `fae play` renders it
(fae.render.play.render_video). Nothing here knows about Dask.

A job that cannot be rendered raises JobFailed with a one-line reason naming the job's
own stream or head (not the worker's temporary copies).
"""

from __future__ import annotations

import tempfile
import threading
import time
from collections import OrderedDict
from pathlib import Path

# Heads kept per worker thread: a batch usually cycles through a few heads; each costs
# the skin model's arrays and a GL context per image size and view.
MAX_CACHED_HEADS = 2


class JobFailed(RuntimeError):
    """The job's inputs could not be rendered; the message says why (one line)."""


class _HeadSetup:
    """A head made ready to play: its FaceModel, a Player and renderers by (size, view)."""

    def __init__(self, model, player):
        self.model = model
        self.player = player
        self.renderers: dict[tuple, object] = {}

    def renderer(self, size: tuple[int, int], view: str):
        from fae.render.renderer import FaceRenderer

        key = (tuple(size), view)
        if key not in self.renderers:
            self.renderers[key] = FaceRenderer(self.model, size=size, view=view)
        return self.renderers[key]

    def close(self) -> None:
        for renderer in self.renderers.values():
            renderer.close()
        self.renderers.clear()


_local = threading.local()  # GL contexts and Players belong to the thread that made them


def _cache() -> OrderedDict:
    if not hasattr(_local, "heads"):
        _local.heads = OrderedDict()
    return _local.heads


def cached_heads() -> list[str]:
    """Checksums of the heads this thread holds ready, oldest first."""
    return list(_cache())


def clear_cache() -> None:
    """Free every head this thread holds (GL contexts included)."""
    heads = _cache()
    while heads:
        heads.popitem(last=False)[1].close()


def _head_setup(head_sha256: str, head_bytes: bytes, head_name: str) -> tuple[_HeadSetup, bool]:
    heads = _cache()
    if head_sha256 in heads:
        heads.move_to_end(head_sha256)
        return heads[head_sha256], True
    from fae.animate.player import Player, playable_head
    from fae.io.facemodel_gltf import FaceModelError, facemodel_from_glb

    try:
        model = facemodel_from_glb(head_bytes, name=head_name)
    except FaceModelError as exc:
        raise JobFailed(str(exc)) from None
    setup = _HeadSetup(model, Player(playable_head(model, device="cpu")))
    while len(heads) >= MAX_CACHED_HEADS:
        heads.popitem(last=False)[1].close()
    heads[head_sha256] = setup
    return setup, False


def render_job(spec: dict, stream_bytes: bytes, head_bytes: bytes) -> dict:
    """Render one job; `spec` holds stream (its name, for messages), head, head_sha256,
    view, size [w, h], fps (None: the stream's) and output (a file name)."""
    from fae.io.fap import FapFormatError, read_fap
    from fae.io.frames import dense_frames
    from fae.render.play import render_video
    from fae.render.video import VideoError

    t0 = time.perf_counter()
    stream_name = str(spec["stream"])
    with tempfile.TemporaryDirectory(prefix="fae-batch-") as folder:
        stream_path = Path(folder) / Path(stream_name).name
        stream_path.write_bytes(stream_bytes)
        video_path = Path(folder) / spec["output"]

        def named(message: str) -> str:  # the user's file, not this worker's copy of it
            return message.replace(str(stream_path), stream_name)

        try:
            stream = read_fap(stream_path)
            for _ in stream:  # a bad stream fails here, before paying for a head's set-up
                pass
        except FapFormatError as exc:
            raise JobFailed(named(str(exc))) from None
        setup, reused = _head_setup(spec["head_sha256"], head_bytes, spec["head"])
        size = (int(spec["size"][0]), int(spec["size"][1]))
        renderer = setup.renderer(size, spec["view"])
        setup_seconds = time.perf_counter() - t0
        try:
            fps = float(spec["fps"]) if spec.get("fps") else float(stream.header.fps)  # the reader's >= MIN_FPS
            player = setup.player
            player.reset()
            frames = dense_frames(stream, fps=spec.get("fps"))
            timings = render_video(player.play(frames, fps=fps), renderer, video_path, fps)
        except FapFormatError as exc:
            raise JobFailed(named(str(exc))) from None
        except (VideoError, ValueError) as exc:
            raise JobFailed(named(f"{stream_name}: {exc}")) from None
        video = video_path.read_bytes()
    return {"video": video, "frames": timings.frames, "seconds": time.perf_counter() - t0,
            "setup_seconds": setup_seconds, "head_reused": reused,
            "warnings": [named(w) for w in frames.warnings]}
