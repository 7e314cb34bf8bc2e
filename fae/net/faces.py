"""Faces the server drives: the frame-consumer interface and the thread that steps one face.

A face turns one dense FAP frame into a pose. The server never does that CPU work on its
event loop: each face lives in its own :class:`FaceWorker`, a single worker thread that
builds the face and then runs its steps one after another, in submission order. Warp
releases the GIL during launches, so several faces use several cores.
"""

from __future__ import annotations

import asyncio
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from typing import Callable, Protocol

import numpy as np

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


class FaceWorker:
    """A face and the one thread that builds and steps it.

    factory  called once, in the worker thread, to build the face (model set-up and
             kernel compilation stay off the event loop)
    name     thread name prefix, for diagnostics
    """

    def __init__(self, factory: FaceFactory, name: str = "fae-face") -> None:
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix=name)
        self._face_future = self._executor.submit(factory)
        self.step_count = 0

    def _face(self) -> FrameConsumer:
        return self._face_future.result()

    def _step(self, frame: DenseFrame, dt: float) -> Pose:
        pose = self._face().step(frame, dt)
        self.step_count += 1
        return pose

    def submit(self, frame: DenseFrame, dt: float) -> asyncio.Future:
        """Queue one step; the returned future resolves to its Pose. Steps run in order."""
        loop = asyncio.get_running_loop()
        return loop.run_in_executor(self._executor, self._step, frame, dt)

    async def ready(self) -> None:
        """Wait until the face is built; raises what its factory raised."""
        await asyncio.wrap_future(self._face_future)

    async def reset(self) -> None:
        """Reset the face, after every step queued before this call."""
        loop = asyncio.get_running_loop()
        await loop.run_in_executor(self._executor, lambda: self._face().reset())

    def close(self) -> None:
        """Drop queued steps and let the thread end once the running step returns."""
        self._executor.shutdown(wait=False, cancel_futures=True)


class FacePool:
    """Hands out FaceWorkers, each with a new face, keeping `spares` of them built ahead.

    Building a Player takes seconds; with a spare, a client's face is (usually) ready when
    its header arrives, and the next spare is built while that client streams.

    factory  builds one face (called in the worker's thread)
    spares   faces kept built ahead (0: each face is built when it is asked for)
    """

    def __init__(self, factory: FaceFactory, spares: int = 0) -> None:
        if spares < 0:
            raise ValueError(f"spares: expected >= 0, got {spares}")
        self.factory = factory
        self.spares = spares
        self._ready: list[FaceWorker] = []
        self._fill()

    def _fill(self) -> None:
        while len(self._ready) < self.spares:
            self._ready.append(FaceWorker(self.factory))

    def take(self) -> FaceWorker:
        """A worker whose face is built or being built; the caller closes it."""
        worker = self._ready.pop(0) if self._ready else FaceWorker(self.factory)
        self._fill()
        return worker

    def close(self) -> None:
        """Release the spares."""
        for worker in self._ready:
            worker.close()
        self._ready.clear()
        self.spares = 0


class PlayerFace:
    """A FaceModel animated by fae's Player (fae.animate.player), as a FrameConsumer.

    model   the head (shared read-only between faces); give it a calibrated fap_mapping
            (see :func:`playable_model`), or every face calibrates it again on build
    device  Warp device ("cpu" or "cuda:0")
    player  a Player to use (one spawned from another, see `player_face_factory`), or None
            to build one
    """

    def __init__(self, model, device: str = "cpu", player=None) -> None:
        from fae.animate.player import Player

        self.player = player if player is not None else Player(model, device=device)

    def step(self, frame: DenseFrame, dt: float) -> Pose:
        skin = self.player.step(frame, dt=dt)
        return Pose(np.asarray(skin, dtype=np.float64),
                    {name: np.array(T, dtype=np.float64) for name, T in self.player.bone_transforms.items()},
                    dict(self.player.pupil_scale))

    def reset(self) -> None:
        self.player.reset()


def playable_model(model, device: str = "cpu"):
    """`model` with the FAP mapping its Players use: itself when it carries one that fits,
    else a copy holding the mapping calibrated now (tens of seconds, once).

    Building one Player here also compiles (or loads) the simulation kernels, so the
    first client does not wait for them.
    """
    from fae.animate.player import Player

    player = Player(model, device=device)
    if player.fap_mapping is model.fap_mapping:
        return model
    return replace(model, fap_mapping=player.fap_mapping)


def player_face_factory(model, device: str = "cpu") -> FaceFactory:
    """A factory building a new PlayerFace on `model` for each stream. The first face builds
    the head's simulation (seconds); every later one spawns from it (milliseconds), sharing
    its static arrays."""
    first: list = []
    lock = threading.Lock()

    def build() -> PlayerFace:
        from fae.animate.player import Player

        with lock:
            if not first:
                first.append(Player(model, device=device))
            return PlayerFace(model, device, first[0].spawn())

    return build
