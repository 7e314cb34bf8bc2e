"""Elastic springs between particles (in-layer edges, layer-to-layer and cross springs).

A spring of stiffness k and rest length r between particles i and j pulls i by
-k (L - r) d / L, d = x_i - x_j, L = |d|, and j by the opposite force (a scatter over
springs). The springs carry no damping of their own: the solver's implicit drag damps
the skin (an explicit damper along each spring would shrink the stable substep).

On the CPU each Warp thread evaluates `chunk` consecutive springs: a launch copies the
kernel's arguments once per thread, which cost more than the spring itself (the full
skin's 163k springs: 3.8 ms one per thread, 1.5 ms in chunks of 32). On CUDA a chunk is one
spring. A spring's constants are one record (`Spring`, made by fae.sim.solver from the
model's arrays): every array read in a Warp kernel also tests for a negative index, and
one read instead of four made the pass 13 % faster on the CPU.
"""

from __future__ import annotations

import warp as wp

# fast math: about 1.5x faster kernels on the CPU; the numpy reference still agrees to 1e-5.
# No adjoint code: nothing is differentiated (kernels compile in 0.6x the time).
wp.set_module_options({"fast_math": True, "enable_backward": False})


@wp.struct
class Spring:
    """One spring: particles i and j, rest length (m), stiffness (N/m)."""

    i: int
    j: int
    rest_length: float
    stiffness: float


@wp.kernel
def eval_springs(particle_q: wp.array(dtype=wp.vec3), springs: wp.array(dtype=Spring),
                 spring_count: int, chunk: int, particle_f: wp.array(dtype=wp.vec3)):
    start = wp.tid() * chunk
    for s in range(start, wp.min(start + chunk, spring_count)):
        spring = springs[s]
        i = spring.i
        j = spring.j
        d = particle_q[i] - particle_q[j]
        length = wp.max(wp.length(d), 1.0e-9)
        f = d * (spring.stiffness * (1.0 - spring.rest_length / length))
        # plain adds on the CPU (a launch runs its threads one after another), atomics on CUDA
        wp.atomic_sub(particle_f, i, f)
        wp.atomic_add(particle_f, j, f)
