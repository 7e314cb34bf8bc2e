"""FaceRenderer: framing, colours, motion, inputs, and the OSMesa shader-cache leak fix."""

from __future__ import annotations

import numpy as np
import pytest

from fae.render.renderer import BACKGROUND, FaceRenderer
from test_render_support import EYE_RADIUS, jaw_frames, synthetic_head

SIZE = (320, 240)
BG = np.round(np.asarray(BACKGROUND) * 255)


@pytest.fixture(scope="module")
def head():
    return synthetic_head()


@pytest.fixture(scope="module")
def renderer(head):
    with FaceRenderer(head, size=SIZE) as r:
        yield r


def foreground(image: np.ndarray) -> np.ndarray:
    return np.abs(image.astype(np.int16) - BG).max(axis=2) > 12


def box_around(renderer, point, half: int) -> tuple[slice, slice]:
    x, y = renderer.camera.project(point, renderer.size)[0]
    return slice(int(y) - half, int(y) + half + 1), slice(int(x) - half, int(x) + half + 1)


def test_front_view_frames_the_whole_head_in_the_centre(renderer):
    image = renderer.render()
    assert image.shape == (SIZE[1], SIZE[0], 3) and image.dtype == np.uint8
    mask = foreground(image)
    assert 0.15 < mask.mean() < 0.6, "the head should fill a good part of the frame"
    assert not (mask[0].any() or mask[-1].any() or mask[:, 0].any() or mask[:, -1].any()), "head is cut off"
    ys, xs = np.nonzero(mask)
    assert abs(xs.mean() - SIZE[0] / 2) < 0.04 * SIZE[0]
    assert abs(ys.mean() - SIZE[1] / 2) < 0.06 * SIZE[1]
    # Skin colour, lit: warm (red > green > blue) in the middle of the face.
    cheek = image[SIZE[1] // 2 - 5:SIZE[1] // 2 + 5, SIZE[0] // 2 - 5:SIZE[0] // 2 + 5].reshape(-1, 3).mean(axis=0)
    assert cheek[0] > cheek[1] > cheek[2] and cheek[0] > 120


@pytest.mark.parametrize("view", ["three-quarter", "profile"])
def test_other_views_keep_the_head_in_frame_and_differ_from_front(head, renderer, view):
    front = renderer.render()
    with FaceRenderer(head, size=SIZE, view=view) as r:
        image = r.render()
    mask = foreground(image)
    assert mask.mean() > 0.15
    assert not (mask[0].any() or mask[-1].any() or mask[:, 0].any() or mask[:, -1].any())
    assert np.abs(image.astype(int) - front).mean() > 1.5
    # Turned towards the face's left (+x): the face's front moves to the image's left.
    eyes = 0.5 * (head.eye_centers["eye_l"] + head.eye_centers["eye_r"])
    assert r.camera.project(eyes, SIZE)[0, 0] < SIZE[0] / 2 - 0.05 * SIZE[0]


def test_three_quarter_view_shows_the_left_pupil_where_the_camera_projects_it(head):
    with FaceRenderer(head, size=SIZE, view="three-quarter") as r:
        image = r.render().astype(int)
        pupil = image[box_around(r, head.eye_centers["eye_l"] + [0.0, 0.0, EYE_RADIUS], 1)]
    assert pupil.reshape(-1, 3).mean(axis=0).max() < 70


def test_eyes_show_a_dark_pupil_inside_a_blue_iris_on_white(head, renderer):
    image = renderer.render().astype(int)
    centre = head.eye_centers["eye_l"] + [0.0, 0.0, EYE_RADIUS]
    pupil = image[box_around(renderer, centre, 1)].reshape(-1, 3).mean(axis=0)
    assert pupil.max() < 60, f"pupil should be near black, got {pupil}"
    ring = head.eye_centers["eye_l"] + EYE_RADIUS * np.array([np.sin(np.radians(27)), 0.0, np.cos(np.radians(27))])
    iris = image[box_around(renderer, ring, 0)].reshape(-1, 3).mean(axis=0)
    assert iris[2] > iris[0] + 20, f"iris should be blue, got {iris}"
    white = head.eye_centers["eye_l"] + EYE_RADIUS * np.array([np.sin(np.radians(60)), 0.0, np.cos(np.radians(60))])
    sclera = image[box_around(renderer, white, 0)].reshape(-1, 3).mean(axis=0)
    assert sclera.min() > 120, f"sclera should be light, got {sclera}"


def test_opening_the_jaw_changes_the_mouth_and_nothing_above(head, renderer):
    rest, opened = (renderer.render(f.skin_vertices, f.bone_transforms) for f in jaw_frames(head, [0.0, 0.3]))
    mouth = 0.5 * (head.feature_point_positions()["2.2"] + head.feature_point_positions()["2.3"])
    region = box_around(renderer, mouth + [0.0, -0.003, 0.0], 8)
    change = np.abs(opened[region].astype(int) - rest[region]).mean()
    assert change > 25, f"mouth pixels barely changed ({change:.1f})"
    # The open mouth shows a dark cavity (and teeth): some mouth pixels get much darker.
    assert (opened[region].sum(axis=2) < 200).sum() > 10
    forehead = box_around(renderer, head.feature_point_positions()["11.4"] * [1, 0.5, 1] + [0, 0, 0.09], 10)
    assert np.array_equal(opened[forehead], rest[forehead])


def test_rest_is_restored_and_frames_are_deterministic(head, renderer):
    first = renderer.render()
    frame = next(jaw_frames(head, [0.3]))
    skin_before = frame.skin_vertices.copy()
    jaw_before = frame.bone_transforms["jaw"].copy()
    a = renderer.render(frame.skin_vertices, frame.bone_transforms)
    b = renderer.render(frame.skin_vertices, frame.bone_transforms)
    assert np.array_equal(a, b)
    assert np.array_equal(frame.skin_vertices, skin_before) and np.array_equal(frame.bone_transforms["jaw"], jaw_before)
    assert np.array_equal(renderer.render(), first)
    assert np.array_equal(renderer.render(head.skin_vertices), first)


def test_bones_under_the_skin_are_hidden_unless_asked_for(head, renderer):
    """Skin pushed inside the skull (as a strong expression can do) still shows skin, not
    bone; with show_bones the cranium is drawn and shows through."""
    sunk = head.skin_vertices * 0.6  # the forehead now lies inside the cranium sphere
    forehead = box_around(renderer, np.array([0.0, 0.035, 0.07]), 6)
    image = renderer.render(sunk)
    patch = image[forehead].reshape(-1, 3).mean(axis=0)
    assert patch[0] > patch[1] > patch[2] and patch[0] > 120, f"forehead should stay skin, got {patch}"
    with FaceRenderer(head, size=SIZE, show_bones=True) as r:
        bones = r.render(sunk)
        rest = r.render()
    bone = bones[forehead].reshape(-1, 3).mean(axis=0)
    assert np.abs(bone - patch).max() > 15, "the cranium should show through sunk skin with show_bones"
    assert np.array_equal(rest, renderer.render()), "bones inside the skin at rest change nothing"


def test_pupil_scale_widens_and_narrows_the_pupil(head, renderer):
    eye = head.eye_centers["eye_l"] + [0.0, 0.0, EYE_RADIUS]
    region = box_around(renderer, eye, 6)

    def dark_pixels(scale):
        image = renderer.render(pupil_scale={"eye_l": scale})
        return int((image[region].max(axis=2) < 50).sum()), image

    narrow, _ = dark_pixels(0.5)
    normal, plain = dark_pixels(1.0)
    wide, image = dark_pixels(1.8)
    assert narrow < normal < wide, (narrow, normal, wide)
    assert np.array_equal(plain, renderer.render()), "scale 1 is the rest pupil"
    # Only the left eye changed.
    right = box_around(renderer, head.eye_centers["eye_r"] + [0.0, 0.0, EYE_RADIUS], 6)
    assert np.array_equal(image[right], plain[right])
    # However wide, a ring of iris stays.
    def blue_pixels(image):
        rgb = image[region].astype(int)
        return int((rgb[..., 2] > rgb[..., 0] + 20).sum())

    _, huge = dark_pixels(10.0)
    assert blue_pixels(huge) > 0.15 * blue_pixels(plain), "a ring of iris should stay around the widest pupil"


@pytest.mark.parametrize("view", ["front", "profile"])
def test_drawing_only_the_inside_that_can_show_changes_no_pixel(head, view):
    """Each frame draws the skin's inside only for triangles near the camera or over a hole
    (the mouth slit here): the picture must equal drawing the whole inside."""
    frames = list(jaw_frames(head, [0.0, 0.15, 0.3]))
    with FaceRenderer(head, size=SIZE, view=view) as r:
        chosen = [r.render(f.skin_vertices, f.bone_transforms) for f in frames]
        assert 0 < len(r._inside_triangles()) < len(head.skin_faces)
        r._inside_triangles = lambda: np.asarray(head.skin_faces, dtype=np.uint32)
        everything = [r.render(f.skin_vertices, f.bone_transforms) for f in frames]
    for a, b in zip(chosen, everything):
        assert np.array_equal(a, b)
    assert np.abs(chosen[2].astype(int) - chosen[0]).mean() > 0.1, "the jaw frames differ"


def test_rgba_frames_are_the_rgb_frames_with_opaque_alpha(head, renderer):
    frame = next(jaw_frames(head, [0.2]))
    rgba = renderer.render_rgba(frame.skin_vertices, frame.bone_transforms)
    rgb = renderer.render(frame.skin_vertices, frame.bone_transforms)
    assert rgba.shape == (SIZE[1], SIZE[0], 4) and np.all(rgba[..., 3] == 255)
    assert np.array_equal(rgba[..., :3], rgb)


def test_supersampling_averages_a_k_times_larger_render(head, renderer):
    plain = renderer.render()
    with FaceRenderer(head, size=SIZE, supersample=2) as r:
        smooth = r.render()
    with FaceRenderer(head, size=(2 * SIZE[0], 2 * SIZE[1])) as r:
        big = r.render().astype(int)
    assert smooth.shape == plain.shape
    expected = big.reshape(SIZE[1], 2, SIZE[0], 2, 3).mean(axis=(1, 3))
    assert np.abs(smooth - expected).max() <= 1
    assert np.abs(smooth.astype(int) - plain).mean() < 4  # same framing
    # Edges get in-between shades: many more distinct colours than the aliased render.
    def colours(img):
        return len(np.unique(img.reshape(-1, 3), axis=0))
    assert colours(smooth) > 1.1 * colours(plain)


def test_bad_input_is_rejected_with_a_clear_error(head, renderer):
    with pytest.raises(ValueError, match="skin_vertices"):
        renderer.render(np.zeros((10, 3)))
    with pytest.raises(ValueError, match="bone_transforms"):
        renderer.render(bone_transforms={"jaw": np.eye(3)})
    with pytest.raises(ValueError, match="view"):
        FaceRenderer(head, view="top")
    with pytest.raises(ValueError, match="size"):
        FaceRenderer(head, size=(0, 10))


@pytest.mark.slow
def test_memory_stays_flat_over_1000_frames():
    """The leak pyrender has under OSMesa (~3 MB per frame) must stay fixed."""
    def rss_mb() -> float:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * 4096 / 1e6

    head = synthetic_head(subdivisions=3)
    frames = list(jaw_frames(head, 0.3 * np.abs(np.sin(np.linspace(0, 6, 50)))))
    with FaceRenderer(head, size=(96, 72)) as r:
        for f in frames:
            r.render(f.skin_vertices, f.bone_transforms)
        start = rss_mb()
        for i in range(1000):
            f = frames[i % len(frames)]
            r.render(f.skin_vertices, f.bone_transforms)
        growth = rss_mb() - start
    assert growth < 50, f"RSS grew {growth:.0f} MB over 1,000 frames"


def test_a_textured_skin_shows_its_texture_and_wraps_around_the_seam(head, renderer):
    """A texture painted red on the face's half of the map and blue on the back's shows red
    from the front and blue from behind; the back's seam (u = 0 | 1) shows no stripe of the
    face's colour; the eyes keep their own colours; an untextured head draws as before."""
    import copy

    from fae.anatomy.template import skin_uv
    from fae.render.framing import CameraView

    model = copy.deepcopy(head)
    model.skin_uv = skin_uv(model.skin_vertices)
    texture = np.zeros((64, 128, 3), np.uint8)
    texture[:, :] = (40, 60, 220)  # back: blue
    texture[:, 32:96] = (230, 40, 30)  # u in [0.25, 0.75]: the face, red
    model.skin_texture = texture
    with FaceRenderer(model, (160, 120)) as front:
        seen = front.render()
        camera = front.camera
    fg = foreground(seen)
    red = fg & (seen[:, :, 0] > 2 * seen[:, :, 2].astype(int))
    assert red.sum() > 0.5 * fg.sum()
    back_pose = camera.pose.copy()
    back_pose[:3, :3] = camera.pose[:3, :3] @ np.diag([-1.0, 1.0, -1.0])
    back_pose[:3, 3] = 2 * camera.target - camera.pose[:3, 3]
    behind = CameraView(back_pose, camera.yfov, camera.znear, camera.zfar, camera.target)
    with FaceRenderer(model, (160, 120), camera=behind) as back:
        seen_back = back.render()
    fg = foreground(seen_back)
    reddish = fg & (seen_back[:, :, 0] > seen_back[:, :, 2])
    # no face colour smeared across the seam (a stripe would run the head's height: 60+ pixels;
    # a pixel or two of the face's side shows at the silhouette)
    assert fg.sum() > 1000 and reddish.sum() < 0.005 * fg.sum()
    untextured = renderer.render()
    model.skin_texture = None
    with FaceRenderer(model, SIZE) as plain:
        assert np.array_equal(plain.render(), untextured)


@pytest.mark.slow
def test_the_teeth_darken_towards_the_back_of_the_arch_in_an_open_mouth():
    """The shipped head's teeth are painted darker towards the back of the arch (the
    cheeks' shade): lit like the incisors, the lower arch's sides stood at the corners of an
    open mouth as two white fangs. expressions.fap's surprise (jaw dropped) from the front:
    the lower teeth seen in the outer fifth of the mouth's width on each side are at most 0.8
    as bright as the upper teeth in its middle fifth (measured 0.72; 0.97 lit alike)."""
    import copy

    from fae.animate.player import Player, playable_head
    from fae.data import shipped_head_path
    from fae.io.facemodel_gltf import read_facemodel
    from fae.io.fap import read_fap

    face = read_facemodel(shipped_head_path())
    frame = next(f for f in Player(playable_head(face)).play(read_fap("fap_streams/expressions.fap")) if f.index == 300)
    images = []
    for left_out in ((), ("lower_teeth",), ("upper_teeth",)):
        model = copy.copy(face)
        model.parts = {k: p for k, p in face.parts.items() if k not in left_out}
        with FaceRenderer(model, size=(900, 900)) as r:
            images.append(r.render(frame.skin_vertices, frame.bone_transforms).astype(float))
            corners = r.camera.project(np.array([face.surface_point_position(face.feature_points[n], frame.skin_vertices)
                                                 for n in ("2.4", "2.5")]), r.size)
    left, right = sorted(corners[:, 0])
    width = right - left
    brightness = images[0].mean(axis=2)

    def seen(i):  # pixels where the teeth left out of image i showed
        return np.abs(images[0] - images[i]).max(axis=2) > 30

    lower_y, lower_x = np.nonzero(seen(1))
    upper_y, upper_x = np.nonzero(seen(2))
    outer = (lower_x < left + 0.2 * width) | (lower_x > right - 0.2 * width)
    middle = np.abs(upper_x - 0.5 * (left + right)) < 0.1 * width
    assert outer.sum() > 10 and middle.sum() > 50, (outer.sum(), middle.sum())
    corner, front = brightness[lower_y[outer], lower_x[outer]].mean(), brightness[upper_y[middle], upper_x[middle]].mean()
    assert corner < 0.8 * front, (corner, front)


def test_a_skin_of_loose_triangles_renders_as_the_welded_skin(head):
    """An STL scan arrives as a triangle soup: every triangle its own piece and its own hole.
    Testing each triangle against every hole's box per frame cost a second a frame at 22k
    triangles; past MAX_HOLE_BOXES holes every inside triangle is drawn instead. The picture
    is the welded skin's (normals shared through normal_groups, as `fae play` does for a
    mesh split along its seams)."""
    import dataclasses

    from fae.render.renderer import MAX_HOLE_BOXES

    F = np.asarray(head.skin_faces, dtype=np.int64)
    corner = F.ravel()
    soup = dataclasses.replace(
        head, skin_vertices=np.asarray(head.skin_vertices)[corner], skin_faces=np.arange(F.size).reshape(-1, 3),
        skin_uv=np.asarray(head.skin_uv)[corner], skin_mirror=np.arange(F.size), skin_region=np.asarray(head.skin_region)[corner],
        skin_thickness=np.asarray(head.skin_thickness)[corner])
    assert len(F) > MAX_HOLE_BOXES
    frames = list(jaw_frames(head, [0.0, 0.3]))
    with FaceRenderer(head, size=SIZE) as r:
        welded = [r.render(f.skin_vertices, f.bone_transforms) for f in frames]
    with FaceRenderer(soup, size=SIZE, normal_groups=corner) as r:
        assert r._holes is None
        loose = [r.render(f.skin_vertices[corner], f.bone_transforms) for f in frames]
    for a, b in zip(welded, loose):
        assert np.abs(a.astype(int) - b).max() <= 2
        assert np.mean(np.abs(a.astype(int) - b) > 0) < 0.001


def test_an_atlas_triangle_wider_than_half_the_texture_is_not_taken_for_the_seam():
    """A cylindrical map's seam triangle narrows when its low corners wrap (u 0.02, 0.97,
    0.98 -> 1.02, 0.97, 0.98); a large triangle of an atlas's chart (u 0.1, 0.7, 0.75) does
    not, and was drawn from u 0.7 to 1.1, across other charts."""
    from fae.mesh import wrapped_seam

    uv = np.array([[0.02, 0.5], [0.97, 0.5], [0.98, 0.6], [0.1, 0.2], [0.7, 0.2], [0.75, 0.3]], np.float32)
    F2, source, uv2 = wrapped_seam(np.array([[0, 1, 2], [3, 4, 5]]), uv)
    assert list(source) == [0] and np.ptp(uv2[F2[0], 0]) < 0.1
    assert list(F2[1]) == [3, 4, 5]
