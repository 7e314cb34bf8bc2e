"""The Player: FAP frames in, skin positions and bone poses out, one frame at a time.

Per frame (only precomputed arrays are used): FAP 1/2 records -> low-level values, added to
the frame's own; clamp (fae.mpeg4.faptables); one matmul to muscle/field activations and
the jaw pose (fae.animate.controls; the upper lids following the eyes' pitch,
lids_following_gaze), the closing lids' pulls led so that they reach the frame's pose by
its end (ActivationLead, per face); one solver step of the skin in the head's frame
(fae.sim), the jaw moving from its last pose over the frame and carrying the skin's holds;
FaceDefTable offsets added (a frame that repeats the previous one on skin that has settled
skips the solver); then the head pose (rotation about 7.1) carries skin and parts. What all faces of one head share is a PlayableHead, built once; a head
without a calibrated `fap_mapping` is calibrated by `playable_head` (fae.animate.calibrate,
tens of seconds; shipped heads carry theirs), never by a constructor.

The "fdt" engine (`playable_head(model, engine="fdt")`) moves the skin through the head's
FaceDefTables baked from this physics (fae.animate.bake; a head without them is baked on
load, minutes) and nothing else: per frame one multiply-add per non-zero FAP's table, no
solver, no settling; the rigid poses are the same. It is exact for one FAP alone at a
table's borders, settled, and adds FAPs up where the physics does not (docs/architecture.md).

    head = playable_head(model, device="cpu", engine="physics")  # once per head; or engine="fdt"
    player = Player(head)                                        # one per face, milliseconds
    positions = player.step(values_or_denseframe, dt=None)   # (V, 3) float64 metres
    for f in player.play(stream, fps=None): f.index, f.time, f.skin_vertices, f.bone_transforms
    player.reset()
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np

from fae.animate.bake import bake_tables, baked_faps, baked_model, has_baked_tables
from fae.animate.calibrate import calibrate, pull_fields
from fae.animate.ears import ear_tables
from fae.animate.controls import (LID_RESPONSE_SECONDS, ActivationLead, FapControls, MappingMismatch, lid_gaze_follow,
                                  lids_following_gaze, merge_lip_pairs)
from fae.animate.facedef import FaceDefOffsets
from fae.mpeg4.faptables import FAP_COUNT, SKIN_TRANSLATION_FAPS, clamp_values, fapu_of
from fae.animate.highlevel import highlevel_values
from fae.animate.rigid import RigidRig
from fae.io.facemodel import BONES
from fae.sim.build import skin_model
from fae.sim.skin import SkinOutput
from fae.sim.solver import SkinSolver

DEFAULT_FPS = 25.0
# Seconds of physics one step simulates at most. A longer frame (a gap in a stream's frame
# numbers, a tiny fps, dt=1e6 through the API) simulates only MAX_STEP_SECONDS: the skin
# has settled by then (a wide-open mouth on the shipped head is within 0.03 mm of its rest
# after 0.9 s), so the time left out would change nothing, and a step costs at most
# MAX_STEP_SECONDS / dt_max substeps (50) whatever its dt.
MAX_STEP_SECONDS = 1.0
SETTLED_MOTION = 1e-8  # metres: a frame moving no particle more than this has settled
ENGINES = ("physics", "fdt")  # the skin simulated, or moved by FaceDefTables baked from the simulation


@dataclass
class PlayedFrame:
    """One played frame.

    index            0-based frame index
    time             seconds
    skin_vertices    (V, 3) float64 metres, in the face frame (head pose applied)
    bone_transforms  bone name ("head", "jaw", "eye_l", "eye_r", "tongue") -> (4, 4) float64 rest -> now
    pupil_scale      {"eye_l", "eye_r"} -> pupil diameter / rest diameter (FAPs 29, 30)
    values           (68,) float64 the low-level FAP values applied (FAPU units)
    """

    index: int
    time: float
    skin_vertices: np.ndarray
    bone_transforms: dict[str, np.ndarray]
    pupil_scale: dict[str, float] = field(default_factory=dict)
    values: np.ndarray | None = None


def stream_frames(stream, fps: float | None, default_fps: float) -> tuple[Iterable, float]:
    """(frames, frames per second) to play: a FapStream's dense frames resampled to `fps`
    (None: its own rate), or an iterable of DenseFrames as it is, at `fps` or `default_fps`."""
    if hasattr(stream, "header"):
        from fae.io.frames import dense_frames

        return dense_frames(stream, fps=fps), float(fps or stream.header.fps)
    return stream, float(fps or default_fps)


class PlayableHead:
    """What every face of one head shares, built once: the calibrated model (`face`), its
    FAPU, the skin's static simulation model (`sim`, None for "fdt"), the FAP controls, the
    FaceDefTables this engine adds (`tables`: authored and ear tables for "physics", the
    baked ones and those of FAPs not baked for "fdt") and their static arrays, and the
    skin-moving FAPs this engine leaves the skin still for (`faps_without_tables`: for "fdt",
    those neither baked nor with a table of their own; none for "physics"). Any number
    of Players step from one PlayableHead (a server's clients), each with its own state.

    The constructor never calibrates or bakes: it refuses a model without a fitting FAP
    mapping (MappingMismatch) or, for "fdt", without baked tables (ValueError).
    `playable_head(model)` does that set-up, explicitly.
    """

    def __init__(self, model, device: str = "cpu", engine: str = "physics"):
        if engine not in ENGINES:
            raise ValueError(f"engine: expected one of {', '.join(ENGINES)}, got {engine!r}")
        FapControls(model)  # MappingMismatch: calibrate first (playable_head does)
        if engine == "fdt" and not has_baked_tables(model):
            raise ValueError("engine 'fdt': the head has no baked FaceDefTables (playable_head bakes them, "
                             "`fae bake` stores them)")
        self.face = model
        self.device = device
        self.engine = engine
        self.fapu = fapu_of(model)
        self.lid_gaze = lid_gaze_follow(model, self.fapu)  # (2,) IRISD units of lid close per AU of eye pitch
        authored = [t for t in model.face_def_tables if t.source == "authored"] + ear_tables(model, self.fapu)
        if engine == "fdt":
            baked = [t for t in model.face_def_tables if t.source == "physics"]
            covered = {(t.fap, t.part) for t in baked}
            self.tables = baked + [t for t in authored if (t.fap, t.part) not in covered]
            # a head baked for some FAPs only (`fae bake --faps`) leaves the skin still for the rest
            self.faps_without_tables = sorted(set(SKIN_TRANSLATION_FAPS) - baked_faps(model)
                                              - {int(t.fap) for t in self.tables})
            self.sim = None
            self.controls = FapControls(model)
            self.rest_skin = np.asarray(model.skin_vertices, dtype=np.float64)
        else:
            self.sim = skin_model(model, device=device, fields=pull_fields(model, self.fapu))
            self.controls = FapControls(model, self.sim)
            self.tables = authored
            self.rest_skin = None
            self.faps_without_tables = []
        self.facedef = FaceDefOffsets(self.tables, model.skin_vertex_count)  # each Player spawns its own buffers


def needs_calibration(model) -> bool:
    """Whether `model` lacks a FAP mapping that fits it (playable_head then calibrates it)."""
    try:
        FapControls(model)
    except MappingMismatch:
        return True
    return False


def playable_head(model, device: str = "cpu", engine: str = "physics") -> PlayableHead:
    """The PlayableHead of `model`, after the set-up it lacks: a head without a calibrated
    FAP mapping that fits is calibrated (fae.animate.calibrate, tens of seconds; store the
    result in its .glb to skip this), and for engine "fdt" a head without baked tables is
    baked (fae.animate.bake, minutes). The calibration runs on the CPU whatever `device`
    (its probes settle in threads, one solver each); the bake and the per-frame steps run
    on `device`."""
    if engine not in ENGINES:
        raise ValueError(f"engine: expected one of {', '.join(ENGINES)}, got {engine!r}")
    if needs_calibration(model):
        model = calibrate(model, device="cpu")
    if engine == "fdt" and not has_baked_tables(model):
        model = baked_model(model, bake_tables(Player(PlayableHead(model, device=device))), SKIN_TRANSLATION_FAPS)
    return PlayableHead(model, device=device, engine=engine)


class Player:
    """Plays FAP frames on one face of a PlayableHead (see module docstring): the state,
    control, solver, FaceDefTable buffers and rigid-pose caches of this face alone. Building
    one is cheap (milliseconds): the head's static arrays are shared."""

    def __init__(self, head: PlayableHead):
        if not isinstance(head, PlayableHead):
            raise TypeError(f"Player: expected a PlayableHead, got {type(head).__name__} "
                            "(fae.animate.player.playable_head(model) builds one, calibrating what it lacks)")
        self.head = head
        self.rig = RigidRig(head.face, head.fapu)
        self.facedef = head.facedef.spawn()
        if head.sim is not None:
            self.solver = SkinSolver(head.sim)
            self.skin = SkinOutput(head.sim)
            self.state, self.control, self._rest = head.sim.state(), head.sim.control(), head.sim.state()
        self._R = np.tile(np.eye(3), (2, 1, 1))
        self._t = np.zeros((2, 3))
        self.fps = DEFAULT_FPS
        self.lead = ActivationLead(head.controls.lid_rows, LID_RESPONSE_SECONDS)
        self._carry = True  # the jaw moves over a frame, carrying the holds (else it is placed)
        self.reset()

    # what the head shares, read through the player
    face = property(lambda self: self.head.face)
    fapu = property(lambda self: self.head.fapu)
    sim = property(lambda self: self.head.sim)
    controls = property(lambda self: self.head.controls)
    tables = property(lambda self: self.head.tables)
    lid_gaze = property(lambda self: self.head.lid_gaze)
    engine = property(lambda self: self.head.engine)

    @property
    def fap_mapping(self) -> dict[str, np.ndarray]:
        """The calibrated mapping in use (store it in the head's .glb to skip calibration)."""
        return self.face.fap_mapping

    @contextmanager
    def lead_off(self):
        """Steps inside go without the lids' lead (ActivationLead), and the jaw is placed
        where a frame puts it rather than moved there (its carry not taken from the drag):
        a pose held from rest and settled as the calibration settles it
        (fae.animate.verify.settled_skin). Led, a lid held at 720 settled 0.2 mm further
        open: its contact with the lower lid keeps how it got there."""
        lead, self.lead = self.lead, ActivationLead(np.zeros(0, dtype=np.int64), LID_RESPONSE_SECONDS)
        carry, self._carry = self._carry, False
        try:
            yield self
        finally:
            self.lead, self._carry = lead, carry

    def reset(self) -> None:
        """Back to the neutral face at rest (in place: the solver's recorded launches stay valid)."""
        if self.sim is not None:
            self.state.assign(self._rest)
            self.control.set(muscle_activation=np.zeros(self.sim.muscle_count),
                             bone_rotation=np.tile(np.eye(3), (2, 1, 1)), bone_translation=np.zeros((2, 3)))
            self._q = self.sim.particle_q.numpy().copy()
        self.bone_transforms = {b: np.eye(4) for b in BONES}
        self.pupil_scale = {"eye_l": 1.0, "eye_r": 1.0}
        self.values = np.zeros(FAP_COUNT)
        self.frame_index = 0
        self._settled = True
        self._last_dt = None
        self.lead.reset()

    def frame_values(self, frame) -> np.ndarray:
        """(68,) clamped low-level values of a DenseFrame or a (68,) array (FAPU units)."""
        if hasattr(frame, "values"):
            v = np.asarray(frame.values, dtype=np.float64)
            extra = highlevel_values(getattr(frame, "viseme", None), getattr(frame, "expression", None))
        else:
            v = np.asarray(frame, dtype=np.float64)
            extra = 0.0
        if v.shape != (FAP_COUNT,):
            raise ValueError(f"FAP values: expected shape ({FAP_COUNT},) indexed by FAP number - 1, got {v.shape}")
        v = v.copy()
        v[:2] = 0.0
        return clamp_values(v + extra)

    def step(self, frame, dt: float | None = None) -> np.ndarray:
        """Advance one frame of `dt` seconds (None: 1/fps) with FAP `frame`; (V, 3) float64 metres.

        dt must be a positive number of seconds (+inf included: the frame lasts for ever);
        the skin is simulated for at most MAX_STEP_SECONDS of it (see there).
        """
        v = self.frame_values(frame)
        dt = 1.0 / self.fps if dt is None else float(dt)
        if not dt > 0.0:  # NaN fails this too
            raise ValueError(f"step: dt must be a positive number of seconds, got {dt!r}")
        dt = min(dt, MAX_STEP_SECONDS)
        if self.sim is None:
            return self._table_step(v)
        activation, jaw = self.controls.controls(lids_following_gaze(v, self.lid_gaze))
        activation = self.lead.apply(activation, dt)
        J = self.rig.jaw(*jaw)
        self._R[1], self._t[1] = J[:3, :3], J[:3, 3]
        if not (self._settled and dt == self._last_dt and np.array_equal(v, self.values)):
            # a held frame on settled skin needs no step (SETTLED_MOTION: its fixed point)
            # the jaw moves from its last pose over the frame, carrying the skin's holds
            self.control.set(muscle_activation=activation, bone_rotation=self._R, bone_translation=self._t,
                             moving=self._carry)
            self.solver.step(self.sim, self.state, self.control, dt, self.state)
            q = self.state.particle_q.numpy()
            self._settled = bool(np.abs(q - self._q).max() < SETTLED_MOTION) if len(q) else True
            self._q[:] = q
        self._last_dt = dt
        bones = self.rig.poses(v, J)
        H = bones["head"]
        skin = self.skin.positions(self.state, self.control, H)
        offsets = self.facedef.offsets(v)
        if offsets is not None:
            skin += offsets @ H[:3, :3].T
        self.bone_transforms = bones
        self.pupil_scale = self.rig.pupil_scale(v)
        self.values = v
        self.frame_index += 1
        return skin

    def _table_step(self, v: np.ndarray) -> np.ndarray:
        """The "fdt" engine's frame: rest skin + FaceDefTable offsets, carried by the head pose.
        Each lip table was baked alone: twins sent alike are merged as the physics merges
        them (merge_lip_pairs), or a corner both move would move twice as far."""
        _, jaw = self.controls.controls(v)
        bones = self.rig.poses(v, self.rig.jaw(*jaw))
        lids = lids_following_gaze(v, self.lid_gaze)
        skin = self.facedef.displaced(merge_lip_pairs(lids, self.controls.pair_overlap), self.head.rest_skin,
                                      bones["head"])
        self.bone_transforms = bones
        self.pupil_scale = self.rig.pupil_scale(v)
        self.values = v
        self.frame_index += 1
        return skin

    def play(self, stream, fps: float | None = None) -> Iterator[PlayedFrame]:
        """Play a FapStream (resampled to `fps`, None: its own) or an iterable of DenseFrames."""
        frames, rate = stream_frames(stream, fps, self.fps)
        self.fps = rate
        for i, frame in enumerate(frames):
            skin = self.step(frame, dt=1.0 / rate)
            yield PlayedFrame(index=int(getattr(frame, "index", i)), time=float(getattr(frame, "time", i / rate)),
                              skin_vertices=skin, bone_transforms={k: v.copy() for k, v in self.bone_transforms.items()},
                              pupil_scale=dict(self.pupil_scale), values=self.values.copy())
