"""Faces the server drives: the frame-consumer interface and the workers that step them.

A face turns one dense FAP frame into a pose. The server never does that CPU work on its
event loop: each face lives in a :class:`FaceWorker`, which builds the face and then runs
its steps one after another, in submission order, on a pool of threads (one per core,
shared by a :class:`FacePool`'s faces). Warp releases the GIL during launches, so several
faces use several cores.
"""

from __future__ import annotations

import asyncio
import math
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Callable, Protocol

import numpy as np

from fae.cores import usable_cores
from fae.io.frames import DenseFrame


@dataclass(frozen=True)
class Pose:
    """The face after one frame.

    skin_vertices    (V, 3) float64, metres: deformed epidermis
    bone_transforms  bone name ("head", "jaw", "eye_l", "eye_r", "tongue") -> (4, 4)
                     float64 rigid transform in the face frame (metres), or empty
    pupil_scale      eye bone ("eye_l", "eye_r") -> pupil diameter / rest diameter, or empty
    """

    skin_vertices: np.ndarray
    bone_transforms: dict
    pupil_scale: dict = field(default_factory=dict)


class FrameConsumer(Protocol):
    """One face: `step` is called with each dense frame of one stream, in order."""

    def step(self, frame: DenseFrame, dt: float) -> Pose:
        """One frame (frame.values (68,) float64 held/clamped FAP values, FAP n at index
        n-1, plus the held viseme/expression records) lasting dt seconds."""

    def reset(self) -> None:
        """Back to the neutral face at rest."""


FaceFactory = Callable[[], FrameConsumer]

FRAME_SLICE = 0.1  # seconds of a long frame stepped per job (5 substeps on the shipped head)


class FaceWorker:
    """A face, built and stepped on a pool of threads, its steps one after another.

    factory   called once, in a pool thread, to build the face (model set-up and kernel
              compilation stay off the event loop)
    name      thread name prefix of an own pool, for diagnostics
    executor  the pool to run on (shared by a FacePool's faces: one thread per core), or
              None for a pool of one thread of the worker's own
    """

    def __init__(self, factory: FaceFactory, name: str = "fae-face", executor: ThreadPoolExecutor | None = None) -> None:
        self._own_executor = executor is None
        self._executor = executor or ThreadPoolExecutor(max_workers=1, thread_name_prefix=name)
        self._face_future = self._executor.submit(factory)
        self._last: asyncio.Future | None = None  # this face's latest queued job
        self._closed = False
        self.step_count = 0

    def _face(self) -> FrameConsumer:
        return self._face_future.result()

    def _step(self, frame: DenseFrame, dt: float) -> Pose:
        pose = self._face().step(frame, dt)
        self.step_count += 1
        return pose

    def _queue(self, fn, *args) -> asyncio.Future:
        """Run fn(*args) in the pool once this face's previous job has finished (whatever its
        outcome): a face is never stepped by two threads at once, and in submission order.

        The chain links the worker's own tasks; callers get a shield of theirs, so a caller
        that stops waiting (a playback cancelled mid-step) cannot cut the chain while the
        job still runs in its thread."""
        loop = asyncio.get_running_loop()
        previous = self._last

        async def run():
            if previous is not None and not previous.done():
                await asyncio.wait([previous])
            if self._closed:
                raise asyncio.CancelledError("the face was closed")
            return await loop.run_in_executor(self._executor, fn, *args)

        task = asyncio.ensure_future(run())
        # a job nobody waits for any more must not warn that its outcome was never read
        task.add_done_callback(lambda t: t.cancelled() or t.exception())
        self._last = task
        return asyncio.shield(task)

    def submit(self, frame: DenseFrame, dt: float) -> asyncio.Future:
        """Queue one step; the returned future resolves to its Pose. Steps run in order.

        A frame longer than FRAME_SLICE seconds (a gap in a stream's frame numbers, a low
        fps) is stepped as equal slices of at most FRAME_SLICE, together the part of it the
        Player simulates (at most fae.animate.player.MAX_STEP_SECONDS): each slice is a job
        of its own on the shared pool, so other faces' steps take turns with them instead
        of waiting behind one long step."""
        if not dt > FRAME_SLICE:
            return self._queue(self._step, frame, dt)
        from fae.animate.player import MAX_STEP_SECONDS

        total = min(float(dt), MAX_STEP_SECONDS)
        slices = max(1, math.ceil(total / FRAME_SLICE - 1e-9))
        for _ in range(slices - 1):
            self._queue(self._step, frame, total / slices)
        return self._queue(self._step, frame, total / slices)

    async def ready(self) -> None:
        """Wait until the face is built; raises what its factory raised."""
        await asyncio.wrap_future(self._face_future)

    async def reset(self) -> None:
        """Reset the face, after every step queued before this call."""
        await self._queue(lambda: self._face().reset())

    def close(self) -> None:
        """Drop queued steps (and the build, if it has not started); a running step
        finishes (an own pool's thread then ends)."""
        self._closed = True
        self._face_future.cancel()
        if self._last is not None and not self._last.done():
            self._last.cancel()
        if self._own_executor:
            self._executor.shutdown(wait=False, cancel_futures=True)


class FacePool:
    """Hands out FaceWorkers, each with a new face, keeping `spares` of them built ahead;
    all of them build and step on one pool of threads, one per core.

    Building a Player takes seconds; with a spare, a client's face is (usually) ready when
    its header arrives, and the next spare is built while that client streams. One thread
    per core, not per face: ten faces in ten threads fought over the interpreter lock (a
    step of 6 ms of CPU took 30 ms), while Warp's kernels, which release it, already keep
    a core busy per thread.

    factory  builds one face (called in a pool thread)
    spares   faces kept built ahead (0: each face is built when it is asked for)
    threads  pool size (default: the cores this process may use)
    """

    def __init__(self, factory: FaceFactory, spares: int = 0, threads: int | None = None) -> None:
        if spares < 0:
            raise ValueError(f"spares: expected >= 0, got {spares}")
        self.factory = factory
        self.spares = spares
        self._executor = ThreadPoolExecutor(max_workers=threads or usable_cores(), thread_name_prefix="fae-face")
        self._ready: list[FaceWorker] = []
        self._fill()

    def _fill(self) -> None:
        while len(self._ready) < self.spares:
            self._ready.append(FaceWorker(self.factory, executor=self._executor))

    def take(self) -> FaceWorker:
        """A worker whose face is built or being built; the caller closes it."""
        worker = self._ready.pop(0) if self._ready else FaceWorker(self.factory, executor=self._executor)
        self._fill()
        return worker

    def close(self) -> None:
        """Release the spares and the pool (running steps finish)."""
        for worker in self._ready:
            worker.close()
        self._ready.clear()
        self.spares = 0
        self._executor.shutdown(wait=False, cancel_futures=True)


class PlayerFace:
    """One face of a head animated by fae's Player (fae.animate.player), as a FrameConsumer.

    head    a fae.animate.player.PlayableHead, shared read-only between faces (built once
            with `playable_head(model)`, which calibrates a head that needs it)
    """

    def __init__(self, head) -> None:
        from fae.animate.player import Player

        self.player = Player(head)

    def step(self, frame: DenseFrame, dt: float) -> Pose:
        skin = self.player.step(frame, dt=dt)
        return Pose(np.asarray(skin, dtype=np.float64),
                    {name: np.array(T, dtype=np.float64) for name, T in self.player.bone_transforms.items()},
                    dict(self.player.pupil_scale))

    def reset(self) -> None:
        self.player.reset()


def player_face_factory(head) -> FaceFactory:
    """A factory building a new PlayerFace of `head` (a PlayableHead) for each stream:
    milliseconds, the head's static arrays shared. Faces are built one at a time (a
    Player's first launches are recorded, fae.sim.launch)."""
    lock = threading.Lock()

    def build() -> PlayerFace:
        with lock:
            return PlayerFace(head)

    return build
