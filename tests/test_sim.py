"""Invariants of the skin simulation (fae.sim) on a small anatomical head."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import trimesh
import warp as wp

from fae.sim.build import skin_model, skin_positions
from fae.sim.reference import ReferenceSolver
from fae.sim.sdf import sample_grid, signed_distance_grid
from fae.sim.solver import SkinSolver, substep_count
from synthetic_head import synthetic_head


@pytest.fixture(scope="module")
def face():
    return synthetic_head(personalized=False, subdivisions=4, complete=False)


@pytest.fixture(scope="module")
def model(face):
    return skin_model(face)


def _jaw_pose(angle: float, pivot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    c, s = np.cos(angle), np.sin(angle)
    R = np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    rot = np.stack([np.eye(3), R])
    tr = np.stack([np.zeros(3), pivot - R @ pivot])
    return rot, tr


def test_signed_distance_grid_of_a_sphere_is_exact_near_it_and_a_lower_bound_far_from_it():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.05)
    values, origin, spacing = signed_distance_grid(sphere.vertices, sphere.faces, cell=0.004)
    pts = np.random.default_rng(1).uniform(-0.06, 0.06, (500, 3))
    phi, grad = sample_grid(values, origin, spacing, pts)
    exact = np.linalg.norm(pts, axis=1) - 0.05
    near = np.abs(exact) < 2 * spacing  # the samples around them are within NEAR_BAND cells
    assert near.sum() > 100 and np.max(np.abs(phi[near] - exact[near])) < 0.002
    assert np.all(np.sign(phi[~near]) == np.sign(exact[~near]))
    assert np.all(np.abs(phi[~near]) <= np.abs(exact[~near]) + 0.002)  # a particle's clearance may rely on it
    far = np.linalg.norm(pts, axis=1) > 0.01
    cosine = np.sum(grad[far] * pts[far], axis=1) / (np.linalg.norm(grad[far], axis=1) * np.linalg.norm(pts[far], axis=1))
    assert np.min(cosine) > 0.95


def test_a_bone_with_a_hole_is_still_signed_inside_and_out():
    """The far samples are signed by the winding number (WINDING_ACCURACY), which a hole does
    not fool: a sphere with a cap of 2 cm cut away (a bone scan's foramen, a mesh left open)
    is still negative deep inside, also straight under the hole, and positive outside."""
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.05)
    keep = sphere.triangles_center[:, 2] < 0.045  # the cap above z = 4.5 cm goes
    values, origin, spacing = signed_distance_grid(sphere.vertices, sphere.faces[keep], cell=0.004)
    rng = np.random.default_rng(2)
    d = rng.normal(size=(400, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    inside = d * rng.uniform(0.0, 0.03, (400, 1))
    axis = np.column_stack([np.zeros(20), np.zeros(20), np.linspace(-0.03, 0.03, 20)])  # under the hole
    outside = d * rng.uniform(0.07, 0.09, (400, 1))
    assert np.all(sample_grid(values, origin, spacing, np.vstack([inside, axis]))[0] < 0.0)
    assert np.all(sample_grid(values, origin, spacing, outside)[0] > 0.0)


def test_rest_stays_at_rest(model):
    solver, state, control = SkinSolver(model), model.state(), model.control()
    for _ in range(100):
        solver.step(model, state, control, 1 / 25, state)
    drift = np.linalg.norm(skin_positions(model, state.particle_q.numpy()) - model.skin_rest, axis=1)
    assert drift.max() < 1e-5


def test_substeps_follow_the_stability_bound(model):
    assert substep_count(model, 1 / 60) <= substep_count(model, 1 / 25)
    assert model.dt_max * substep_count(model, 1 / 25) >= 1 / 25 - 1e-12
    with pytest.raises(ValueError, match="dt"):
        substep_count(model, 0.0)


def _twin_steps(model, activation, rot, tr, frames: int):
    """(Warp State, numpy q, numpy qd, the ReferenceSolver) after `frames` steps of 1/25 s
    from rest by both solvers under the same controls."""
    solver, state, control = SkinSolver(model), model.state(), model.control()
    control.set(muscle_activation=activation, bone_rotation=rot, bone_translation=tr)
    ref = ReferenceSolver(model)
    q, qd = state.particle_q.numpy().astype(np.float64), state.particle_qd.numpy().astype(np.float64)
    for _ in range(frames):
        state = solver.step(model, state, control, 1 / 25)
        q, qd = ref.step(q, qd, activation, rot, tr, 1 / 25)
    return state, q, qd, ref


def test_warp_step_matches_numpy_reference(model):
    rng = np.random.default_rng(3)
    activation = rng.uniform(0.0, 1.0, model.muscle_count)
    rot, tr = _jaw_pose(0.15, model.jaw_pivot)
    state, q, qd, _ = _twin_steps(model, activation, rot, tr, frames=3)
    moved = np.abs(q - model.particle_q.numpy()).max()
    assert moved > 1e-3  # the comparison is about real motion
    assert np.abs(state.particle_q.numpy() - q).max() < 1e-5 * max(1.0, moved / 1e-3)
    assert np.abs(state.particle_qd.numpy() - qd).max() < 1e-3


def test_skin_carried_by_a_moving_jaw_keeps_up_with_it_as_its_numpy_twin_does(model):
    """A jaw moved from rest to 0.15 rad over one 40 ms step (a Control set `moving`): the
    holds go with it over the step and the carried part of the drag resists motion
    relative to them. The Warp step equals its numpy twin; the jaw's skin covers more of
    its way than with the whole drag against its motion (nothing carried); a control set
    without motion gives both poses alike."""
    from fae.sim.model import BONE_COUNT, POSE_COUNT

    rot, tr = _jaw_pose(0.15, model.jaw_pivot)
    control = model.control()
    control.set(bone_rotation=rot, bone_translation=tr, moving=True)
    R, t = control.bone_rotation.numpy(), control.bone_translation.numpy()
    assert len(R) == POSE_COUNT and np.allclose(R[:BONE_COUNT], rot) and np.allclose(R[BONE_COUNT:], np.eye(3))
    assert np.allclose(t[BONE_COUNT:], 0.0)
    activation = np.zeros(model.muscle_count)
    moving_rot, moving_tr = R.astype(np.float64), t.astype(np.float64)
    state, q, qd, ref = _twin_steps(model, activation, moving_rot, moving_tr, frames=1)
    moved = np.abs(q - model.particle_q.numpy()).max()
    assert moved > 1e-3
    assert np.abs(state.particle_q.numpy() - q).max() < 1e-5 * max(1.0, moved / 1e-3)
    assert np.abs(state.particle_qd.numpy() - qd).max() < 1e-3
    uncarried = dataclasses.replace(model, particle_carried_drag=wp.zeros_like(model.particle_carried_drag))
    dragged, _, _, _ = _twin_steps(uncarried, activation, moving_rot, moving_tr, frames=1)
    hold = ref.holds(rot, tr)
    jaw = model.particle_jaw.numpy() > 0.9
    left = np.linalg.norm(state.particle_q.numpy() - hold, axis=1)[jaw].mean()
    left_dragged = np.linalg.norm(dragged.particle_q.numpy() - hold, axis=1)[jaw].mean()
    assert left < 0.8 * left_dragged
    control.set(bone_rotation=rot, bone_translation=tr)
    assert np.allclose(control.bone_rotation.numpy()[BONE_COUNT:], rot, atol=1e-6)


def test_a_field_with_less_drag_moves_its_skin_sooner_to_the_same_place(face):
    """A pull field that asks for less drag (the eyelids' does) lowers it on the skin it
    pulls, by its weight, and nowhere else; that skin covers more of a step in the first
    frame and settles where the skin's own drag takes it; the Warp step still equals its
    numpy twin and the substep stays within the stability bound of that skin's own drag."""
    from fae.sim.build import DEFAULTS, PullField, max_stiffness_rate
    from fae.sim.solver import stable_substep

    V = np.asarray(face.skin_vertices)
    centre = V[np.argmax(V[:, 2])]  # the nose's tip: in front, skin all round
    weight = np.clip(1.0 - np.linalg.norm(V - centre, axis=1) / 0.02, 0.0, 1.0)
    moved = {}
    for drag in (None, 20.0):
        m = skin_model(face, fields=[PullField("pull", np.array([0.0, 1.0, 0.0]), weight, drag=drag)])
        d = m.particle_drag.numpy()
        quick = (d < DEFAULTS["drag"]) & (m.particle_inv_mass.numpy() > 0.0)
        if quick.any():
            mass = m.particle_mass.numpy().astype(np.float64)
            rate = max_stiffness_rate(m.particle_count, m.spring_indices.numpy().reshape(-1, 2),
                                      m.spring_stiffness.numpy().astype(np.float64), mass, quick)
            anchor = float(np.min(m.particle_anchor_stiffness.numpy()[quick] / mass[quick]))
            assert m.dt_max <= stable_substep(rate, anchor, float(d[quick].min()), DEFAULTS["cfl"]) * (1 + 1e-6)
        activation = np.zeros(m.muscle_count)
        activation[m.muscle_names.index("pull")] = 0.15
        rot, tr = np.tile(np.eye(3), (2, 1, 1)), np.zeros((2, 3))
        if drag is None:
            assert np.allclose(d, DEFAULTS["drag"])
        else:
            tip = m.skin_particle[np.argmax(weight)]
            assert d[tip] == pytest.approx(drag) and d.max() == pytest.approx(DEFAULTS["drag"])
            state, q, _, _ = _twin_steps(m, activation, rot, tr, frames=2)
            step = np.abs(q - m.particle_q.numpy()).max()
            assert step > 1e-3 and np.abs(state.particle_q.numpy() - q).max() < 1e-5 * step / 1e-3
        solver, state, control = SkinSolver(m), m.state(), m.control()
        control.set(muscle_activation=activation, bone_rotation=rot, bone_translation=tr)
        tip = int(np.argmax(weight))
        path = []
        for _ in range(40):
            solver.step(m, state, control, 1 / 25, state)
            path.append(skin_positions(m, state.particle_q.numpy())[tip, 1] - V[tip, 1])
        moved[drag] = np.array(path)
    assert moved[None][-1] > 1e-3 and moved[20.0][-1] == pytest.approx(moved[None][-1], rel=0.02)
    assert moved[20.0][0] / moved[20.0][-1] > 1.3 * moved[None][0] / moved[None][-1]


def test_left_muscle_moves_the_left_side_only(face, model):
    m = model.muscle_names.index("zygomatic_major_l")
    activation = np.zeros(model.muscle_count)
    activation[m] = 1.0
    solver, state, control = SkinSolver(model), model.state(), model.control()
    control.set(muscle_activation=activation)
    for _ in range(25):
        solver.step(model, state, control, 1 / 25, state)
    d = np.linalg.norm(skin_positions(model, state.particle_q.numpy()) - model.skin_rest, axis=1)
    x = face.skin_vertices[:, 0]
    assert d[x > 0].max() > 0.005
    assert d[x < -0.01].max() < 0.1 * d[x > 0].max()


def test_a_part_of_the_skin_simulated_alone_settles_as_it_does_in_the_whole(face, model):
    """A muscle's footprint (and a margin) simulated alone, the rest held: a fraction of the
    particles, and the skin settles where the whole model puts it; a mask of the wrong size, or of
    skin nothing simulates, is refused."""
    from fae.mesh import adjacency
    from fae.sim.build import dilate

    m = model.muscle_names.index("zygomatic_major_l")
    activation = np.zeros(model.muscle_count)
    activation[m] = 1.0

    def settled(mdl):
        solver, state, control = SkinSolver(mdl), mdl.state(), mdl.control()
        control.set(muscle_activation=activation)
        for _ in range(40):
            solver.step(mdl, state, control, 1 / 25, state)
        return skin_positions(mdl, state.particle_q.numpy())

    whole = settled(model) - model.skin_rest
    moved = np.linalg.norm(whole, axis=1)
    A = adjacency(np.asarray(face.skin_faces), len(face.skin_vertices))
    part = skin_model(face, only=dilate(moved > 0.02 * moved.max(), A, 3), like=model)
    assert part.particle_count < 0.5 * model.particle_count
    with pytest.raises(ValueError, match="only: expected shape"):
        skin_model(face, only=moved[:10] > 0, like=model)
    # and one of skin the simulation does not move (held by a bone: the scalp)
    with pytest.raises(ValueError, match="none of these skin vertices is simulated"):
        skin_model(face, only=model.skin_particle < 0, like=model)
    alone = settled(part) - model.skin_rest
    assert np.abs(alone - whole).max() < 0.01 * moved.max()  # 0.1 % here; 1.8 % without the margin
    # the skin outside the part stays where its hold puts it
    outside = part.skin_particle < 0
    assert np.abs(alone[outside]).max() < 1e-9


def test_full_activation_and_wide_jaw_stay_stable_and_outside_bones(face, model):
    rot, tr = _jaw_pose(0.35, model.jaw_pivot)
    solver, state, control = SkinSolver(model), model.state(), model.control()
    control.set(muscle_activation=np.full(model.muscle_count, 3.0), bone_rotation=rot, bone_translation=tr)
    for _ in range(50):
        solver.step(model, state, control, 1 / 25, state)
    q = state.particle_q.numpy().astype(np.float64)
    assert np.all(np.isfinite(q))
    assert np.abs(q - model.particle_q.numpy()).max() < 0.1
    col = np.flatnonzero(model.particle_collider.numpy())
    phis = []
    for b, values in enumerate(model.sdf_values):
        local = (q[col] - tr[b]) @ rot[b]
        phis.append(sample_grid(values.numpy(), model.sdf_origin[b], model.sdf_spacing[b], local)[0])
    # the mandible is projected last: nothing deeper in it than a fraction of a grid cell;
    # a particle wedged between the two bones may stay slightly inside the skull
    assert phis[1].min() > -0.5 * model.sdf_spacing[1]
    assert np.percentile(phis[0], 1) > -1e-4 and phis[0].min() > -0.003


@pytest.mark.gpu
@pytest.mark.skipif(not wp.is_cuda_available(), reason="no CUDA device")
def test_cuda_matches_cpu(face):
    cpu, gpu = skin_model(face, device="cpu"), skin_model(face, device="cuda")
    activation = np.linspace(0.0, 1.0, cpu.muscle_count)
    out = []
    for m in (cpu, gpu):
        solver, state, control = SkinSolver(m), m.state(), m.control()
        control.set(muscle_activation=activation)
        for _ in range(10):
            solver.step(m, state, control, 1 / 25, state)
        out.append(state.particle_q.numpy())
    assert np.abs(out[0] - out[1]).max() < 1e-5


def test_skin_kernel_matches_the_numpy_skin_positions(model):
    """The Player's skin assembly (one kernel) equals the numpy twin: simulated vertices from
    their particles, the rest carried by their hold, all under a rigid pose."""
    from fae.sim.skin import SkinOutput

    rng = np.random.default_rng(5)
    rot, tr = _jaw_pose(0.3, model.jaw_pivot)
    state, control = model.state(), model.control()
    control.set(bone_rotation=rot, bone_translation=tr)
    q = model.particle_q.numpy() + rng.normal(0.0, 1e-3, (model.particle_count, 3)).astype(np.float32)
    state.particle_q.assign(q)
    pose = np.eye(4)
    pose[:3, :3] = _jaw_pose(0.2, np.zeros(3))[0][1]
    pose[:3, 3] = [0.01, -0.02, 0.03]
    got = SkinOutput(model).positions(state, control, pose)
    want = skin_positions(model, q.astype(np.float64), rot, tr) @ pose[:3, :3].T + pose[:3, 3]
    assert np.abs(got - want).max() < 1e-6
    # the jaw carries the unsimulated skin of its hold, and only that
    moved = np.linalg.norm(skin_positions(model, model.particle_q.numpy(), rot, tr) - model.skin_rest, axis=1)
    carried = (model.skin_particle < 0) & (model.skin_jaw > 0.0)
    assert carried.any() and np.all(moved[carried] > 0.0)
    assert np.all(moved[(model.skin_particle < 0) & (model.skin_jaw == 0.0)] == 0.0)


def test_a_fast_particle_does_not_pass_through_the_skull_and_slides_along_it(model):
    """A particle thrown at the skull at 5 m/s (a substep's path of 2-3 cm crosses the thin
    skull) stops on the bone instead of tunnelling, keeping its sideways motion."""
    solver, state, control = SkinSolver(model), model.state(), model.control()
    q0 = model.particle_q.numpy().astype(np.float64)
    col = np.flatnonzero(model.particle_collider.numpy())
    values = model.sdf_values[0].numpy()
    phi, grad = sample_grid(values, model.sdf_origin[0], model.sdf_spacing[0], q0[col])
    k = int(np.argmin(np.where(phi > 0.0, phi, np.inf)))  # the collider nearest the skull
    i, grad = int(col[k]), grad[k:k + 1]
    inward = -grad[0] / np.linalg.norm(grad[0])
    side = np.cross(inward, np.eye(3)[np.argmin(np.abs(inward))])
    side /= np.linalg.norm(side)
    qd = np.zeros_like(q0)
    qd[i] = 5.0 * inward + 0.5 * side
    state.particle_qd.assign(qd.astype(np.float32))
    solver.step(model, state, control, model.dt_max, state)  # one substep: its path is 2-3 cm
    x = state.particle_q.numpy().astype(np.float64)[i]
    phi = sample_grid(values, model.sdf_origin[0], model.sdf_spacing[0], x[None])[0][0]
    assert phi > -0.5 * model.sdf_spacing[0]
    # it is on its own side of the thin skull: the way back to its rest place crosses no bone
    way_back = q0[i] + np.linspace(0.0, 1.0, 50)[:, None] * (x - q0[i])
    assert sample_grid(values, model.sdf_origin[0], model.sdf_spacing[0], way_back)[0].min() > -0.5 * model.sdf_spacing[0]
    assert (x - q0[i]) @ side > 1e-4  # and it slid sideways along the bone


def test_a_strong_sphincter_stays_stable_at_the_largest_substep(model):
    """A sphincter at the activation limit is stiffer than every spring; the pass treats its
    stiffness implicitly, so the largest stable substep stays stable."""
    from fae.animate.controls import ACTIVATION_LIMIT

    m = model.muscle_names.index("orbicularis_oris")
    activation = np.zeros(model.muscle_count)
    activation[m] = ACTIVATION_LIMIT
    solver, state, control = SkinSolver(model), model.state(), model.control()
    control.set(muscle_activation=activation)
    for _ in range(200):
        solver.step(model, state, control, model.dt_max, state)
    q = state.particle_q.numpy()
    assert np.all(np.isfinite(q)) and np.abs(q - model.particle_q.numpy()).max() < 0.05


def test_solvers_made_at_once_share_one_packed_copy_of_the_model(model):
    """A server's faces make their solvers in several threads: one packing per model."""
    import dataclasses
    import threading

    from fae.sim.solver import packed_arrays

    fresh = dataclasses.replace(model)  # the same arrays, nothing packed yet
    assert fresh._packed is None
    start, got = threading.Barrier(8), []

    def make():
        start.wait()
        got.append(packed_arrays(fresh))

    threads = [threading.Thread(target=make) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(got) == 8 and all(g is got[0] for g in got)
    rows, springs, static = got[0]
    assert rows.numpy()[-1] == model.spring_count and static.shape == (model.particle_count,)


def _settled_skin(model, activation: float, frames: int = 40) -> np.ndarray:
    solver, state, control = SkinSolver(model), model.state(), model.control()
    control.set(muscle_activation=np.full(model.muscle_count, activation))
    for _ in range(frames):
        solver.step(model, state, control, 1 / 25, state)
    return skin_positions(model, state.particle_q.numpy())


def test_fold_guard_keeps_squeezed_skin_from_turning_over(face, model):
    """Every muscle at three times its usual activation squeezes the skin between them: without
    the guard dozens of triangles turn over; with it none do."""
    from fae.animate.skin_check import SkinCheck

    check = SkinCheck(face)
    unguarded = skin_model(face, params={"fold_passes": 0})
    assert check.frame(_settled_skin(unguarded, 3.0)).folded.sum() > 20
    assert check.frame(_settled_skin(model, 3.0)).folded.sum() == 0


def test_warp_fold_guard_matches_numpy_reference(model):
    """Where the guard acts (a squeezed face), the Warp step still equals its numpy twin (over
    a few frames: float32 and float64 drift apart later where the guard and the bones meet)."""
    activation = np.full(model.muscle_count, 3.0)
    rot, tr = _jaw_pose(0.1, model.jaw_pivot)
    state, q, qd, ref = _twin_steps(model, activation, rot, tr, frames=3)
    guarded = q.copy()
    ref.guard_folds(guarded, qd.copy(), rot, tr, ref.holds(rot, tr))
    assert np.abs(guarded - q).max() > 1e-6  # the guard is at work in this pose
    moved = np.abs(q - model.particle_q.numpy()).max()
    assert np.abs(state.particle_q.numpy() - q).max() < 1e-5 * max(1.0, moved / 1e-3)


def test_a_step_stopped_inside_the_fold_guard_leaves_the_next_step_as_a_fresh_solver_takes_it(model):
    """The guard's passes keep lists of the particles they move, consistent only from pass to
    pass: a step interrupted between a pass's moves and their application (Ctrl-C, a failed
    launch) must not leave moves behind that no later pass lists, and the next step is the one
    a new solver takes."""
    activation = np.full(model.muscle_count, 3.0)
    rot, tr = _jaw_pose(0.1, model.jaw_pivot)
    control = model.control()
    control.set(muscle_activation=activation, bone_rotation=rot, bone_translation=tr)
    solver, state = SkinSolver(model), model.state()
    for _ in range(3):
        state = solver.step(model, state, control, 1 / 25)
    first_pass = solver._guard

    def stopped(model_, first, later, apply):
        for launch in first:  # the first pass asks its moves, then the step stops
            launch.launch()
        assert solver.pass_counts.numpy()[1] > 0
        raise KeyboardInterrupt

    solver._guard = stopped
    with pytest.raises(KeyboardInterrupt):
        solver.step(model, state, control, 1 / 25, model.state())
    solver._guard = first_pass
    again = solver.step(model, state, control, 1 / 25, model.state())
    fresh = SkinSolver(model).step(model, state, control, 1 / 25, model.state())
    np.testing.assert_allclose(again.particle_q.numpy(), fresh.particle_q.numpy(), atol=1e-7)


def test_a_stretched_edge_is_pulled_back_within_the_strain_limit(face, model):
    """One epidermis particle pulled off its place by three times its longest edge stretches
    its edges to several times their rest length; a step too short to move anything leaves it to the fold guard's
    strain limit, which pulls it back (and its neighbours towards it) in the Warp step as
    in its numpy twin."""
    F = np.asarray(face.skin_faces)
    q0 = model.particle_q.numpy().astype(np.float64)
    movable = model.particle_inv_mass.numpy() > 0
    skin_particle = model.skin_particle
    # a movable epidermis particle whose neighbours are all movable too
    nb = {}
    for a, b in np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]):
        nb.setdefault(a, set()).add(b)
    v = next(v for v in range(len(skin_particle)) if skin_particle[v] >= 0 and movable[skin_particle[v]]
             and all(skin_particle[u] >= 0 and movable[skin_particle[u]] for u in nb[v]))
    i, others = skin_particle[v], [skin_particle[u] for u in nb[v]]

    def worst(q):
        return max(np.linalg.norm(q[i] - q[j]) / np.linalg.norm(q0[i] - q0[j]) for j in others)

    q = q0.copy()
    q[i] += np.array([0.0, 0.0, 3.0 * max(np.linalg.norm(q0[i] - q0[j]) for j in others)])
    assert worst(q) > 3.0
    state = model.state()
    state.particle_q.assign(q.astype(np.float32))
    control = model.control()
    SkinSolver(model).step(model, state, control, 1e-7, state)
    ref_q, _ = ReferenceSolver(model).step(q, np.zeros_like(q), np.zeros(model.muscle_count),
                                           control.bone_rotation.numpy().astype(np.float64),
                                           control.bone_translation.numpy().astype(np.float64), 1e-7)
    got = state.particle_q.numpy().astype(np.float64)
    assert np.abs(got - ref_q).max() < 1e-6
    assert worst(got) < 0.75 * worst(q)
    assert np.linalg.norm(got[others] - q0[others], axis=1).max() > 1e-5  # its neighbours come along


def test_the_lips_contact_kernel_moves_each_partner_by_its_share_as_the_numpy_twin_does():
    """Pairs that overlap (upper below lower), that rise past a most height, and that are
    clear, with upper shares 0, 0.25, 0.5 and 1 and holds turned by the jaw: the Warp kernel
    and ReferenceSolver.lip_moves give the same moves, the same number of moves per particle
    and the same count of pairs corrected; a share of 1 leaves the lower partner where it is."""
    from fae.sim import folds
    from fae.sim.folds import LipPair
    from fae.sim.reference import _accumulate

    rng = np.random.default_rng(3)
    P, K = 40, 64
    q = rng.normal(size=(P, 3)) * 0.01
    rec = np.zeros(K, dtype=LipPair.numpy_dtype())
    rec["upper"], rec["lower"] = rng.integers(0, 20, K), rng.integers(20, 40, K)
    rec["jaw"] = rng.uniform(0.0, 1.0, K)
    rec["gap"] = rng.normal(size=K) * 0.01
    rec["most"] = np.where(rng.uniform(size=K) < 0.3, rng.uniform(0.0, 0.01, K), np.inf)
    rec["upper_share"] = rng.choice([0.0, 0.25, 0.5, 1.0], K)
    a = 0.2
    rot = np.stack([np.eye(3), np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])])
    move, moves = wp.zeros(P, dtype=wp.vec3, device="cpu"), wp.zeros(P, dtype=float, device="cpu")
    count, touched = wp.zeros(2, dtype=int, device="cpu"), wp.zeros(P, dtype=int, device="cpu")
    wp.launch(folds.separate_lips, dim=K, device="cpu",
              inputs=[wp.array(q.astype(np.float32), dtype=wp.vec3, device="cpu"), wp.array(rec, dtype=LipPair, device="cpu"),
                      wp.array(rot.astype(np.float32), dtype=wp.mat33, device="cpu"), K],
              outputs=[move, moves, touched, count])
    ref = object.__new__(ReferenceSolver)
    ref.a = {"lip_pair": rec}
    idx, mv, hits = ref.lip_moves(q, rot)
    assert 10 < hits < K and count.numpy()[0] == hits
    np.testing.assert_allclose(move.numpy(), _accumulate(P, idx, mv), atol=1e-7)
    np.testing.assert_array_equal(moves.numpy(), np.bincount(idx, minlength=P))
    # each particle moved is listed once for apply_guard
    listed = touched.numpy()[:count.numpy()[1]]
    assert sorted(listed) == sorted(set(idx.tolist()))
    one = rec[:1].copy()
    one["upper"], one["lower"], one["jaw"], one["gap"], one["most"], one["upper_share"] = 0, 1, 0.0, 0.01, np.inf, 1.0
    ref.a = {"lip_pair": one}  # the upper 1 cm short of its least height: it alone moves, 1 cm up
    idx, mv, hits = ref.lip_moves(np.zeros((2, 3)), rot)
    assert hits == 1 and list(idx) == [0]
    np.testing.assert_allclose(mv[0], [0.0, 0.01, 0.0], atol=1e-12)


def test_a_lid_is_held_above_the_lower_margin_between_its_points_not_above_the_higher_one():
    """lid_pairs: a lower margin of points at x 0, 1, 2, 3 mm and heights 0, 1, 0, -1 mm; an
    upper particle at x 0.5 mm is held at least at 0.5 mm (the straight margin there), from
    either partner; one at x 2.5 at -0.5 mm; beyond the margin's ends the end's height; a
    partner not simulated (-1) leaves its pair out, not the heights; an upper particle below
    the margin at rest is held no higher than it lies."""
    from fae.sim.folds import lid_pairs

    lower_rest = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 0.0], [2.0, 0.0, 0.0], [3.0, -1.0, 0.0]]) * 1e-3
    lower = np.arange(4)
    upper_rest = np.array([[0.5, 5.0, 0.0], [2.5, 5.0, 0.0], [-1.0, 5.0, 0.0], [1.5, -2.0, 0.0]]) * 1e-3
    upper = np.arange(4, 8)
    jaw = np.zeros(8)
    rec = lid_pairs(upper, upper_rest, lower, lower_rest, jaw)
    floor = {4: 0.5e-3, 5: -0.5e-3, 6: 0.0, 7: -2e-3}
    assert set(rec["upper"]) == set(floor) and np.all(rec["upper_share"] == 1.0) and np.all(np.isinf(rec["most"]))
    for r in rec:
        assert lower_rest[r["lower"], 1] + r["gap"] == pytest.approx(floor[r["upper"]], abs=1e-9)
    lower_part = lower.copy()
    lower_part[1] = -1
    part = lid_pairs(upper, upper_rest, lower_part, lower_rest, jaw)
    assert 1 not in part["lower"] and len(part) < len(rec)
    for r in part:
        assert lower_rest[r["lower"], 1] + r["gap"] == pytest.approx(floor[r["upper"]], abs=1e-9)
    assert len(lid_pairs(upper, upper_rest, lower[:0], lower_rest[:0], jaw)) == 0


def test_each_lip_particle_is_paired_with_its_nearest_on_the_other_lip_within_reach():
    """lip_pairs: an upper lip of three particles 4 mm apart over a lower lip of three, 1.5 mm
    below: with the nearest alone each pairs with the one under it (a wall meshed this
    coarsely let a lower particle rise through the upper triangle between two pairs); with
    up to 3 neighbours within 6 mm also with the ones beside it, 4.3 mm off, but not with
    those 8.1 mm off; each pair once, the upper above at rest (gap 0)."""
    from fae.sim.folds import lip_pairs

    x = np.array([0.0, 4.0, 8.0]) * 1e-3
    q = np.vstack([np.column_stack([x, np.full(3, 1.5e-3), np.zeros(3)]), np.column_stack([x, np.zeros(3), np.zeros(3)])])
    upper, lower, jaw = np.arange(3), np.arange(3, 6), np.zeros(6)
    one = lip_pairs(q, upper, lower, jaw, 0.003)
    assert sorted(map(tuple, np.column_stack([one["upper"], one["lower"]]).tolist())) == [(0, 3), (1, 4), (2, 5)]
    more = lip_pairs(q, upper, lower, jaw, 0.006, neighbours=3)
    pairs = sorted(map(tuple, np.column_stack([more["upper"], more["lower"]]).tolist()))
    assert pairs == [(0, 3), (0, 4), (1, 3), (1, 4), (1, 5), (2, 4), (2, 5)]
    assert np.all(more["gap"] == 0.0) and np.all(more["upper_share"] == 0.5)


def test_lips_pressed_together_keep_a_clearance_but_are_never_pushed_apart_at_rest():
    """lip_pairs' clearance: an upper particle 1.5 mm over its partner at rest keeps at least
    0.3 mm over it (pairs hold points apart while the other lip's wall slopes between its
    particles: pressed level, a lower lip's particle poked 0.2 mm through the upper lip), one
    0.1 mm over it keeps that 0.1 mm (the mouth's corners, where the lips meet at rest, are
    not pushed apart), one lower at rest may stay as low."""
    from fae.sim.folds import lip_pairs

    q = np.array([[0.0, 1.5e-3, 0.0], [4e-3, 0.1e-3, 0.0], [8e-3, -0.2e-3, 0.0],
                  [0.0, 0.0, 0.0], [4e-3, 0.0, 0.0], [8e-3, 0.0, 0.0]])
    pairs = lip_pairs(q, np.arange(3), np.arange(3, 6), np.zeros(6), 0.003, clearance=3e-4)
    gap = {(int(p["upper"]), int(p["lower"])): float(p["gap"]) for p in pairs}
    assert gap == pytest.approx({(0, 3): 3e-4, (1, 4): 1e-4, (2, 5): -2e-4})
    assert np.all(lip_pairs(q, np.arange(3), np.arange(3, 6), np.zeros(6), 0.003)["gap"] <= 0.0)


def test_the_shipped_heads_lips_keep_the_clearance_and_its_lids_lining_none():
    """The built model of the shipped head: each pair of the mouth's lips (half the
    correction each, no most height) keeps min(LIP_CLEARANCE, its rest height); the upper
    lids' lining pairs (a most height) keep none (at most their rest height, as before)."""
    from fae.data import shipped_head_path
    from fae.io.facemodel_gltf import read_facemodel
    from fae.sim.build import LIP_CLEARANCE

    built = skin_model(read_facemodel(shipped_head_path()))
    pairs = built.lip_pair.numpy()
    q = built.particle_q.numpy().astype(np.float64)
    rest = q[pairs["upper"], 1] - q[pairs["lower"], 1]
    mouth = (pairs["upper_share"] == 0.5) & np.isinf(pairs["most"])
    lining = np.isfinite(pairs["most"])
    assert mouth.sum() > 200 and lining.sum() > 50
    assert np.allclose(pairs["gap"][mouth], np.minimum(LIP_CLEARANCE, rest[mouth]), atol=1e-6)
    assert np.all(pairs["gap"][mouth & (rest > 0.001)] == pytest.approx(LIP_CLEARANCE))
    assert np.allclose(pairs["gap"][lining], np.minimum(0.0, rest[lining]), atol=1e-6)


def test_a_control_set_in_parts_never_replays_an_old_motion(model):
    """Poses not given in a `set` stay where they are and do not move in the next step:
    after a moving set, activations alone (or one pose array alone) leave the start and
    end poses equal for what was not given; a flat pose array is read as the bones' poses;
    a pose array of the wrong size is named."""
    from fae.sim.model import BONE_COUNT

    rot, tr = _jaw_pose(0.3, model.jaw_pivot)
    control = model.control()
    control.set(bone_rotation=rot, bone_translation=tr, moving=True)
    control.set(muscle_activation=np.zeros(model.muscle_count))
    R, t = control.bone_rotation.numpy(), control.bone_translation.numpy()
    assert np.allclose(R[:BONE_COUNT], rot, atol=1e-6) and np.allclose(R[BONE_COUNT:], rot, atol=1e-6)
    assert np.allclose(t[BONE_COUNT:], t[:BONE_COUNT])
    control.set(bone_rotation=np.tile(np.eye(3), (2, 1, 1)), bone_translation=np.zeros((2, 3)), moving=True)
    control.set(bone_rotation=rot, moving=True)  # the rotation moves back; the translation stays at 0
    t = control.bone_translation.numpy()
    assert np.allclose(t, 0.0)
    control.set(bone_translation=tr.ravel())
    assert np.allclose(control.bone_translation.numpy()[:BONE_COUNT], tr, atol=1e-7)
    with pytest.raises(ValueError, match="bone poses: expected 6 values"):
        control.set(bone_translation=np.zeros(5))
