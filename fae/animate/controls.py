"""FAP values -> simulation controls, through a head's calibrated `fap_mapping` (one matmul).

controls(v) = sum_k max(w_k, 0) gain_pos[k] + max(-w_k, 0) gain_neg[k], w_k = s_k(u_k) u_k,
u = v - jaw_follow v_3: a lip FAP's controls also take back what open_jaw carries its point
by (fae.animate.mapping). s_k is piecewise linear over table_values[k] (see
fae.animate.calibrate) where u_k moves the point the way the FAP's own value does, 1
otherwise: the table scales of a lip raised alone, which must push the other lip too,
would lift a lip the jaw has lowered far past its place. Muscle contractions
are kept >= 0 and every control is bounded, whatever the input.
"""

from __future__ import annotations

import numpy as np

from fae.animate.mapping import FORMAT_VERSION, JAW_CONTROLS, JAW_OPEN, field_faps
from fae.mpeg4.faps import FAP_COUNT

ACTIVATION_LIMIT = 50.0
# rad: the widest opening; below the angle where the chin (2.1) is lowest (about 0.6 rad
# on the generic head with its condylar glide, fae.animate.rigid), so the chin goes down
# monotonically with open_jaw and visemes
JAW_ANGLE_LIMIT = 0.5


class MappingMismatch(ValueError):
    """The head's fap_mapping does not fit its muscles and fields (recalibrate)."""


class FapControls:
    """Precomputed mapping of one head; `controls(values)` per frame."""

    def __init__(self, face, model=None):
        m = face.fap_mapping or {}
        need = ("layout", "gain_pos", "gain_neg", "table_values", "table_scale", "field_faps", "jaw_follow")
        missing = [k for k in need if k not in m]
        if missing:
            raise MappingMismatch(f"fap_mapping: missing {', '.join(missing)} (the head is not calibrated)")
        layout = np.asarray(m["layout"]).astype(int)
        nm, nf, nj, version = (int(x) for x in layout[:4])
        C = nm + nf + nj
        if version != FORMAT_VERSION or nj != JAW_CONTROLS or nm != len(face.muscles):
            raise MappingMismatch(f"fap_mapping: layout {layout.tolist()} does not match this head "
                                  f"({len(face.muscles)} muscles, format {FORMAT_VERSION})")
        fields = np.asarray(m["field_faps"]).astype(int).tolist()
        if fields != field_faps(face):
            raise MappingMismatch(f"fap_mapping: pull fields for FAPs {fields}, this head needs {field_faps(face)}")
        if model is not None and model.muscle_count != nm + nf:
            raise MappingMismatch(f"fap_mapping: {nm + nf} muscles and fields, the simulation has {model.muscle_count}")
        self.gain_pos = np.asarray(m["gain_pos"], dtype=np.float64)
        self.gain_neg = np.asarray(m["gain_neg"], dtype=np.float64)
        self.table_values = np.asarray(m["table_values"], dtype=np.float64)
        self.table_scale = np.asarray(m["table_scale"], dtype=np.float64)
        self.jaw_follow = np.asarray(m["jaw_follow"], dtype=np.float64)
        for name, a, shape in (("gain_pos", self.gain_pos, (FAP_COUNT, C)), ("gain_neg", self.gain_neg, (FAP_COUNT, C)),
                               ("jaw_follow", self.jaw_follow, (FAP_COUNT,)),
                               ("table_values", self.table_values, (FAP_COUNT, 5)),
                               ("table_scale", self.table_scale, (FAP_COUNT, 5))):
            if a.shape != shape or not np.all(np.isfinite(a)):
                raise MappingMismatch(f"fap_mapping.{name}: expected finite {shape}, got {a.shape}")
        self.muscle_count = nm + nf
        self.model_muscles = nm
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
        s = np.where(u * v > 0.0, self.scale(u), 1.0) * u
        c = np.concatenate([np.maximum(s, 0.0), np.maximum(-s, 0.0)]) @ self._gains
        act = np.minimum(np.maximum(c[: self.muscle_count], -ACTIVATION_LIMIT), ACTIVATION_LIMIT)
        act[: self.model_muscles] = np.maximum(act[: self.model_muscles], 0.0)
        a, t, x = (float(z) for z in c[self.muscle_count:])
        jaw = np.array([min(max(a, -0.05), JAW_ANGLE_LIMIT), min(max(t, -0.02), 0.03), min(max(x, -0.03), 0.03)])
        return act, jaw
