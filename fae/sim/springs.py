"""Elastic springs between particles (in-layer edges, layer-to-layer and cross springs).

A spring of stiffness k and rest length r between particles i and j pulls i by
-k (L - r) d / L, d = x_i - x_j, L = |d|, and j by the opposite force (a scatter: each
spring adds to both ends). The springs carry no damping of their own: the solver's implicit drag damps
the skin (an explicit damper along each spring would shrink the stable substep).

The springs are evaluated in rows, one row per particle i holding its springs to
higher-numbered particles (made by fae.sim.solver from the model's spring list): i's
position is read and its force written once per row, not once per spring (the pass 10 %
faster on the CPU), and a spring's constants are one record (`Spring`: every array read in
a Warp kernel also tests for a negative index; one read instead of three, 13 % faster).
On the CPU each Warp thread evaluates the rows of `chunk` consecutive particles: a launch
copies the kernel's arguments once per thread, which costs more than a spring (measured
with one spring per thread: 3.8 ms for 163k springs, 1.5 ms in chunks of 32). On CUDA a
chunk is one row, and both ends' additions are atomic (other rows add to a row's particle).
"""

from __future__ import annotations

import warp as wp

# fast math: about 1.5x faster kernels on the CPU; the numpy reference still agrees to 1e-5.
# No adjoint code: nothing is differentiated (kernels compile in 0.6x the time).
wp.set_module_options({"fast_math": True, "enable_backward": False})


@wp.struct
class Spring:
    """One spring seen from its lower-numbered particle i (its row): the other particle j,
    rest length (m), stiffness (N/m)."""

    j: int
    rest_length: float
    stiffness: float


@wp.kernel
def eval_springs(particle_q: wp.array(dtype=wp.vec3), particle_spring_start: wp.array(dtype=int),
                 springs: wp.array(dtype=Spring), particle_count: int, chunk: int,
                 particle_f: wp.array(dtype=wp.vec3)):
    start = wp.tid() * chunk
    for i in range(start, wp.min(start + chunk, particle_count)):
        first = particle_spring_start[i]
        end = particle_spring_start[i + 1]
        if first == end:
            continue
        x = particle_q[i]
        f_i = wp.vec3(0.0, 0.0, 0.0)
        for s in range(first, end):
            spring = springs[s]
            d = x - particle_q[spring.j]
            length = wp.max(wp.length(d), 1.0e-9)
            f = d * (spring.stiffness * (1.0 - spring.rest_length / length))
            f_i = f_i - f
            # plain adds on the CPU (a launch runs its threads one after another), atomics on CUDA
            wp.atomic_add(particle_f, spring.j, f)
        wp.atomic_add(particle_f, i, f_i)
