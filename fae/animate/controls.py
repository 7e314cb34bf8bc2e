"""FAP values -> simulation controls, through a head's calibrated `fap_mapping` (one matmul).

controls(v) = sum_k max(w_k, 0) gain_pos[k] + max(-w_k, 0) gain_neg[k], w_k = s_k(u_k) u_k,
u = v - jaw_follow v_3: a lip FAP's controls also take back what open_jaw carries its point
by (fae.animate.mapping). s_k is piecewise linear over table_values[k] (see
fae.animate.calibrate) where u_k moves the point the way the FAP's own value does,
hold_scale[k] otherwise (calibrated with the jaw opening alone): the table scales of a
lip raised alone, which must push the other lip too, would lift a lip the jaw has
lowered far past its place. An inner lip FAP and its outer twin sent the same way are
scaled together so that the larger request is met, not their sum where their points
overlap (merge_lip_pairs, fae.animate.mapping). Muscle contractions are kept >= 0 and
every control is bounded, whatever the input. The lids' pull fields are led while they
close (ActivationLead, one per face), so that a blink one frame long closes.
"""

from __future__ import annotations

import numpy as np

from fae.animate.mapping import FORMAT_VERSION, JAW_CONTROLS, JAW_OPEN, LIP_PAIRS, field_faps
from fae.mpeg4.faps import FAP_COUNT

ACTIVATION_LIMIT = 50.0
# rad: the widest opening; below the angle where the chin (2.1) is lowest (about 0.6 rad
# on the generic head with its condylar glide, fae.animate.rigid), so the chin goes down
# monotonically with open_jaw and visemes
JAW_ANGLE_LIMIT = 0.5


# The lids' skin follows its pull fields as a first-order lag of about LID_RESPONSE_SECONDS
# (the shipped head's upper lid: 0.59, 0.85, 0.96 of a step in its first three 40 ms
# frames; refitted to 0.048 s when the fold guard grew stronger, fae.sim.build: at 0.045 a
# one-frame blink then stopped 0.5 mm short of closed). A blink sent as one frame at 1024
# between 341 and 512 (eyes_head.fap) left the lid 2.7 mm short of closed at its deepest
# frame, the eyeball's white showing (now 0.3 mm further down than settled closed, on the
# lower lid); the xface streams' 512, 1024, 1024, 512 closed only on its second frame at
# 1024 (2.0 mm open on the first; now 0.2 mm). A FAP value is the pose of its frame: the
# closing lids' pulls are led to reach it (ActivationLead). Opening keeps its lag (led, a
# lid opened 2 mm past its rest for two frames; real lids open slower than they close).
LID_FAPS = (19, 20, 21, 22)
LID_RESPONSE_SECONDS = 0.048


class ActivationLead:
    """Per face: the activations `rows` of the controls, led while they rise, so that skin
    following each as a first-order lag of `seconds` reaches the frame's activation by the
    frame's end (the pull of a frame of length dt is (a - e r) / (1 - e), e = exp(-dt /
    seconds), r what the lag had reached: a step is pulled 1.8x for one 40 ms frame, then
    as asked), within ACTIVATION_LIMIT. A falling activation is passed as it is; the lag's
    reach follows whatever was pulled. The lag was fitted at 25 fps: the lid has inertia
    the model lacks, so shorter frames are led less well (a step's first 10 ms frame at
    100 fps is pulled 5.3x; eyes_head's blink sent at 100 fps ends its 40 ms at 1024 with a
    2.1 mm gap, 5.2 without the lead, 1.3 at 25 fps; settled closed: 1.6)."""

    def __init__(self, rows: np.ndarray, seconds: float):
        self.rows = np.asarray(rows, dtype=np.int64)
        self.seconds = float(seconds)
        self.reached = np.zeros(len(self.rows))

    def reset(self) -> None:
        """At rest: nothing reached."""
        self.reached[:] = 0.0

    def apply(self, activation: np.ndarray, dt: float) -> np.ndarray:
        """The activations (M,) to simulate a frame of dt seconds with, for the frame's own
        `activation` (M,); updates what the lag has reached."""
        if len(self.rows) == 0:
            return activation
        a = activation[self.rows]
        e = float(np.exp(-dt / self.seconds))
        gone = float(-np.expm1(-dt / self.seconds))  # 1 - e, exact for short frames too
        rising = a > self.reached
        pull = a.copy()
        if gone > 0.0:
            pull[rising] = np.minimum((a[rising] - e * self.reached[rising]) / gone, ACTIVATION_LIMIT)
        self.reached = pull + (self.reached - pull) * e  # = a, unless the pull was bounded
        out = activation.copy()
        out[self.rows] = pull
        return out


_INNER = np.array([k - 1 for k, _ in LIP_PAIRS])
_OUTER = np.array([o - 1 for _, o in LIP_PAIRS])


def merge_lip_pairs(values: np.ndarray, overlap: np.ndarray) -> np.ndarray:
    """(68,) `values` with each inner lip FAP and its outer twin (LIP_PAIRS) that point the
    same way scaled by max / (max + overlap x min) of their magnitudes (overlap (68,), 0..1,
    the mapping's pair_overlap): the point of the larger request then moves as far as it
    asks, where moving each FAP's own point by its value would move it by the sum. One FAP
    alone, twins pointing opposite ways, or points that do not overlap are unchanged."""
    a, b = values[_INNER], values[_OUTER]
    big, small = np.maximum(np.abs(a), np.abs(b)), np.minimum(np.abs(a), np.abs(b))
    f = np.where(a * b > 0.0, big / np.maximum(big + overlap[_INNER] * small, 1e-300), 1.0)
    out = values.copy()
    out[_INNER] *= f
    out[_OUTER] *= f
    return out


# The upper lids follow the eyes' vertical turn, as a person's do: an eye turned down 0.2
# rad under a still lid showed a band of white over its iris, a stare. A lid's close value
# (IRISD units) gains LID_FOLLOWS_GAZE x the eyeball's radius x its pitch (down +), the
# lid's margin then moving with the top of the iris (lids_following_gaze); turned up, half
# as much (followed as far, the lid bared the white over the iris, a startled look).
LID_FOLLOWS_GAZE = 0.8
LID_FOLLOWS_GAZE_UP = 0.5  # of LID_FOLLOWS_GAZE
PITCH_FAPS = (25, 26)  # pitch_l_eyeball, pitch_r_eyeball (AU, down +), moving lids 19, 20


def lids_following_gaze(values: np.ndarray, follow: np.ndarray) -> np.ndarray:
    """(68,) FAP values with the upper lids' close values (19, 20) raised by `follow` (2,)
    IRISD units per AU times their eye's pitch (25, 26; turned up, LID_FOLLOWS_GAZE_UP of
    that): the lids the physics and the FaceDefTables move. `values` itself is not
    changed; follow 0 returns it."""
    if not np.any(follow):
        return values
    out = np.array(values, dtype=np.float64)
    for k, (lid, pitch) in enumerate(zip(LID_FAPS[:2], PITCH_FAPS)):
        turn = out[pitch - 1]
        out[lid - 1] += follow[k] * turn * (1.0 if turn > 0.0 else LID_FOLLOWS_GAZE_UP)
    return out


def lid_gaze_follow(face, fapu: dict[str, float]) -> np.ndarray:
    """(2,) IRISD units of upper lid close per AU of eye pitch (left, right) for `face`:
    LID_FOLLOWS_GAZE x the eyeball's radius (fae.sim.build.eyeball_sphere, the one the skin
    slides over) in IRISD units x AU; 0 for a side without an eyeball."""
    from fae.sim.build import eyeball_sphere

    out = np.zeros(2)
    for k, side in enumerate(("eye_l", "eye_r")):
        sphere = eyeball_sphere(face, side)
        if sphere is not None:
            out[k] = LID_FOLLOWS_GAZE * sphere[1] * fapu["AU"] / fapu["IRISD"]
    return out


class MappingMismatch(ValueError):
    """The head's fap_mapping does not fit its muscles and fields (recalibrate)."""


class FapControls:
    """Precomputed mapping of one head; `controls(values)` per frame."""

    def __init__(self, face, model=None):
        m = face.fap_mapping or {}
        need = ("layout", "gain_pos", "gain_neg", "table_values", "table_scale", "field_faps", "jaw_follow",
                "hold_scale", "pair_overlap")
        missing = [k for k in need if k not in m]
        if missing:
            raise MappingMismatch(f"fap_mapping: missing {', '.join(missing)} (the head is not calibrated)")
        try:  # a mapping of any shape and type (what a file held) is one to recalibrate, not a crash
            layout = np.asarray(m["layout"]).astype(int).ravel()
            nm, nf, nj, version = (int(x) for x in layout[:4])
            fields = np.asarray(m["field_faps"]).astype(int).ravel().tolist()
        except (TypeError, ValueError, OverflowError):
            raise MappingMismatch(f"fap_mapping: layout {m['layout']!r:.60} or field_faps {m['field_faps']!r:.60}: "
                                  "expected whole numbers (the head is not calibrated)") from None
        C = nm + nf + nj
        if version != FORMAT_VERSION or nj != JAW_CONTROLS or nm != len(face.muscles):
            raise MappingMismatch(f"fap_mapping: layout {layout.tolist()} does not match this head "
                                  f"({len(face.muscles)} muscles, format {FORMAT_VERSION})")
        if fields != field_faps(face):
            raise MappingMismatch(f"fap_mapping: pull fields for FAPs {fields}, this head needs {field_faps(face)}")
        if model is not None and model.muscle_count != nm + nf:
            raise MappingMismatch(f"fap_mapping: {nm + nf} muscles and fields, the simulation has {model.muscle_count}")
        try:
            self.gain_pos = np.asarray(m["gain_pos"], dtype=np.float64)
            self.gain_neg = np.asarray(m["gain_neg"], dtype=np.float64)
            self.table_values = np.asarray(m["table_values"], dtype=np.float64)
            self.table_scale = np.asarray(m["table_scale"], dtype=np.float64)
            self.jaw_follow = np.asarray(m["jaw_follow"], dtype=np.float64)
            self.hold_scale = np.clip(np.asarray(m["hold_scale"], dtype=np.float64), 0.1, 10.0)
            self.pair_overlap = np.clip(np.asarray(m["pair_overlap"], dtype=np.float64), 0.0, 1.0)
        except (TypeError, ValueError) as exc:
            raise MappingMismatch(f"fap_mapping: expected arrays of numbers ({exc})") from None
        for name, a, shape in (("gain_pos", self.gain_pos, (FAP_COUNT, C)), ("gain_neg", self.gain_neg, (FAP_COUNT, C)),
                               ("jaw_follow", self.jaw_follow, (FAP_COUNT,)),
                               ("hold_scale", self.hold_scale, (FAP_COUNT,)),
                               ("pair_overlap", self.pair_overlap, (FAP_COUNT,)),
                               ("table_values", self.table_values, (FAP_COUNT, 5)),
                               ("table_scale", self.table_scale, (FAP_COUNT, 5))):
            if a.shape != shape or not np.all(np.isfinite(a)):
                raise MappingMismatch(f"fap_mapping.{name}: expected finite {shape}, got {a.shape}")
        self.muscle_count = nm + nf
        self.model_muscles = nm
        # the lids' pull fields among the controls (ActivationLead)
        self.lid_rows = np.array([nm + fields.index(k) for k in LID_FAPS if k in fields], dtype=np.int64)
        tv, ts = self.table_values, self.table_scale
        # per-FAP slopes of the scale tables, for a vectorized interpolation
        self._x = tv
        self._slope = np.divide(np.diff(ts, axis=1), np.diff(tv, axis=1), out=np.zeros((FAP_COUNT, 4)),
                                where=np.diff(tv, axis=1) > 0)
        self._rows = np.arange(FAP_COUNT)
        self._gains = np.vstack([self.gain_pos, self.gain_neg])  # one matmul per frame

    def scale(self, values: np.ndarray) -> np.ndarray:
        """(68,) table multiplier at `values` (clamped to the table's ends)."""
        v = np.minimum(np.maximum(values, self._x[:, 0]), self._x[:, -1])
        seg = np.minimum((v[:, None] >= self._x[:, 1:4]).sum(axis=1), 3)
        r = self._rows
        return self.table_scale[r, seg] + self._slope[r, seg] * (v - self._x[r, seg])

    def controls(self, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(activation (M,) for muscles then fields, jaw (3,) angle rad, thrust m, shift m)."""
        v = np.asarray(values, dtype=np.float64)
        u = v - self.jaw_follow * v[JAW_OPEN - 1]
        s = merge_lip_pairs(np.where(u * v > 0.0, self.scale(u), self.hold_scale) * u, self.pair_overlap)
        c = np.concatenate([np.maximum(s, 0.0), np.maximum(-s, 0.0)]) @ self._gains
        act = np.minimum(np.maximum(c[: self.muscle_count], -ACTIVATION_LIMIT), ACTIVATION_LIMIT)
        act[: self.model_muscles] = np.maximum(act[: self.model_muscles], 0.0)
        a, t, x = (float(z) for z in c[self.muscle_count:])
        jaw = np.array([min(max(a, -0.05), JAW_ANGLE_LIMIT), min(max(t, -0.02), 0.03), min(max(x, -0.03), 0.03)])
        return act, jaw
