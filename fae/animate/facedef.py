"""FaceDefTables applied as the standard defines: piecewise-linear displacement per FAP interval.

A table gives, for FAP-value intervals [b_j, b_j+1], a displacement per FAP unit for each
of its vertices; a value v moves a vertex by the integral of that piecewise-constant rate
from 0 to v:  sum_j (clip(v, b_j, b_j+1) - clip(0, b_j, b_j+1)) * D_j.
The integral at each border, S(b_j), is precomputed, so a frame costs one multiply-add per
vertex of each table whose FAP is not 0: S(b_j) + (v - b_j) / (b_j+1 - b_j) (S(b_j+1) - S(b_j))
for the interval j holding v, in one Warp kernel over the tables (numpy's fancy indexing
per table cost 4x as much on the shipped head's baked tables).
"""

from __future__ import annotations

import numpy as np
import warp as wp

import fae.warp_setup  # noqa: F401  (Warp's configuration before any kernel is built)

wp.set_module_options({"enable_backward": False})


@wp.kernel
def add_table_offsets(first_entry: wp.array(dtype=int), entry_vertex: wp.array(dtype=int),
                      entry_samples: wp.array(dtype=wp.vec3d), stride: int, interval: wp.array(dtype=int),
                      fraction: wp.array(dtype=wp.float64), out: wp.array(dtype=wp.vec3d)):
    """One thread per table: out[vertex] += S_j + fraction (S_j+1 - S_j) for each of its
    entries, j = interval[table] (-1: the FAP is 0, nothing to add)."""
    t = wp.tid()
    j = interval[t]
    if j < 0:
        return
    f = fraction[t]
    for e in range(first_entry[t], first_entry[t + 1]):
        a = entry_samples[e * stride + j]
        b = entry_samples[e * stride + j + 1]
        wp.atomic_add(out, entry_vertex[e], a + (b - a) * f)


class FaceDefOffsets:
    """Precomputed FaceDefTables of one mesh ("skin"); `offsets(values)` per frame.

    tables        list of fae.io.facemodel.FaceDefTable; those of other parts are ignored
    vertex_count  V of the mesh
    """

    def __init__(self, tables, vertex_count: int, part: str = "skin"):
        self.vertex_count = vertex_count
        faps, borders, samples, vertices = [], [], [], []
        for t in tables:
            if t.part != part:
                continue
            b = np.asarray(t.borders, dtype=np.float64)
            D = np.asarray(t.displacements, dtype=np.float64)
            idx = np.asarray(t.vertices, dtype=np.int64)
            if b.ndim != 1 or len(b) < 2 or np.any(np.diff(b) <= 0) or not b[0] <= 0.0 <= b[-1]:
                raise ValueError(f"FaceDefTable of FAP {t.fap}: borders must increase and contain 0, got {b.tolist()}")
            if D.shape != (len(b) - 1, len(idx), 3):
                raise ValueError(f"FaceDefTable of FAP {t.fap}: displacements must have shape "
                                 f"({len(b) - 1}, {len(idx)}, 3), got {D.shape}")
            if len(idx) and (idx.min() < 0 or idx.max() >= vertex_count):
                raise ValueError(f"FaceDefTable of FAP {t.fap}: vertex index outside 0..{vertex_count - 1}")
            # S (m + 1, k, 3) metres: the displacement at each border (the integral from 0)
            w = np.clip(b[:, None], b[None, :-1], b[None, 1:]) - np.clip(0.0, b[:-1], b[1:])[None, :]
            faps.append(int(t.fap))
            borders.append(b)
            samples.append(np.tensordot(w, D, axes=1))
            vertices.append(idx)
        self.faps = faps  # FAP number of each table, in table order
        T = len(faps)
        width = max((len(b) for b in borders), default=2)
        # borders padded with +inf (T, width) FAPU; the interval search counts borders <= v
        self._borders = np.full((T, width), np.inf)
        self._last = np.zeros(T, dtype=np.int64)  # index of each table's last border
        for i, b in enumerate(borders):
            self._borders[i, :len(b)] = b
            self._last[i] = len(b) - 1
        self._fap_index = np.asarray(faps, dtype=np.int64) - 1
        self._rows = np.arange(T)
        # entries: one per (table, vertex); samples (entries * width, 3) metres, padded with 0
        first = np.concatenate([[0], np.cumsum([len(v) for v in vertices])]).astype(np.int32)
        entry_samples = np.zeros((int(first[-1]), width, 3))
        for i, S in enumerate(samples):
            entry_samples[first[i]:first[i + 1], :S.shape[0]] = S.transpose(1, 0, 2)
        self._width = width
        self._first = wp.array(first, dtype=int, device="cpu")
        self._vertex = wp.array(np.concatenate(vertices).astype(np.int32) if vertices else np.zeros(0, np.int32),
                                dtype=int, device="cpu")
        self._samples = wp.array(entry_samples.reshape(-1, 3), dtype=wp.vec3d, device="cpu")
        self.entry_count = int(first[-1])

    def add_offsets(self, values: np.ndarray, out: np.ndarray) -> bool:
        """Add the displacement (metres) of FAP `values` (68,) to `out` (V, 3) float64 C-contiguous,
        in place; False (and `out` untouched) when no table's FAP is non-zero."""
        if not self.faps:
            return False
        v = values[self._fap_index]
        active = v != 0.0
        if not active.any():
            return False
        B = self._borders
        v = np.minimum(np.maximum(v, B[:, 0]), B[self._rows, self._last])
        j = np.minimum((B[:, 1:] <= v[:, None]).sum(axis=1), self._last - 1)
        lo, hi = B[self._rows, j], B[self._rows, j + 1]
        interval = np.where(active, j, -1).astype(np.int32)
        fraction = (v - lo) / (hi - lo)
        wp.launch(add_table_offsets, dim=len(self.faps), device="cpu",
                  inputs=[self._first, self._vertex, self._samples, self._width,
                          wp.array(interval, dtype=int, device="cpu", copy=False),
                          wp.array(fraction, dtype=wp.float64, device="cpu", copy=False)],
                  outputs=[wp.array(out, dtype=wp.vec3d, device="cpu", copy=False)])
        return True

    def offsets(self, values: np.ndarray) -> np.ndarray | None:
        """(V, 3) metres of displacement for FAP `values` (68,), or None when no table applies."""
        out = np.zeros((self.vertex_count, 3))
        return out if self.add_offsets(values, out) else None
