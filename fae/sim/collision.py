"""Skull and mandible non-penetration through signed-distance grids.

Each bone's grid is sampled in the bone's rest frame (the mandible's grid therefore moves
with the jaw). Contact is a position projection, which stays stable for any contact
(penalty springs on contact blew up with explicit integration), and the particle loses its
inward normal velocity. The solver's particle pass (fae.sim.integrate) and the fold guard's
moves (fae.sim.folds) call `bone_contact` for the skull and then the mandible
(`skull_then_jaw_contact`) with the particle's positions before and after the move:

A particle that was outside (or on the surface, where contact left it) before the step and
whose path reached the bone (it ends
inside, or it is longer than its distances to the bone at both ends allow without
touching it) entered during the step: where is found by sphere tracing its path in the
grid (bisection for a grazing path), and the particle is projected onto the surface's
tangent plane there (then once along the gradient), however deep or far it got: a long
step cannot carry skin into or through a bone, and skin slides along a bone instead of
sticking where it touched it (stopped where it entered, lip skin that touched the teeth
at a slant stayed caught on them). If it entered from the bone's far side (see below),
it passes on towards its hold.

A particle that was already inside (the bone moved onto it) and is less than
`contact_depth` deep (-depth < phi < 0) is projected onto the surface along the distance
gradient (twice at most, since the grid is trilinear). Deeper, it is left to its springs:
only a bone that jumps (a jaw opened in one frame) can bury skin so deep; projecting it would push it out on the nearest side, which may be the wrong
one (skin pushed behind the mandible stayed caught there after the pose relaxed), while
its springs and bone anchors always pull it back to rest.

Nor is a particle held on the far side of a bone from its hold (the place its anchor pulls
it to, fae.sim.integrate: the surface normal more than 120 degrees from the direction to
the hold, in the bone's frame), when the hold is outside the bone: a jaw snapped open in one
step can carry chin skin through the thin mandible, extreme lip poses can tuck the upper lip
behind the teeth; held on the bone's inner face, such skin stayed trapped there, 2 cm off
rest, while its springs pulled it into the bone (after 10,000 random frames). Left to the
springs, it passes back. A hold blended between skull and jaw can lie inside a bone: then
the bone holds the skin off wherever it is.
"""

from __future__ import annotations

import warp as wp

from fae.sim.sdf import GRID_PADDING

# fast math: about 1.5x faster kernels on the CPU; the numpy reference still agrees to 1e-5.
# No adjoint code: nothing is differentiated (kernels compile in 0.6x the time).
wp.set_module_options({"fast_math": True, "enable_backward": False})

# cosine: skin whose hold lies more than 120 degrees away from the surface normal is on the
# bone's wrong side (it passed through a thin bone) and is left to its springs
WRONG_SIDE_COS = 0.5
# metres: a particle this little inside a bone is on its surface (where contact put it)
ON_SURFACE = 5.0e-4
# finding where a particle's step entered a bone: sphere-tracing steps, the distance (m) at
# which the trace has arrived, and halvings of a grazing path's rest (1/32 of it)
TRACE_STEPS = 8
TRACE_TOLERANCE = 1.0e-4
ENTRY_BISECTIONS = 5


@wp.func
def grid_sample(values: wp.array3d(dtype=float), origin: wp.vec3, spacing: float, p: wp.vec3):
    """(phi, grad) trilinear in a signed-distance grid; outside it, a lower bound of the
    distance (to the grid's box plus GRID_PADDING, fae.sim.sdf) and no gradient."""
    g = (p - origin) / spacing
    nx = values.shape[0]
    ny = values.shape[1]
    nz = values.shape[2]
    # written so that a NaN position is outside too (never an index)
    inside = g[0] >= 0.0 and g[1] >= 0.0 and g[2] >= 0.0
    inside = inside and g[0] <= float(nx - 1) - 1.0e-6 and g[1] <= float(ny - 1) - 1.0e-6
    if not (inside and g[2] <= float(nz - 1) - 1.0e-6):
        hi = origin + wp.vec3(float(nx - 1), float(ny - 1), float(nz - 1)) * spacing
        away = wp.vec3(wp.max(wp.max(origin[0] - p[0], p[0] - hi[0]), 0.0),
                       wp.max(wp.max(origin[1] - p[1], p[1] - hi[1]), 0.0),
                       wp.max(wp.max(origin[2] - p[2], p[2] - hi[2]), 0.0))
        dist = wp.length(away) + GRID_PADDING
        if not (dist >= 0.0):
            dist = 1.0  # a NaN position
        return dist, wp.vec3(0.0, 0.0, 0.0)
    i = int(wp.floor(g[0]))
    j = int(wp.floor(g[1]))
    k = int(wp.floor(g[2]))
    fx = g[0] - float(i)
    fy = g[1] - float(j)
    fz = g[2] - float(k)
    c000 = values[i, j, k]
    c100 = values[i + 1, j, k]
    c010 = values[i, j + 1, k]
    c110 = values[i + 1, j + 1, k]
    c001 = values[i, j, k + 1]
    c101 = values[i + 1, j, k + 1]
    c011 = values[i, j + 1, k + 1]
    c111 = values[i + 1, j + 1, k + 1]
    c00 = c000 * (1.0 - fx) + c100 * fx
    c10 = c010 * (1.0 - fx) + c110 * fx
    c01 = c001 * (1.0 - fx) + c101 * fx
    c11 = c011 * (1.0 - fx) + c111 * fx
    c0 = c00 * (1.0 - fy) + c10 * fy
    c1 = c01 * (1.0 - fy) + c11 * fy
    phi = c0 * (1.0 - fz) + c1 * fz
    gx = ((c100 - c000) * (1.0 - fy) + (c110 - c010) * fy) * (1.0 - fz) + ((c101 - c001) * (1.0 - fy) + (c111 - c011) * fy) * fz
    gy = (c10 - c00) * (1.0 - fz) + (c11 - c01) * fz
    gz = c1 - c0
    return phi, wp.vec3(gx, gy, gz) / spacing


@wp.func
def path_entry(start: wp.vec3, end: wp.vec3, phi_start: float, phi_end: float, sdf_values: wp.array3d(dtype=float),
               sdf_origin: wp.vec3, sdf_spacing: float):
    """(found, point): where the straight path from `start` (outside, distance phi_start) to
    `end` first reaches the bone, by sphere tracing in the distance grid (each step is the
    distance to the bone, so none can jump over it); a path that grazes the surface is
    finished by bisection. Not found: the path stays outside."""
    d = end - start
    length = wp.length(d)
    if length <= 1.0e-12:
        return 0, start
    direction = d / length
    t = float(0.0)
    t_out = float(0.0)
    phi = phi_start
    for _it in range(TRACE_STEPS):
        if phi <= TRACE_TOLERANCE:
            return 1, start + direction * t
        t_out = t
        t = t + phi
        if t >= length:
            break
        phi, grad = grid_sample(sdf_values, sdf_origin, sdf_spacing, start + direction * t)
    if phi_end >= 0.0:
        return 0, end
    lo = t_out
    hi = length
    for _it in range(ENTRY_BISECTIONS):
        mid = 0.5 * (lo + hi)
        phi_mid, grad_mid = grid_sample(sdf_values, sdf_origin, sdf_spacing, start + direction * mid)
        if phi_mid >= 0.0:
            lo = mid
        else:
            hi = mid
    return 1, start + direction * lo


@wp.func
def bone_contact(x_prev: wp.vec3, x: wp.vec3, v: wp.vec3, rest: wp.vec3, hold: wp.vec3, clearance: float,
                 sdf_values: wp.array3d(dtype=float), sdf_origin: wp.vec3, sdf_spacing: float, R: wp.mat33,
                 t: wp.vec3, contact_depth: float):
    """(x, v) of a particle that moved from x_prev to x with velocity v, after contact with one
    bone (pose R, t) whose signed-distance grid is in the bone's rest frame; `rest` is the
    particle's rest position, `clearance` how far from it it cannot reach the bone, `hold`
    where its anchor pulls it (fae.sim.integrate)."""
    Rt = wp.transpose(R)
    local = Rt * (x - t)
    away = local - rest
    if wp.dot(away, away) < clearance * clearance:
        return x, v
    phi, grad = grid_sample(sdf_values, sdf_origin, sdf_spacing, local)
    start = Rt * (x_prev - t)
    if phi >= wp.length(local - start):
        return x, v  # the whole step stayed farther from the bone than it moved
    phi_start, grad_start = grid_sample(sdf_values, sdf_origin, sdf_spacing, start)
    # the side of the bone the particle belongs to is its hold's, where that is outside
    hold_local = Rt * (hold - t)
    phi_hold, grad_hold = grid_sample(sdf_values, sdf_origin, sdf_spacing, hold_local)
    n_local = wp.vec3(0.0, 0.0, 0.0)
    if phi_start >= -ON_SURFACE:
        # outside (or on the surface) before the step: a path shorter than both distances
        # cannot reach the bone
        if phi >= 0.0 and wp.length(local - start) <= phi + phi_start:
            return x, v
        found, entry = path_entry(start, local, phi_start, phi, sdf_values, sdf_origin, sdf_spacing)
        if found == 0:
            return x, v
        phi, grad = grid_sample(sdf_values, sdf_origin, sdf_spacing, entry)
        glen = wp.length(grad)
        if glen > 1.0e-9:
            n_local = grad / glen
        # a particle on the bone's far side from its hold passes back through it
        to_hold = hold_local - entry
        if phi_hold > 0.0 and wp.dot(n_local, to_hold) < -WRONG_SIDE_COS * wp.length(to_hold):
            return x, v
        # onto the surface's tangent plane where it entered: it slides, it does not stick
        local = local + n_local * wp.max(wp.dot(entry - local, n_local), 0.0)
        phi, grad = grid_sample(sdf_values, sdf_origin, sdf_spacing, local)
        glen = wp.length(grad)
        if phi < 0.0 and glen > 1.0e-9:
            local = local - grad * (phi / glen)
    else:
        # inside at the start too: the bone came onto it (a jaw that jumped)
        if phi >= 0.0 or phi < -contact_depth:
            return x, v
        # a bone pushes skin out only towards the side the skin belongs to (its hold's)
        to_hold = hold_local - local
        if phi_hold > 0.0 and wp.dot(grad, to_hold) < -WRONG_SIDE_COS * wp.length(grad) * wp.length(to_hold):
            return x, v
        moved = int(0)
        for _it in range(2):
            if phi < 0.0:
                glen = wp.length(grad)
                if glen > 1.0e-9:
                    n_local = grad / glen
                    local = local - n_local * phi
                    moved = 1
                    phi, grad = grid_sample(sdf_values, sdf_origin, sdf_spacing, local)
                else:
                    phi = 0.0
        if moved == 0:
            return x, v
    n = R * n_local
    vn = wp.dot(v, n)
    if vn < 0.0:
        v = v - n * vn
    return R * local + t, v


@wp.func
def sphere_contact(x: wp.vec3, v: wp.vec3, sphere: wp.vec4, sphere_max: float, R: wp.mat33, t: wp.vec3):
    """(x, v) of a particle kept in a shell about an eyeball: centre sphere[0:3] in the
    skull's rest frame (pose R, t), at least sphere[3] from it and, where sphere_max > 0, at
    most sphere_max; a particle outside the shell goes back along the radius and loses its
    velocity across it (a sphere has no far side to pass back through, unlike a thin bone)."""
    c = R * wp.vec3(sphere[0], sphere[1], sphere[2]) + t
    d = x - c
    r = wp.length(d)
    if r < 1.0e-9:
        return x, v
    n = d / r
    vn = wp.dot(v, n)
    if r < sphere[3]:
        if vn < 0.0:
            v = v - n * vn
        return c + n * sphere[3], v
    if sphere_max > 0.0 and r > sphere_max:
        if vn > 0.0:
            v = v - n * vn
        return c + n * sphere_max, v
    return x, v


@wp.func
def skull_then_jaw_contact(x_prev: wp.vec3, x: wp.vec3, v: wp.vec3, rest: wp.vec3, hold: wp.vec3,
                           clearance: wp.vec2,
                           head_sdf: wp.array3d(dtype=float), head_sdf_origin: wp.vec3, head_sdf_spacing: float,
                           R0: wp.mat33, t0: wp.vec3,
                           jaw_sdf: wp.array3d(dtype=float), jaw_sdf_origin: wp.vec3, jaw_sdf_spacing: float,
                           R1: wp.mat33, t1: wp.vec3, contact_depth: float):
    """`bone_contact` with the skull, then with the mandible (the later one wins where a
    particle is wedged between them); clearance: the particle's per bone."""
    x, v = bone_contact(x_prev, x, v, rest, hold, clearance[0], head_sdf, head_sdf_origin, head_sdf_spacing, R0,
                        t0, contact_depth)
    return bone_contact(x_prev, x, v, rest, hold, clearance[1], jaw_sdf, jaw_sdf_origin, jaw_sdf_spacing, R1, t1,
                        contact_depth)
