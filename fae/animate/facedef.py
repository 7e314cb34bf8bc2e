"""FaceDefTables applied as the standard defines: piecewise-linear displacement per FAP interval.

A table gives, for FAP-value intervals [b_j, b_j+1], a displacement per FAP unit for each
of its vertices; a value v moves a vertex by the integral of that piecewise-constant rate
from 0 to v:  sum_j (clip(v, b_j, b_j+1) - clip(0, b_j, b_j+1)) * D_j.
"""

from __future__ import annotations

import numpy as np


class FaceDefOffsets:
    """Precomputed FaceDefTables of one mesh ("skin"); `offsets(values)` per frame.

    tables  list of fae.io.facemodel.FaceDefTable; those of other parts are ignored
    vertex_count  V of the mesh
    """

    def __init__(self, tables, vertex_count: int, part: str = "skin"):
        self.vertex_count = vertex_count
        self.tables = []
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
            self.tables.append((int(t.fap), b, D, idx))

    def offsets(self, values: np.ndarray) -> np.ndarray | None:
        """(V, 3) metres of displacement for FAP `values` (68,), or None when no table applies."""
        out = None
        for fap, b, D, idx in self.tables:
            v = float(values[fap - 1])
            if v == 0.0:
                continue
            w = np.clip(v, b[:-1], b[1:]) - np.clip(0.0, b[:-1], b[1:])
            if out is None:
                out = np.zeros((self.vertex_count, 3))
            out[idx] += np.tensordot(w, D, axes=1)  # a table lists each vertex once
        return out
