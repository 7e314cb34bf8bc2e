"""The solver's step in plain numpy (float64): the reference in tests, the baseline in
benchmarks. Same scheme, substeps and order of operations as :mod:`fae.sim.solver`."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from fae.sim.model import BONE_COUNT, MUSCLE_FIELD, MUSCLE_LINEAR, MUSCLE_SPHINCTER, POSE_COUNT, SkinModel
from fae.sim.collision import ENTRY_BISECTIONS, ON_SURFACE, TRACE_STEPS, TRACE_TOLERANCE, WRONG_SIDE_COS
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
        # per particle: anchor stiffness / mass (1/s^2), the implicit part of a substep
        self.anchor_rate = a["particle_anchor_stiffness"] * self.inv_mass
        self.drag = a["particle_drag"].astype(np.float64)
        self.carried_drag = a["particle_carried_drag"].astype(np.float64)
        self.rest = a["particle_q"].astype(np.float64)
        self.jaw = a["particle_jaw"].astype(np.float64)[:, None]

    def holds(self, bone_rotation: np.ndarray, bone_translation: np.ndarray) -> np.ndarray:
        """(P, 3) metres: each particle's hold, its rest place carried by skull and jaw."""
        head = self.rest @ bone_rotation[0].T + bone_translation[0]
        jaw = self.rest @ bone_rotation[1].T + bone_translation[1]
        return head * (1.0 - self.jaw) + jaw * self.jaw

    def rest_stiffness(self) -> tuple[sp.csc_matrix, np.ndarray]:
        """The skin's linear stiffness at rest, over its free particles: (K (3F, 3F) sparse
        N/m, springs k n n^T along each spring's rest direction plus every particle's
        anchor; free (3P,) bool, the coordinates of particles with mass, in K's order).
        Calibration factors it once to get each control's linear response."""
        a, P = self.a, self.model.particle_count
        q = a["particle_q"].astype(np.float64)
        n = q[self.j] - q[self.i]
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        blocks = a["spring_stiffness"][:, None, None] * n[:, :, None] * n[:, None, :]
        # 3x3 blocks (particle row, particle column): +k n n^T on both ends' diagonals, - off them
        ap = np.arange(P)
        rows = np.concatenate([self.i, self.j, self.i, self.j, ap])
        cols = np.concatenate([self.i, self.j, self.j, self.i, ap])
        anchor = a["particle_anchor_stiffness"].astype(np.float64)[:, None, None] * np.eye(3)
        data = np.concatenate([blocks, blocks, -blocks, -blocks, anchor])
        # only the free particles' rows and columns, numbered among themselves
        moving = a["particle_inv_mass"] > 0
        keep = moving[rows] & moving[cols]
        number = np.cumsum(moving) - 1
        rows, cols, data = number[rows[keep]], number[cols[keep]], data[keep]
        r3 = np.arange(3)
        rr = np.broadcast_to(3 * rows[:, None, None] + r3[None, :, None], data.shape).reshape(-1)
        cc = np.broadcast_to(3 * cols[:, None, None] + r3[None, None, :], data.shape).reshape(-1)
        size = 3 * int(moving.sum())
        K = sp.csc_matrix((data.reshape(-1), (rr, cc)), shape=(size, size))
        return K, np.repeat(moving, 3)

    def spring_forces(self, q: np.ndarray) -> np.ndarray:
        """(P, 3) N: the springs' forces at positions q (P, 3) metres."""
        a, P = self.a, self.model.particle_count
        d = q[self.i] - q[self.j]
        length = np.maximum(np.linalg.norm(d, axis=1), 1e-9)
        fs = d * (a["spring_stiffness"] * (1.0 - a["spring_rest_length"] / length))[:, None]
        return _accumulate(P, self.j, fs) - _accumulate(P, self.i, fs)

    def forces(self, q: np.ndarray, activation: np.ndarray, bone_rotation: np.ndarray,
               bone_translation: np.ndarray) -> np.ndarray:
        """(P, 3) N: springs + anchors + muscles at positions q (P, 3) metres."""
        f = self.spring_forces(q)
        f += (self.holds(bone_rotation, bone_translation) - q) * self.a["particle_anchor_stiffness"][:, None]
        f += self.muscles(q, activation, bone_rotation, bone_translation)[0]
        return f

    def muscles(self, q: np.ndarray, activation: np.ndarray, bone_rotation: np.ndarray,
                bone_translation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(force (P, 3) N, stiffness (P,) N/m) of the muscles at positions q (fae.sim.muscles)."""
        P = self.model.particle_count
        if not self.model.influence_count:
            return np.zeros((P, 3)), np.zeros(P)
        m, p, dirs, rate = self._influences(q, bone_rotation, bone_translation)
        act = activation[m] * self.a["influence_weight"]
        return _accumulate(P, p, dirs * act[:, None]), np.bincount(p, weights=rate * np.abs(act), minlength=P)

    def muscle_force_matrix(self, q: np.ndarray, bone_rotation: np.ndarray, bone_translation: np.ndarray
                            ) -> sp.csc_matrix:
        """(3P, muscle_count) sparse N per unit activation: column m is muscle m's force
        field (P, 3) flattened, at positions q (P, 3) metres (muscles(q, e_m, ...) for every
        m at once)."""
        P, M = self.model.particle_count, self.model.muscle_count
        if not self.model.influence_count:
            return sp.csc_matrix((3 * P, M))
        m, p, dirs, _ = self._influences(q, bone_rotation, bone_translation)
        w = self.a["influence_weight"][:, None] * dirs
        rows = (3 * p[:, None] + np.arange(3)).ravel()
        return sp.coo_matrix((w.ravel(), (rows, np.repeat(m, 3))), shape=(3 * P, M)).tocsc()

    def _influences(self, q: np.ndarray, bone_rotation: np.ndarray, bone_translation: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Per muscle influence: (muscle (A,), particle (A,), pull per unit activation and
        weight (A, 3): a unit direction for linear and field muscles, the offset over the
        muscle's scale for sphincters; stiffness rate (A,) 1/m) at positions q."""
        a = self.a
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
        scale = a["muscle_scale"][m]
        sph = -(u * np.sum(off * u, axis=1)[:, None] + v * np.sum(off * v, axis=1)[:, None]) / scale[:, None]
        assert np.all((kind >= MUSCLE_LINEAR) & (kind <= MUSCLE_FIELD))
        dirs = np.where((kind == MUSCLE_LINEAR)[:, None], lin, np.where((kind == MUSCLE_SPHINCTER)[:, None], sph, u))
        rate = np.where(kind == MUSCLE_LINEAR, np.where(dl > 1e-9, 1.0 / np.maximum(dl, 1e-3), 0.0),
                        np.where(kind == MUSCLE_SPHINCTER, 1.0 / scale, 0.0))
        return m, p, dirs, rate

    def collide(self, q: np.ndarray, qd: np.ndarray, q_prev: np.ndarray, bone_rotation: np.ndarray,
                bone_translation: np.ndarray, hold: np.ndarray | None = None, only: np.ndarray | None = None) -> None:
        """Particles whose step from q_prev reached a bone go back to its surface where they
        entered; particles that were inside already are projected out (in place, as
        fae.sim.collision.bone_contact). hold (P, 3) metres: the particles' holds (None:
        computed here); only (P,) bool: the particles to look at (None: every collider)."""
        col = self.a["particle_collider"] != 0
        col = np.flatnonzero(col if only is None else col & only)
        clearance = self.a["particle_clearance"].astype(np.float64)
        for b, values in enumerate(self.a["sdf_values"]):
            if values is None or len(col) == 0:
                continue

            def sample(points):
                return sample_grid(values, self.model.sdf_origin[b], self.model.sdf_spacing[b], points)

            R, t = bone_rotation[b], bone_translation[b]
            rest = self.rest[col]
            local = (q[col] - t) @ R
            beyond = np.sum((local - rest) ** 2, axis=1) >= clearance[col, b] ** 2
            idx, local = col[beyond], local[beyond]
            phi, grad = sample(local)
            hold_local = ((self.holds(bone_rotation, bone_translation) if hold is None else hold)[idx] - t) @ R
            hold_out = sample(hold_local)[0] > 0.0
            start = (q_prev[idx] - t) @ R
            phi_s = sample(start)[0]
            n_local = np.zeros((len(idx), 3))
            new = local.copy()
            moved = np.zeros(len(idx), dtype=bool)

            # outside before the step: did its path reach the bone? (sphere tracing)
            seg = local - start
            length = np.linalg.norm(seg, axis=1)
            reach = (phi_s >= -ON_SURFACE) & ((phi < 0.0) | (length > phi + phi_s)) & (length > 1e-12)
            direction = seg / np.maximum(length, 1e-300)[:, None]
            tt, t_out, ph = np.zeros(len(idx)), np.zeros(len(idx)), phi_s.copy()
            found, active = np.zeros(len(idx), dtype=bool), reach.copy()
            entry = start.copy()
            for _ in range(TRACE_STEPS):
                hit = active & (ph <= TRACE_TOLERANCE)
                found |= hit
                entry[hit] = start[hit] + direction[hit] * tt[hit, None]
                active &= ~hit
                t_out = np.where(active, tt, t_out)
                tt = np.where(active, tt + ph, tt)
                active &= tt < length
                ph = np.where(active, sample(start + direction * tt[:, None])[0], ph)
            graze = reach & ~found & (phi < 0.0)
            lo, hi = t_out.copy(), length.copy()
            for _ in range(ENTRY_BISECTIONS):
                mid = 0.5 * (lo + hi)
                out = sample(start + direction * mid[:, None])[0] >= 0.0
                lo, hi = np.where(out, mid, lo), np.where(out, hi, mid)
            entry[graze] = start[graze] + direction[graze] * lo[graze, None]
            found |= graze
            g = sample(entry)[1]
            glen = np.linalg.norm(g, axis=1)
            ne = np.where((glen > 1e-9)[:, None], g / np.maximum(glen, 1e-300)[:, None], 0.0)
            to_hold = hold_local - entry
            far = hold_out & (np.sum(ne * to_hold, axis=1) < -WRONG_SIDE_COS * np.linalg.norm(to_hold, axis=1))
            slide = found & ~far
            slid = local + ne * np.maximum(np.sum((entry - local) * ne, axis=1), 0.0)[:, None]
            ph2, gr2 = sample(slid)
            gl2 = np.linalg.norm(gr2, axis=1)
            fix = (ph2 < 0.0) & (gl2 > 1e-9)
            slid = np.where(fix[:, None], slid - gr2 * (ph2 / np.maximum(gl2, 1e-300))[:, None], slid)
            new[slide], n_local[slide], moved[slide] = slid[slide], ne[slide], True

            # inside before the step too: shallow ones on the side they belong to are projected out
            to_hold = hold_local - local
            wrong = hold_out & (np.sum(grad * to_hold, axis=1)
                                < -WRONG_SIDE_COS * np.linalg.norm(grad, axis=1) * np.linalg.norm(to_hold, axis=1))
            active = (phi_s < -ON_SURFACE) & (phi < 0.0) & (phi >= -self.model.contact_depth) & ~wrong
            loc, ph, gr = local.copy(), phi.copy(), grad.copy()
            for _ in range(2):
                active &= ph < 0.0
                gl = np.linalg.norm(gr, axis=1)
                active &= gl >= 1e-9
                nl = gr / np.maximum(gl, 1e-300)[:, None]
                n_local = np.where(active[:, None], nl, n_local)
                loc = np.where(active[:, None], loc - nl * ph[:, None], loc)
                moved |= active
                new = np.where(active[:, None], loc, new)
                ph3, gr3 = sample(loc)
                ph = np.where(active, ph3, ph)
                gr = np.where(active[:, None], gr3, gr)

            idx, new, n_local = idx[moved], new[moved], n_local[moved]
            q[idx] = new @ R.T + t
            n = n_local @ R.T
            vn = np.sum(qd[idx] * n, axis=1)
            qd[idx] -= n * np.minimum(vn, 0.0)[:, None]
        # then the eyeballs (fae.sim.collision.sphere_contact), whatever the bones did
        sphere = self.a["particle_sphere"].astype(np.float64)
        far = self.a["particle_sphere_max"].astype(np.float64)
        eye = ((sphere[:, 3] > 0.0) | (far > 0.0)) & (self.a["particle_inv_mass"] > 0.0)
        if only is not None:
            eye &= only
        idx = np.flatnonzero(eye)
        if len(idx):
            c = sphere[idx, :3] @ bone_rotation[0].T + bone_translation[0]
            d = q[idx] - c
            r = np.linalg.norm(d, axis=1)
            ok = r >= 1e-9
            inside = ok & (r < sphere[idx, 3])
            outside = ok & ~inside & (far[idx] > 0.0) & (r > far[idx])
            for hit, to, sign in ((inside, sphere[idx, 3], 1.0), (outside, far[idx], -1.0)):
                j = idx[hit]
                n = d[hit] / r[hit, None]
                q[j] = c[hit] + n * to[hit, None]
                vn = np.sum(qd[j] * n, axis=1)
                # the velocity across the shell's wall goes (into the eye, or out of the shell)
                qd[j] -= n * (np.minimum(vn, 0.0) if sign > 0 else np.maximum(vn, 0.0))[:, None]

    def layer_order(self, q: np.ndarray, qd: np.ndarray, q_prev: np.ndarray, bone_rotation: np.ndarray) -> None:
        """Keep upper-layer particles above their vertex in the layer below (in place)."""
        a = self.a
        below = a["particle_below"].astype(np.int64)
        idx = np.flatnonzero(below >= 0)
        if len(idx) == 0:
            return
        n0 = a["particle_normal"][idx].astype(np.float64)
        n = n0 @ bone_rotation[0].T * (1.0 - self.jaw[idx]) + n0 @ bone_rotation[1].T * self.jaw[idx]
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        gap = a["particle_height"][idx] - np.sum((q[idx] - q_prev[below[idx]]) * n, axis=1)
        hit = gap > 0.0
        idx, n, gap = idx[hit], n[hit], gap[hit]
        q[idx] += n * gap[:, None]
        vn = np.sum(qd[idx] * n, axis=1)
        qd[idx] -= n * np.minimum(vn, 0.0)[:, None]

    def guard_folds(self, q: np.ndarray, qd: np.ndarray, bone_rotation: np.ndarray, bone_translation: np.ndarray,
                    hold: np.ndarray, moved: np.ndarray | None = None) -> tuple[int, np.ndarray]:
        """One pass of fae.sim.folds (in place): triangles near folding pulled back towards
        their rest shape, creases smoothed, lips kept apart, stopping at the bones; moved (P,)
        bool: look only next to these particles (None: everywhere). Returns (how many
        triangles, particles and lip pairs were guarded, (P,) bool the particles moved)."""
        tri = self.a["triangle_guard"]
        if len(tri) == 0:
            return 0, np.zeros(self.model.particle_count, dtype=bool)
        P = self.model.particle_count
        ids = np.column_stack([tri["i"], tri["j"], tri["k"]]).astype(np.int64)
        w = tri["jaw"].astype(np.float64)[:, None]
        n0 = tri["normal"].astype(np.float64)
        n = n0 @ bone_rotation[0].T * (1.0 - w) + n0 @ bone_rotation[1].T * w
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        x = q[ids]
        c = x.mean(axis=1)
        e = x[:, 1] - x[:, 0]
        a = e - n * np.sum(e * n, axis=1, keepdims=True)
        la = np.linalg.norm(a, axis=1)
        alt = np.cross(n, x[:, 2] - x[:, 0])
        a = np.where((la < 1e-12)[:, None], alt, a)
        la = np.linalg.norm(a, axis=1)
        ok = la >= 1e-12
        a = a / np.maximum(la, 1e-300)[:, None]
        b = np.cross(n, a)
        d = x - c[:, None]
        p = np.stack([np.sum(d * a[:, None], axis=2), np.sum(d * b[:, None], axis=2)], axis=2)
        r = np.stack([tri["p0"], tri["p1"], tri["p2"]], axis=1).astype(np.float64)

        def cross2(u, v):
            return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]

        ratio = np.sum(np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]) * n, axis=1) / tri["area2"]
        m = self.model.fold_min_area
        hit = ok & (ratio < m)
        if moved is not None:
            hit &= moved[ids].any(axis=1)
        beta = np.minimum(1.0, (m - ratio) / m)
        s = cross2(r, p).sum(axis=1)
        k = np.sum(r * p, axis=2).sum(axis=1)
        h = np.hypot(s, k)
        cs = np.where(h > 1e-20, k / np.maximum(h, 1e-300), 1.0)[:, None]
        sn = np.where(h > 1e-20, s / np.maximum(h, 1e-300), 0.0)[:, None]
        g = np.stack([cs * r[..., 0] - sn * r[..., 1], sn * r[..., 0] + cs * r[..., 1]], axis=2) - p
        move = (a[:, None] * g[..., :1] + b[:, None] * g[..., 1:]) * beta[:, None, None]
        idx, move = ids[hit].reshape(-1), move[hit].reshape(-1, 3)
        crease_idx, crease_move, creased = self.crease_moves(q, bone_rotation, moved)
        lip_idx, lip_move, lip_hits = self.lip_moves(q, bone_rotation)
        idx = np.concatenate([idx, crease_idx, lip_idx])
        move = np.concatenate([move, crease_move, lip_move])
        total = _accumulate(P, idx, move)
        count = np.bincount(idx, minlength=P)
        on = (count > 0) & (self.inv_mass > 0.0)
        q_prev = q.copy()
        q[on] += total[on] / count[on, None]
        # a crease move is inelastic: the velocity against it goes (as fae.sim.folds.apply_guard)
        i, c = crease_idx[:creased], crease_move[:creased]
        keep = self.inv_mass[i] > 0.0
        i, c = i[keep], c[keep]
        against = np.sum(qd[i] * c, axis=1)
        qd[i] -= c * (np.minimum(against, 0.0) / np.maximum(np.sum(c * c, axis=1), 1e-300))[:, None]
        self.collide(q, qd, q_prev, bone_rotation, bone_translation, hold, only=on)
        return int(hit.sum()) + len(crease_idx) + lip_hits, on

    def lip_moves(self, q: np.ndarray, bone_rotation: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
        """(particles (m,), moves (m, 3) metres, k): the k lip pairs that overlap, moved apart
        by their shares (as fae.sim.folds.separate_lips)."""
        lp = self.a["lip_pair"]
        if len(lp) == 0:
            return np.zeros(0, dtype=np.int64), np.zeros((0, 3)), 0
        u, low = lp["upper"].astype(np.int64), lp["lower"].astype(np.int64)
        w = lp["jaw"].astype(np.float64)[:, None]
        y = np.array([0.0, 1.0, 0.0])
        up = (bone_rotation[0] @ y)[None] * (1.0 - w) + (bone_rotation[1] @ y)[None] * w
        up /= np.linalg.norm(up, axis=1, keepdims=True)
        height = np.sum((q[u] - q[low]) * up, axis=1)
        overlap = np.maximum(lp["gap"] - height, 0.0) - np.maximum(height - lp["most"], 0.0)
        share = lp["upper_share"].astype(np.float64)
        move = up * overlap[:, None]
        up_hit, low_hit = (overlap != 0.0) & (share > 0.0), (overlap != 0.0) & (share < 1.0)
        return (np.concatenate([u[up_hit], low[low_hit]]),
                np.concatenate([move[up_hit] * share[up_hit, None], move[low_hit] * (share[low_hit, None] - 1.0)]),
                int(np.count_nonzero(overlap)))

    def crease_moves(self, q: np.ndarray, bone_rotation: np.ndarray,
                     moved: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, int]:
        """(particles (k,), moves (k, 3) metres, c): epidermis particles whose offset from
        their neighbours' mean strays from the rest offset, and the move restoring it (the
        first c), then one move per edge beyond its strain limits (as
        fae.sim.folds.smooth_creases); moved: only particles that moved or touch one."""
        cv = self.a["crease_vertex"]
        nb = self.a["crease_neighbours"].astype(np.int64)
        count = (cv["end"] - cv["first"]).astype(np.int64)
        has = np.flatnonzero(count > 0)
        if moved is not None:
            owner = np.repeat(has, count[has])
            near = moved[:len(cv)].copy()
            np.logical_or.at(near, owner, moved[nb])
            has = has[near[has]]
        if len(has) == 0:
            return np.zeros(0, dtype=np.int64), np.zeros((0, 3)), 0
        rows = np.concatenate([np.arange(cv["first"][i], cv["end"][i]) for i in has]) if len(has) else np.zeros(0, int)
        owner = np.repeat(has, count[has])
        mean = _accumulate(self.model.particle_count, owner, q[nb[rows]])[has] / count[has, None]
        delta = cv["delta"][has].astype(np.float64)
        w = cv["jaw"][has].astype(np.float64)[:, None]
        rest = delta @ bone_rotation[0].T * (1.0 - w) + delta @ bone_rotation[1].T * w
        err = q[has] - mean - rest
        excess = np.linalg.norm(err, axis=1) / (self.model.crease_tolerance * cv["edge"][has]) - 1.0
        hit = excess > 0.0
        # edges beyond their strain limits: half the excess each end
        rest_length = self.a["crease_rest_length"].astype(np.float64)[rows]
        d = q[owner] - q[nb[rows]]
        length = np.linalg.norm(d, axis=1)
        over = np.clip(length, self.model.strain_min * rest_length, self.model.strain_max * rest_length) - length
        strained = (rest_length > 0.0) & (over != 0.0) & (length > 1e-12)
        limit_move = d[strained] * (0.5 * over[strained] / length[strained])[:, None]
        return (np.concatenate([has[hit], owner[strained]]),
                np.concatenate([-err[hit] * np.minimum(1.0, excess[hit])[:, None], limit_move]), int(hit.sum()))

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
        end = self.holds(R, t)
        # the bones at the step's start (POSE_COUNT poses; BONE_COUNT alone: placed, not moving)
        begin = self.holds(R[BONE_COUNT:], t[BONE_COUNT:]) if len(R) == POSE_COUNT else end
        carried = (end - begin) / n  # h u: the hold's move in a substep
        ka = self.a["particle_anchor_stiffness"][:, None]
        for k in range(n):
            hold = begin + (end - begin) * ((k + 1) / n)
            f_muscle, k_muscle = self.muscles(q, act, R, t)
            f = self.spring_forces(q) + (hold - q) * ka + f_muscle
            implicit = 1.0 + h * self.drag + h * h * (self.anchor_rate + k_muscle * self.inv_mass)
            qd = (qd + f * w * h + carried * self.carried_drag[:, None]) / implicit[:, None]
            qd[fixed] = 0.0
            q_prev = q
            q = q + qd * h
            q[fixed] = hold[fixed]
            self.layer_order(q, qd, q_prev, R)
            self.collide(q, qd, q_prev, R, t, end)
            moved = None
            for _ in range(self.model.fold_passes):
                guarded, moved = self.guard_folds(q, qd, R, t, end, moved)
                if guarded == 0:
                    break
        return q, qd
