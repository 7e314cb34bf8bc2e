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
_CHUNK = 3 * 4096  # columns (4096 vertices) of the (N, 3k) offsets handled at a time


def shape_targets(offsets: np.ndarray, tolerance: float = SHAPE_TOLERANCE,
                  max_targets: int = MAX_SHAPE_TARGETS) -> tuple[list[MorphTarget], np.ndarray, float]:
    """A played mesh's frames as a few morph targets, for a mesh without FaceDefTables (a
    target of motion transfer): offsets (N, k, 3) metres (float32 will do) of its k vertices
    from their rest, one row per frame -> (targets, weights (N, K), error). The targets are
    the frames' principal shapes (the SVD of the (N, 3k) offsets, not centred: a frame at
    rest has all weights 0), found from the N x N Gram matrix and vertex blocks at a time
    (a 1,656-frame stream on a 53k-vertex mesh: a full SVD took 12 GB); K is the fewest,
    found by bisection, whose rebuild lies within `tolerance` metres of every frame at every
    vertex (0 when the frames do), at most max_targets; error: the largest vertex error of
    any frame rebuilt (metres), which exceeds `tolerance` only when max_targets do not do."""
    D = np.asarray(offsets)
    M = D.reshape(D.shape[0], 3 * D.shape[1])
    N, width = M.shape
    if N == 0 or width == 0:
        return [], np.zeros((N, 0)), 0.0
    k = width // 3
    blocks = [slice(a, min(a + _CHUNK, width)) for a in range(0, width, _CHUNK)]
    G = np.zeros((N, N))
    for b in blocks:
        block = M[:, b].astype(np.float64)
        G += block @ block.T
    lam, U = np.linalg.eigh(G)
    order = np.argsort(lam)[::-1]
    s = np.sqrt(np.maximum(lam[order], 0.0))
    U = U[:, order]
    cap = int(min(max_targets, np.sum(s > 1e-7 * s[0]))) if N and s[0] > 0.0 else 0
    # the shapes (cap, 3k): U^T M / s, block by block
    B = np.zeros((cap, width))
    for b in blocks:
        B[:, b] = (U[:, :cap].T @ M[:, b].astype(np.float64)) / s[:cap, None]
    W = U[:, :cap] * s[:cap]  # weights of the unit shapes

    def error(K: int) -> float:
        worst = 0.0
        for b in blocks:
            R = M[:, b].astype(np.float64) - W[:, :K] @ B[:K, b]
            worst = max(worst, float(np.max(np.sum(R.reshape(N, -1, 3) ** 2, axis=2), initial=0.0)))
        return float(np.sqrt(worst))

    lo, hi = 0, cap  # bisection: the error falls (near enough) as K grows
    if error(hi) > tolerance:
        lo = hi
    while lo < hi:
        mid = (lo + hi) // 2
        if error(mid) <= tolerance:
            hi = mid
        else:
            lo = mid + 1
    K = lo
    scale = float(s[0]) if K else 1.0  # shapes scaled so that the weights stay within about [-1, 1]
    targets = []
    for j in range(K):
        shape = B[j].reshape(k, 3) * scale
        moved = np.flatnonzero(np.any(shape != 0.0, axis=1)).astype(np.int32)
        targets.append(MorphTarget(f"shape {j + 1}", 0, 0.0, 1.0, moved, shape[moved]))
    return targets, W[:, :K] / scale, error(K)
