"""FaceDefTables as linear morph targets (what glTF and every viewer animates), and the
weights and bone poses of a played stream.

A table's displacement is piecewise linear in its FAP's value; a morph target is linear
in its weight. So each interval [b_j, b_j+1] of a table becomes one target, its full
extent: on the positive side (b_j >= 0) T = S(b_j+1) - S(b_j) with weight
(clip(v, b_j, b_j+1) - b_j) / (b_j+1 - b_j); on the negative side (b_j+1 <= 0)
T = S(b_j) - S(b_j+1) with weight (b_j+1 - clip(v, b_j, b_j+1)) / (b_j+1 - b_j); an
interval holding 0 inside is split there. S is the table's displacement at a border
(fae.animate.facedef). Every weight is in [0, 1], and sum_i w_i T_i is the table's
displacement at v exactly: the morph targets are the FaceDefTables, not a fit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fae.mpeg4.faptables import FAP_NAME
from fae.mpeg4.faps import FAP_COUNT


@dataclass
class MorphTarget:
    """One interval of one FaceDefTable as a morph target of a mesh.

    name          "<FAP name> <lower>..<upper>" (FAPU), unique within a mesh
    fap           FAP number
    lower, upper  the interval, FAPU units; lower >= 0 or upper <= 0
    vertices      (k,) int32 vertex indices, increasing
    displacement  (k, 3) float64 metres at weight 1
    """

    name: str
    fap: int
    lower: float
    upper: float
    vertices: np.ndarray
    displacement: np.ndarray


def morph_targets(tables, part: str = "skin") -> list[MorphTarget]:
    """The morph targets of the FaceDefTables `tables` of mesh `part`, table by table, each
    table's intervals in increasing order."""
    out = []
    for t in tables:
        if t.part != part:
            continue
        order = np.argsort(np.asarray(t.vertices), kind="stable")
        vertices = np.asarray(t.vertices, dtype=np.int32)[order]
        rates = np.asarray(t.displacements, dtype=np.float64)[:, order]  # (m, k, 3) metres per FAPU
        b = np.asarray(t.borders, dtype=np.float64)
        for j in range(len(b) - 1):
            for lo, hi in ((b[j], min(b[j + 1], 0.0)), (max(b[j], 0.0), b[j + 1])):
                if hi <= lo:
                    continue
                extent = (hi - lo) * rates[j] * (1.0 if lo >= 0.0 else -1.0)
                out.append(MorphTarget(f"{FAP_NAME[t.fap - 1]} {lo:g}..{hi:g}", int(t.fap), float(lo), float(hi),
                                       vertices, extent))
    return out


class MorphWeights:
    """Weights of `targets` (list of MorphTarget) for FAP values, vectorized; `weights(values)`."""

    def __init__(self, targets: list[MorphTarget]):
        self.fap_index = np.array([t.fap - 1 for t in targets], dtype=np.int64)
        self.lower = np.array([t.lower for t in targets], dtype=np.float64)
        self.upper = np.array([t.upper for t in targets], dtype=np.float64)
        self.positive = self.lower >= 0.0

    def weights(self, values: np.ndarray) -> np.ndarray:
        """(T,) weights in [0, 1] for FAP `values` (68,) FAPU (clamped low-level values)."""
        v = np.clip(np.asarray(values, dtype=np.float64)[self.fap_index], self.lower, self.upper)
        span = self.upper - self.lower
        return np.where(self.positive, (v - self.lower) / span, (self.upper - v) / span)


def displacement(targets: list[MorphTarget], weights: np.ndarray, vertex_count: int) -> np.ndarray:
    """(V, 3) metres: sum_i weights[i] targets[i] (what a viewer adds to the rest mesh)."""
    out = np.zeros((vertex_count, 3))
    for t, w in zip(targets, weights):
        if w != 0.0:
            out[t.vertices] += w * t.displacement
    return out


@dataclass
class Keyframes:
    """A played stream sampled once per frame.

    times            (N,) seconds
    weights          (N, T) morph weights of the skin's targets
    bone_transforms  bone name -> (N, 4, 4) rest -> now in the face frame (as Player gives)
    """

    times: np.ndarray
    weights: np.ndarray
    bone_transforms: dict[str, np.ndarray]


def keyframes(player, targets: list[MorphTarget], frames, fps: float) -> Keyframes:
    """Play `frames` (DenseFrames or (68,) arrays) at `fps` on `player` (reset first) and
    sample the morph weights and bone poses of every frame."""
    mw = MorphWeights(targets)
    player.reset()
    times, weights, bones = [], [], {}
    for f in player.play(frames, fps=fps):
        times.append(len(times) / fps)  # strictly increasing, as glTF wants, from 0
        weights.append(mw.weights(f.values if f.values is not None else np.zeros(FAP_COUNT)))
        for name, T in f.bone_transforms.items():
            bones.setdefault(name, []).append(T)
    player.reset()
    return Keyframes(np.asarray(times, dtype=np.float64), np.asarray(weights).reshape(len(times), len(targets)),
                     {k: np.asarray(v) for k, v in bones.items()})


SHAPE_TOLERANCE = 1e-4  # m: the largest vertex error of a frame rebuilt from shape_targets
MAX_SHAPE_TARGETS = 64


def shape_targets(offsets: np.ndarray, tolerance: float = SHAPE_TOLERANCE,
                  max_targets: int = MAX_SHAPE_TARGETS) -> tuple[list[MorphTarget], np.ndarray, float]:
    """A played mesh's frames as a few morph targets, for a mesh without FaceDefTables (a
    target of motion transfer): offsets (N, k, 3) metres of its k vertices from their rest,
    one row per frame -> (targets, weights (N, K), error). The targets are the frames'
    principal shapes (the SVD of the (N, 3k) offsets, not centred: a frame at rest has all
    weights 0), as few as rebuild every frame within `tolerance` metres at every vertex,
    at most max_targets; error: the largest vertex error of any frame rebuilt (metres)."""
    D = np.asarray(offsets, dtype=np.float64)
    N, k = D.shape[0], D.shape[1]
    M = D.reshape(N, 3 * k)
    if N == 0 or not np.any(M):
        return [], np.zeros((N, 0)), 0.0
    U, s, Vt = np.linalg.svd(M, full_matrices=False)
    s_max = float(s[0])
    s = s[s > 1e-12 * s_max]  # shapes no frame has: dropped
    cap = min(len(s), max_targets)

    def error(K: int) -> float:
        R = M - (U[:, :K] * s[:K]) @ Vt[:K]
        return float(np.sqrt(np.max(np.sum(R.reshape(N, k, 3) ** 2, axis=2))))

    lo, hi = 1, cap  # the fewest K within tolerance, by bisection (the error falls with K)
    if error(hi) > tolerance:
        lo = hi
    while lo < hi:
        mid = (lo + hi) // 2
        if error(mid) <= tolerance:
            hi = mid
        else:
            lo = mid + 1
    K = lo
    targets = []
    for j in range(K):
        shape = Vt[j].reshape(k, 3) * s_max  # scaled so that weights stay within about [-1, 1]
        moved = np.flatnonzero(np.any(shape != 0.0, axis=1)).astype(np.int32)
        targets.append(MorphTarget(f"shape {j + 1}", 0, 0.0, 1.0, moved, shape[moved]))
    return targets, U[:, :K] * (s[:K] / s_max), error(K)
