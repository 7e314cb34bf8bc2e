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

import copy

import numpy as np
import warp as wp

import fae.warp_setup  # noqa: F401  (Warp's configuration before any kernel is built)
from fae.sim.solver import call_first_alone

wp.set_module_options({"enable_backward": False})


@wp.kernel
def add_table_offsets(first_entry: wp.array(dtype=int), first_sample: wp.array(dtype=int),
                      entry_vertex: wp.array(dtype=int), samples: wp.array(dtype=wp.vec3d),
                      interval: wp.array(dtype=int), fraction: wp.array(dtype=wp.float64),
                      out: wp.array(dtype=wp.vec3d)):
    """One thread per table: out[vertex] += S_j + fraction (S_j+1 - S_j) for each of its
    entries, j = interval[table] (-1: the FAP is 0, nothing to add); a table's samples are
    border-major (S_j of all its entries, then S_j+1), so both rows are read in order. CPU
    only: its threads run one after another, so tables sharing a vertex need no atomics."""
    t = wp.tid()
    j = interval[t]
    if j < 0:
        return
    f = fraction[t]
    e0 = first_entry[t]
    k = first_entry[t + 1] - e0
    a0 = first_sample[t] + j * k
    for i in range(k):
        a = samples[a0 + i]
        b = samples[a0 + k + i]
        v = entry_vertex[e0 + i]
        out[v] = out[v] + a + (b - a) * f


@wp.kernel
def posed(points: wp.array(dtype=wp.vec3d), rest: wp.array(dtype=wp.vec3d), pose: wp.array(dtype=wp.mat44d),
          count: int, chunk: int):
    """points[i] = pose (rest[i] + points[i]), `chunk` points per thread."""
    start = wp.tid() * chunk
    P = pose[0]
    R = wp.mat33d(P[0, 0], P[0, 1], P[0, 2], P[1, 0], P[1, 1], P[1, 2], P[2, 0], P[2, 1], P[2, 2])
    t = wp.vec3d(P[0, 3], P[1, 3], P[2, 3])
    for i in range(start, wp.min(start + chunk, count)):
        points[i] = R * (rest[i] + points[i]) + t


_CHUNK = 256  # points per thread of `posed`


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
        # entries: one per (table, vertex); samples: each table's S (m + 1, k, 3) metres, flattened
        first = np.concatenate([[0], np.cumsum([len(v) for v in vertices])]).astype(np.int32)
        first_sample = np.concatenate([[0], np.cumsum([S.shape[0] * S.shape[1] for S in samples])]).astype(np.int32)
        self._first = wp.array(first, dtype=int, device="cpu")
        self._first_sample = wp.array(first_sample, dtype=int, device="cpu")
        self._vertex = wp.array(np.concatenate(vertices).astype(np.int32) if vertices else np.zeros(0, np.int32),
                                dtype=int, device="cpu")
        self._samples = wp.array(np.concatenate([S.reshape(-1, 3) for S in samples]) if samples else np.zeros((0, 3)),
                                 dtype=wp.vec3d, device="cpu")
        self.entry_count = int(first[-1])
        self._rest_source = None
        self._buffers()

    def _buffers(self) -> None:
        """This instance's per-frame arrays and the launches recorded with them."""
        self._rest_source = None
        T, V = len(self.faps), self.vertex_count
        self._interval = wp.zeros(T, dtype=int, device="cpu")
        self._fraction = wp.zeros(T, dtype=wp.float64, device="cpu")
        self._out = wp.zeros(V, dtype=wp.vec3d, device="cpu")
        self._rest = wp.zeros(V, dtype=wp.vec3d, device="cpu")
        self._pose = wp.zeros(1, dtype=wp.mat44d, device="cpu")
        self._add = wp.launch(add_table_offsets, dim=T, device="cpu", record_cmd=True,
                              inputs=[self._first, self._first_sample, self._vertex, self._samples, self._interval,
                                      self._fraction], outputs=[self._out]) if T else None
        self._posed = wp.launch(posed, dim=-(-V // _CHUNK), device="cpu", record_cmd=True,
                                inputs=[self._out, self._rest, self._pose, V, _CHUNK]) if V else None
        # numpy views of the same memory (CPU arrays), made once
        self._interval_np, self._fraction_np = self._interval.numpy(), self._fraction.numpy()
        self._out_np, self._rest_np, self._pose_np = self._out.numpy(), self._rest.numpy(), self._pose.numpy()
        # each kernel's first run alone, as the solver's (fae.sim.solver.call_first_alone):
        # with nothing active the tables add nothing, and the pose writes this instance's buffer
        self._interval_np[:] = -1
        for key, launch in (("add_table_offsets", self._add), ("posed", self._posed)):
            if launch is not None:
                call_first_alone(("FaceDefOffsets", key), launch.launch)

    def spawn(self) -> "FaceDefOffsets":
        """Another instance sharing the tables (static arrays) with buffers of its own: players
        stepping in different threads must not share per-frame arrays."""
        other = copy.copy(self)
        other._buffers()
        return other

    def _launch_tables(self, values: np.ndarray) -> bool:
        """Offsets of FAP `values` (68,) into self._out; False when no table's FAP is non-zero."""
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
        self._interval_np[:] = np.where(active, j, -1)
        self._fraction_np[:] = (v - lo) / (hi - lo)
        self._out_np[:] = 0.0
        self._add.launch()
        return True

    def offsets(self, values: np.ndarray) -> np.ndarray | None:
        """(V, 3) metres of displacement for FAP `values` (68,), or None when no table applies."""
        return self._out_np.copy() if self._launch_tables(values) else None

    def displaced(self, values: np.ndarray, rest: np.ndarray, pose: np.ndarray) -> np.ndarray:
        """(V, 3) float64 metres: pose (rest + offsets of FAP `values` (68,)) for `rest` (V, 3)
        metres (the same array every call: it is copied only when it changes) and the rigid
        `pose` (4, 4)."""
        if rest is not self._rest_source:
            self._rest_np[:] = rest
            self._rest_source = rest
        if not self._launch_tables(values):
            self._out_np[:] = 0.0
        self._pose_np[0] = pose
        if self._posed is not None:
            self._posed.launch()
        return self._out_np.copy()
