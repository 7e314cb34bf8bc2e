"""The skin solver: explicit substeps with implicit drag, bone anchors and contact projection.

Choice of scheme. The skin is a mass-spring-damper network whose stiffness is
proportional to mass (stiffness = kappa x the lighter end's mass, kappa in 1/s^2, see
:mod:`fae.sim.build`; with the mean mass a sliver triangle's nearly massless vertex made
the shipped head need 0.17 ms substeps). Symplectic Euler is stable while dt < 2 / omega_max;
omega_max^2, the largest eigenvalue of M^-1 K in any configuration without compressed
springs, is bounded by that of the springs' weighted graph Laplacian plus the anchors,
computed once at build (Lanczos; 0.55 of the Gershgorin row-sum bound used before, which
made 7 substeps per 25 fps frame instead of 5):

    dt_max = cfl * 2 / (omega_max + spring_damping_ratio * omega_max^2),   cfl = 0.9.

A frame of length dt is split into n = ceil(dt / dt_max) equal substeps (a CFL-like
bound, so every step is stable whatever the frame rate); each substep is

    f = springs (a scatter over springs, fae.sim.springs);
    one pass over particles (fae.sim.integrate): f += bone anchor + muscles;
        v' = (v + dt f/m) / (1 + dt c);  x' = x + dt v';  upper layers kept above the next;
    then particles inside the skull or mandible grid are projected onto their surface.

The drag c (1/s) is implicit, hence unconditionally stable, and sized near critical
damping of the slowest mode (the skin moving against its bone anchors) so that the skin
settles within one or two frames. Contact is a projection (no stiff penalty springs) of
shallow penetrations only, towards the side of the bone the particle belongs to
(fae.sim.collision). Every skin particle is held to its bone: the deepest layer stiffly
(kappa_anchor 10000), the upper layers by weak tethers (kappa_tether 500), which gives the
network a single rest shape to return to (without them, skin folded by extreme poses
stayed folded). Kernels are compiled with fast math. On the shipped head (21,840
particles, 163k springs) dt_max is 8.4 ms: a 25 fps frame takes 5 substeps of 4-5 ms
on one CPU core (the spring scatter about half of it, contact about a quarter).

Schemes not taken: a per-particle gather of the springs (no atomics) measured 1.5x slower
on the CPU than the scatter, since it evaluates each spring from both ends.
"""

from __future__ import annotations

import math


import warp as wp

from fae.sim.collision import collide
from fae.sim.integrate import integrate
from fae.sim.model import Control, SkinModel, State
from fae.sim.springs import eval_spring_forces


def substep_count(model: SkinModel, dt: float) -> int:
    """Number of stable substeps for a step of dt seconds."""
    if not (dt > 0.0) or not math.isfinite(dt):
        raise ValueError(f"step: dt must be a positive number of seconds, got {dt!r}")
    return max(1, int(math.ceil(dt / model.dt_max - 1e-9)))


class SkinSolver:
    """Advances a SkinModel's State under a Control; allocates its scratch arrays once."""

    def __init__(self, model: SkinModel):
        self.model = model
        self.particle_f = wp.zeros(model.particle_count, dtype=wp.vec3, device=model.device)
        self._scratch = model.state()

    def step(self, model: SkinModel, state_in: State, control: Control, dt: float,
             state_out: State | None = None) -> State:
        """Advance dt seconds (split into stable substeps); returns state_out (new if None).

        state_in is left unchanged unless it is also state_out.
        """
        if state_out is None:
            state_out = model.state()
        n = substep_count(model, dt)
        h = dt / n
        src = state_in
        for k in range(n):
            dst = state_out if (n - k) % 2 == 1 else self._scratch
            self.particle_f.zero_()
            eval_spring_forces(model, src, self.particle_f)
            integrate(model, src, dst, control, self.particle_f, h)
            collide(model, dst, control)
            src = dst
        return state_out
