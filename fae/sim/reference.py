"""The solver's step in plain numpy (float64): the reference in tests, the baseline in
benchmarks. Same scheme, substeps and order of operations as :mod:`fae.sim.solver`."""

from __future__ import annotations

import numpy as np

from fae.sim.model import MUSCLE_FIELD, MUSCLE_LINEAR, MUSCLE_SPHINCTER, SkinModel
from fae.sim.collision import WRONG_SIDE_COS
from fae.sim.sdf import sample_grid
from fae.sim.solver import substep_count


def _accumulate(n: int, index: np.ndarray, f: np.ndarray) -> np.ndarray:
    return np.column_stack([np.bincount(index, weights=f[:, c], minlength=n) for c in range(3)])


class ReferenceSolver:
    """Numpy twin of :class:`fae.sim.solver.SkinSolver`; positions and velocities are (P, 3) arrays."""

    def __init__(self, model: SkinModel):
        self.model = model
        a = model.numpy_arrays()
        self.a = a
        self.i = a["spring_indices"][0::2].astype(np.int64)
        self.j = a["spring_indices"][1::2].astype(np.int64)
        self.inv_mass = a["particle_inv_mass"].astype(np.float64)

    def forces(self, q: np.ndarray, qd: np.ndarray, activation: np.ndarray, bone_rotation: np.ndarray,
               bone_translation: np.ndarray) -> np.ndarray:
        """(P, 3) N: springs + anchors + muscles at positions q, velocities qd."""
        a, P = self.a, self.model.particle_count
        d = q[self.i] - q[self.j]
        length = np.linalg.norm(d, axis=1)
        ok = length > 1e-9
        dirn = np.where(ok[:, None], d / np.where(ok, length, 1.0)[:, None], 0.0)
        c = length - a["spring_rest_length"]
        dcdt = np.sum(dirn * (qd[self.i] - qd[self.j]), axis=1)
        fs = dirn * (a["spring_stiffness"] * c + a["spring_damping"] * dcdt)[:, None]
        f = _accumulate(P, self.j, fs) - _accumulate(P, self.i, fs)
        if self.model.anchor_count:
            ap, ab = a["anchor_particle"], a["anchor_bone"]
            target = np.einsum("aij,aj->ai", bone_rotation[ab], a["anchor_rest"]) + bone_translation[ab]
            f += _accumulate(P, ap, (target - q[ap]) * a["anchor_stiffness"][:, None])
        if self.model.influence_count:
            m, p = a["influence_muscle"], a["influence_particle"]
            kind, b = a["muscle_kind"][m], a["muscle_bone"][m]
            R = bone_rotation[b]
            point = np.einsum("aij,aj->ai", R, a["muscle_point"][m]) + bone_translation[b]
            u = np.einsum("aij,aj->ai", R, a["muscle_axis_u"][m])
            v = np.einsum("aij,aj->ai", R, a["muscle_axis_v"][m])
            x = q[p]
            dvec = point - x
            dl = np.linalg.norm(dvec, axis=1)
            lin = np.where((dl > 1e-9)[:, None], dvec / np.maximum(dl, 1e-300)[:, None], 0.0)
            off = x - point
            sph = -(u * np.sum(off * u, axis=1)[:, None] + v * np.sum(off * v, axis=1)[:, None]) / a["muscle_scale"][m][:, None]
            dirs = np.where((kind == MUSCLE_LINEAR)[:, None], lin, np.where((kind == MUSCLE_SPHINCTER)[:, None], sph, u))
            assert np.all((kind >= MUSCLE_LINEAR) & (kind <= MUSCLE_FIELD))
            f += _accumulate(P, p, dirs * (activation[m] * a["influence_weight"])[:, None])
        return f

    def collide(self, q: np.ndarray, qd: np.ndarray, bone_rotation: np.ndarray, bone_translation: np.ndarray) -> None:
        """Project particles inside a bone grid onto its surface, in place."""
        for b, values in enumerate(self.a["sdf_values"]):
            col = self.a["collider_particle"].astype(np.int64)
            if values is None or len(col) == 0:
                continue
            R, t = bone_rotation[b], bone_translation[b]
            local = (q[col] - t) @ R
            phi, grad = sample_grid(values, self.model.sdf_origin[b], self.model.sdf_spacing[b], local)
            to_rest = self.a["particle_q"][col].astype(np.float64) - local
            wrong = np.sum(grad * to_rest, axis=1) < -WRONG_SIDE_COS * np.linalg.norm(grad, axis=1) * np.linalg.norm(to_rest, axis=1)
            hit = np.flatnonzero((phi < 0.0) & (phi >= -self.model.contact_depth) & ~wrong)
            if len(hit) == 0:
                continue
            loc, ph, gr = local[hit], phi[hit], grad[hit]
            moved = np.zeros(len(hit), dtype=bool)
            n_local = np.zeros((len(hit), 3))
            active = np.ones(len(hit), dtype=bool)
            for _ in range(2):
                glen = np.linalg.norm(gr, axis=1)
                active &= glen >= 1e-9
                nl = gr / np.maximum(glen, 1e-300)[:, None]
                n_local = np.where(active[:, None], nl, n_local)
                loc = np.where(active[:, None], loc - nl * ph[:, None], loc)
                moved |= active
                ph2, gr2 = sample_grid(values, self.model.sdf_origin[b], self.model.sdf_spacing[b], loc)
                ph = np.where(active, ph2, ph)
                gr = np.where(active[:, None], gr2, gr)
                active &= ph < 0.0
            hit, n_local = hit[moved], n_local[moved]
            idx = col[hit]
            q[idx] = loc[moved] @ R.T + t
            n = n_local @ R.T
            vn = np.sum(qd[idx] * n, axis=1)
            qd[idx] -= n * np.minimum(vn, 0.0)[:, None]

    def layer_order(self, q: np.ndarray, qd: np.ndarray, q_prev: np.ndarray, bone_rotation: np.ndarray) -> None:
        """Keep upper-layer particles above their vertex in the layer below (in place)."""
        a = self.a
        below = a["particle_below"].astype(np.int64)
        pa = a["particle_anchor"].astype(np.int64)
        idx = np.flatnonzero((below >= 0) & (pa >= 0))
        if len(idx) == 0:
            return
        n = np.einsum("aij,aj->ai", bone_rotation[a["anchor_bone"][pa[idx]]], a["particle_normal"][idx].astype(np.float64))
        gap = a["particle_height"][idx] - np.sum((q[idx] - q_prev[below[idx]]) * n, axis=1)
        hit = gap > 0.0
        idx, n, gap = idx[hit], n[hit], gap[hit]
        q[idx] += n * gap[:, None]
        vn = np.sum(qd[idx] * n, axis=1)
        qd[idx] -= n * np.minimum(vn, 0.0)[:, None]

    def step(self, q: np.ndarray, qd: np.ndarray, activation: np.ndarray, bone_rotation: np.ndarray,
             bone_translation: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """Advance dt seconds; returns new (q (P, 3), qd (P, 3)) metres, metres/s; inputs unchanged."""
        q = np.array(q, dtype=np.float64)
        qd = np.array(qd, dtype=np.float64)
        act = np.asarray(activation, dtype=np.float64)
        R = np.asarray(bone_rotation, dtype=np.float64)
        t = np.asarray(bone_translation, dtype=np.float64)
        n = substep_count(self.model, dt)
        h = dt / n
        w = self.inv_mass[:, None]
        fixed = self.inv_mass == 0.0
        for _ in range(n):
            f = self.forces(q, qd, act, R, t)
            qd = (qd + f * w * h) / (1.0 + h * self.model.damping)
            qd[fixed] = 0.0
            q_prev = q
            q = q + qd * h
            self.layer_order(q, qd, q_prev, R)
            self.collide(q, qd, R, t)
        return q, qd
