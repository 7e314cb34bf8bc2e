"""A personalized head from one frontal photo (paper 002 §2).

    adapt_photo(template, photo, seen_on_template) -> (FaceModel, report)

A face-landmark model (MediaPipe Face Mesh, run by the caller: fae.render.landmarks) puts
its 468 points on the photo and on a front render of the template. The same points on the
two faces correspond, so:

1. Pose: a similarity maps the template's points (metres, face frame) to the photo's
   (pixels; x right, y up, z towards the viewer, the model's own depth in pixels). It gives
   the photo's camera (weak perspective: the face is far from the lens compared with its
   depth) and the head's turn; a face turned more than MAX_TURN is refused: one photo of a
   profile shows too little of the face to fit it or to colour it.
2. Targets: each template point moves to where the photo puts it across the image, and
   keeps the depth the generic head gives it (the paper's choice: a photo has no depth, and
   the model's own depth is noisy, about 10 mm RMS against the template's). Points on
   the eyes' and lips' inner contours are the template's feature points (eyelids, eye
   corners, lip corners) taken where the landmark model's nearest point lies on the photo,
   corrected by the offset between the two on the template's render (the detector's habit).
3. Shape: a biharmonic RBF through the targets deforms the whole template (fae.adapt.rbf),
   with a small ridge; the anatomy is carried over as for a scan (fae.adapt.transfer).

The head's scan_transform maps its face frame to the photo's pixels (x right, y down; z
is depth in pixels): fae.adapt.texture colours the skin from the photo through it.

A photo without a face, with a face too small to measure, turned too far, or one whose
points do not fit a face's layout raises PhotoRefused with the reason.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fae.adapt.calibration import similarity_transform
from fae.io.facemodel import FaceModel

MAX_TURN_DEG = 30.0  # head turned (yaw) or nodded (pitch) further than this is refused
MIN_EYE_DISTANCE_PX = 20.0  # pupils closer than this on the photo: too small to measure
MAX_RESIDUAL_SHARE = 0.15  # RMS of the points after the similarity, share of the eye distance
RIDGE = 1e-4  # of the RBF (metres^2 scale of the biharmonic kernel), smooths the detector's jitter
FDP_MATCH_SHARE = 0.12  # a feature point takes the landmark point within this share of the eye distance
# The feature points placed from their nearest landmark point (they lie on contours that the
# landmark rays miss on the template: the lids over the eyeball, the lip corners).
CONTOUR_FDPS = ("3.1", "3.2", "3.3", "3.4", "3.7", "3.8", "3.11", "3.12", "8.3", "8.4")
# The feature points checked on the result (each with a landmark point on the template's render).
CHECKED_FDPS = ("2.10", "3.1", "3.2", "3.3", "3.4", "3.7", "3.8", "3.11", "3.12", "4.1", "4.2", "4.3", "4.4",
                "4.5", "4.6", "8.1", "8.2", "8.3", "8.4", "9.3")
_FLIP = np.diag([1.0, -1.0, -1.0])  # image (x right, y down, z away) <-> (x right, y up, z towards)


class PhotoRefused(Exception):
    """The photo cannot give a head; the message says why and what would help."""


@dataclass
class PhotoPoints:
    """The landmark model's points on a photo: points (468, 3) pixels (x right, y down,
    z away from the viewer, in pixels of width); size (width, height)."""

    points: np.ndarray
    size: tuple[int, int]


@dataclass
class TemplatePoints:
    """The same landmark points on a front render of the template: pixels (468, 2) of
    the render, points (468, 3) metres where each lands on the skin (nan where it missed),
    fdp_pixels: FDP name -> (2,) the template's feature points in the same render."""

    pixels: np.ndarray
    points: np.ndarray
    fdp_pixels: dict[str, np.ndarray]


def pupil_distance_px(photo: PhotoPoints, eyes: tuple[np.ndarray, np.ndarray]) -> float:
    """Distance (pixels) between the centres of the two eyes' landmark contours."""
    a, b = (photo.points[list(e), :2].mean(axis=0) for e in eyes)
    return float(np.linalg.norm(a - b))


def face_to_photo(s: float, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(4, 4): face frame (metres) -> photo pixels (x right, y down, z away)."""
    M = np.eye(4)
    M[:3, :3] = _FLIP @ (s * R)
    M[:3, 3] = _FLIP @ t
    return M


def turn_degrees(R: np.ndarray) -> tuple[float, float]:
    """(yaw, pitch) in degrees of the face's forward axis (+z) under R."""
    f = R @ np.array([0.0, 0.0, 1.0])
    return float(np.degrees(np.arctan2(f[0], f[2]))), float(np.degrees(np.arctan2(f[1], f[2])))


def contour_matches(template: TemplatePoints, names, eye_distance_px: float) -> dict[str, int]:
    """FDP name -> the landmark index nearest to it on the template's render, for the
    names whose nearest landmark lies within FDP_MATCH_SHARE of the eye distance."""
    out = {}
    for name in names:
        p = template.fdp_pixels.get(name)
        if p is None:
            continue
        d = np.linalg.norm(template.pixels - p, axis=1)
        i = int(np.argmin(d))
        if d[i] <= FDP_MATCH_SHARE * eye_distance_px:
            out[name] = i
    return out


def image_similarity(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """(2, 3) the 2-D similarity x -> M[:, :2] x + M[:, 2] taking points A (k, 2) to B (k, 2)."""
    A3 = np.column_stack([A, np.zeros(len(A))])
    B3 = np.column_stack([B, np.zeros(len(B))])
    s, R, t = similarity_transform(A3, B3)
    return np.column_stack([s * R[:2, :2], t[:2]])


def detected_fdp_pixels(template: TemplatePoints, photo: PhotoPoints, matches: dict[str, int],
                        render_to_photo: np.ndarray) -> dict[str, np.ndarray]:
    """FDP name -> (2,) pixels on the photo where the landmark model puts that feature
    point: its matched landmark on the photo plus the offset between the two on the
    template's render, carried into the photo by the render-to-photo similarity (2, 3)."""
    A = render_to_photo[:, :2]
    return {n: photo.points[i, :2] + A @ (template.fdp_pixels[n] - template.pixels[i]) for n, i in matches.items()}


def adapt_photo(template: FaceModel, photo: PhotoPoints, on_template: TemplatePoints,
                skip: tuple[tuple[int, ...], ...] = (), eyes: tuple[tuple[int, ...], tuple[int, ...]] = ((), ()),
                photo_name: str = "photo") -> tuple[FaceModel, dict]:
    """See the module docstring. skip: groups of landmark indices not to pair directly
    (the eyes' and inner lips' contours, whose rays miss the template's skin); eyes: the
    landmark indices of each eye's contour (for the eye distance)."""
    from fae.adapt.multilevel import Deformation
    from fae.adapt.nonrigid import folded_triangles
    from fae.adapt.rbf import rbf_weights
    from fae.adapt.transfer import personalize

    if not eyes[0] or not eyes[1]:
        raise ValueError("adapt_photo needs the landmark indices of both eyes")
    eye_px = pupil_distance_px(photo, eyes)
    if eye_px < MIN_EYE_DISTANCE_PX:
        raise PhotoRefused(f"{photo_name}: the face is too small ({eye_px:.0f} pixels between the eyes, at least "
                           f"{MIN_EYE_DISTANCE_PX:.0f} needed); use a photo where the face is larger")
    use = np.all(np.isfinite(on_template.points), axis=1)
    for group in skip:
        use[list(group)] = False
    idx = np.flatnonzero(use)
    if len(idx) < 50:
        raise PhotoRefused(f"{photo_name}: only {len(idx)} of the landmark points could be matched on the template")
    Q = photo.points @ _FLIP  # y up, z towards the viewer
    s, R, t = similarity_transform(on_template.points[idx], Q[idx])  # x_photo = s R x + t
    # across the image only: the model's depth is its own guess
    residual = np.linalg.norm((s * on_template.points[idx] @ R.T + t - Q[idx])[:, :2], axis=1)
    rms_share = float(np.sqrt(np.mean(residual ** 2)) / eye_px)
    yaw, pitch = turn_degrees(R)
    report = {"method": "photo", "photo": photo_name, "photo_size": list(photo.size),
              "eye_distance_px": eye_px, "pixels_per_metre": float(s), "yaw_deg": yaw, "pitch_deg": pitch,
              "landmark_pairs": int(len(idx)), "similarity_residual_share_of_eye_distance": rms_share}
    if abs(yaw) > MAX_TURN_DEG or abs(pitch) > MAX_TURN_DEG:
        raise PhotoRefused(f"{photo_name}: the face is turned {abs(yaw):.0f} degrees sideways and {abs(pitch):.0f} "
                           f"up or down (at most {MAX_TURN_DEG:.0f} allowed); use a photo of the face from the front")
    if rms_share > MAX_RESIDUAL_SHARE:
        raise PhotoRefused(f"{photo_name}: the points found do not fit a face's layout ({rms_share * 100:.0f} % of "
                           f"the eye distance RMS, at most {MAX_RESIDUAL_SHARE * 100:.0f} %): is it a face, "
                           "seen from the front?")

    def target(points_face: np.ndarray, photo_xy_up: np.ndarray) -> np.ndarray:
        """Face-frame targets: photo position across the image, the template's depth."""
        q = s * points_face @ R.T + t
        q[:, :2] = photo_xy_up
        return ((q - t) @ R) / s

    src = [on_template.points[idx]]
    dst = [target(on_template.points[idx], Q[idx, :2])]
    # contour feature points, from their nearest landmark (offset by the detector's habit)
    render_to_photo = image_similarity(on_template.pixels[idx], photo.points[idx, :2])
    render_eye_px = float(np.linalg.norm(on_template.fdp_pixels["3.5"] - on_template.fdp_pixels["3.6"])) \
        if "3.5" in on_template.fdp_pixels and "3.6" in on_template.fdp_pixels else eye_px
    fdp = template.feature_point_positions()
    contour = contour_matches(on_template, [n for n in CONTOUR_FDPS if n in fdp], render_eye_px)
    found = detected_fdp_pixels(on_template, photo, contour, render_to_photo)
    if found:
        names = sorted(found)
        P = np.array([fdp[n] for n in names])
        src.append(P)
        dst.append(target(P, np.array([found[n] for n in names]) * np.array([1.0, -1.0])))
    PL, QL = np.vstack(src), np.vstack(dst)
    deformation = Deformation(rbf_weights(PL, QL - PL, "biharmonic", rho=RIDGE))
    X = deformation(template.skin_vertices)
    T = np.linalg.inv(face_to_photo(s, R, t))  # photo pixels -> face frame
    model, transfer_report = personalize(template, X, T, "pixel", "photo")
    model.meta["photo"] = {"name": str(photo_name), "size": [int(photo.size[0]), int(photo.size[1])]}
    folded = folded_triangles(template.skin_vertices, model.skin_vertices, template.skin_faces)
    report.update(transfer_report)
    report["contour_feature_points"] = sorted(found)
    report["folded_triangles"] = int(folded.sum())
    report["feature_point_error"] = feature_point_error(model, photo, on_template, render_to_photo, eye_px,
                                                        render_eye_px)
    return model, report


def feature_point_error(model: FaceModel, photo: PhotoPoints, on_template: TemplatePoints,
                        render_to_photo: np.ndarray, eye_px: float, render_eye_px: float) -> dict:
    """How far the head's feature points, seen through the photo's camera (the head's
    scan_transform), lie from where the landmark model puts them on the photo: per point
    and at most, as a share of the photo's eye distance."""
    matches = contour_matches(on_template, [n for n in CHECKED_FDPS if n in model.feature_points], render_eye_px)
    detected = detected_fdp_pixels(on_template, photo, matches, render_to_photo)
    fdp = model.feature_point_positions()
    M = model.scan_transform
    per = {}
    for n, p in detected.items():
        q = M[:3, :3] @ fdp[n] + M[:3, 3]
        per[n] = float(np.linalg.norm(q[:2] - p) / eye_px)
    return {"per_point_share_of_eye_distance": per, "max_share": max(per.values()) if per else None,
            "points": len(per)}


def head_from_photo(template: FaceModel, image: np.ndarray, photo: PhotoPoints, on_template: TemplatePoints,
                    skip=(), eyes=((), ()), outline=(), holes=(), photo_name: str = "photo"
                    ) -> tuple[FaceModel, dict]:
    """adapt_photo, then the skin's texture from the photo (fae.adapt.texture.photo_texture):
    outline, holes: landmark indices of the face's outline and of the polygons (the eyes,
    the mouth's opening) whose colours are not skin. image (h, w, 3) uint8."""
    from fae.adapt.texture import photo_texture
    from fae.adapt.transfer import visible_skin
    from fae.mesh import vertex_normals

    model, report = adapt_photo(template, photo, on_template, skip=skip, eyes=eyes, photo_name=photo_name)
    seen = visible_skin(template)
    N = vertex_normals(model.skin_vertices, model.skin_faces)
    xy = photo.points[:, :2]
    texture, texture_report = photo_texture(model.skin_vertices[seen], N[seen], model.skin_uv[seen],
                                            model.scan_transform, image, xy[list(outline)],
                                            holes=[xy[list(h)] for h in holes], hair=hair_cap(model))
    model.skin_texture = texture
    report["texture"] = texture_report
    report["iris_colour"] = iris_from_photo(model, image, photo, eyes)
    return model, report


HAIRLINE_SOFTNESS = 0.006  # metres: the hair's edge fades over this much height either side
HAIRLINE_OVER_EAR = 0.008  # metres: the hairline's height over the top of an ear
BEHIND_EAR_DEGREES = 20.0  # of azimuth behind an ear over which the hairline drops to the nape


def hair_cap(face: FaceModel):
    """Where a head's hair grows, a cap above a smooth hairline: a function of points
    (k, 3) metres in the head frame giving (k,) weights in [0, 1], or None. Around the
    head's vertical axis (through the ears' mean depth) the hairline's height follows the
    azimuth: at the front the middle hairline point (FDP 11.1), at the
    temples the side ones (11.2, 11.3), over the ears HAIRLINE_OVER_EAR above their tops,
    then down behind them to the earlobes' height (the nape) and round the back at that
    height. Each vertex's weight rises from 0 to 1 over HAIRLINE_SOFTNESS either side of
    that height (the ears lie below it). None for a head without those feature points or
    ear regions. (A function of points, not weights per vertex: the texture evaluates it
    at each texel, and a vertex's weight interpolated over a large triangle zigzags along
    the hairline.)"""
    from scipy.interpolate import PchipInterpolator

    V = np.asarray(face.skin_vertices, dtype=np.float64)
    names = list(face.region_names)
    region = np.asarray(face.skin_region)
    fdp = face.feature_point_positions()
    ear_ids = [names.index(e) for e in ("ear_l", "ear_r") if e in names]
    ears = np.isin(region, ear_ids)
    if len(ear_ids) < 2 or not all(p in fdp for p in ("11.1", "11.2", "11.3")):
        return None
    centre_z = float(np.mean([V[region == e, 2].mean() for e in ear_ids]))

    def azimuth(P):  # degrees from the front, either side
        P = np.atleast_2d(P)
        return np.degrees(np.arctan2(np.abs(P[:, 0]), P[:, 2] - centre_z))

    E = V[ears]
    ear_front, ear_back = float(azimuth(E).min()), float(azimuth(E).max())
    over_ear = E[:, 1].max() + HAIRLINE_OVER_EAR
    nape = E[:, 1].min()
    temple = float(np.mean(azimuth(np.array([fdp["11.2"], fdp["11.3"]]))))
    knots = [0.0, temple, ear_front, ear_back, ear_back + BEHIND_EAR_DEGREES, 180.0]
    height = [fdp["11.1"][1], 0.5 * (fdp["11.2"][1] + fdp["11.3"][1]), over_ear, over_ear, nape, nape]
    if not np.all(np.diff(knots) > 0.0):
        return None

    line = PchipInterpolator(knots, height)  # through the knots without overshooting them

    def weight(P: np.ndarray) -> np.ndarray:
        P = np.asarray(P, dtype=np.float64).reshape(-1, 3)
        w = np.clip(0.5 + (P[:, 1] - line(azimuth(P))) / (2.0 * HAIRLINE_SOFTNESS), 0.0, 1.0)
        return w * w * (3.0 - 2.0 * w)

    return weight


IRIS_SAMPLE_SHARE = 0.06  # of the eye distance: the disc about each eye's centre whose pixels give the iris colour


def iris_from_photo(model: FaceModel, image: np.ndarray, photo: PhotoPoints, eyes) -> list[float] | None:
    """Colour the irises of the model's eyes (in place) as the photo shows them: the median
    of the pixels about the centre of each eye's contour, leaving out the darkest (pupil,
    lashes) and brightest (white, highlights) thirds. The iris is the vertex colour that
    is neither the eyeball's base colour nor its darkest (the pupil). Returns the linear
    RGB colour used, or None when the head's eyes have no iris colour."""
    eye_px = pupil_distance_px(photo, eyes)
    h, w = image.shape[:2]
    radius = IRIS_SAMPLE_SHARE * eye_px
    samples = []
    for eye in eyes:
        c = photo.points[list(eye), :2].mean(axis=0)
        x0, x1 = max(int(c[0] - radius) - 1, 0), min(int(c[0] + radius) + 2, w)
        y0, y1 = max(int(c[1] - radius) - 1, 0), min(int(c[1] + radius) + 2, h)
        if x1 <= x0 or y1 <= y0:  # the eye's centre beyond the photo's edge (a face cut by the frame)
            continue
        yy, xx = np.mgrid[y0:y1, x0:x1]
        disc = (xx + 0.5 - c[0]) ** 2 + (yy + 0.5 - c[1]) ** 2 <= radius ** 2
        samples.append(image[y0:y1, x0:x1][disc][:, :3].astype(np.float64))
    pixels = np.vstack(samples) if samples else np.zeros((0, 3))
    if len(pixels) < 3:
        return None
    luminance = pixels @ np.array([0.2126, 0.7152, 0.0722])
    lo, hi = np.percentile(luminance, [33.0, 67.0])
    middle = pixels[(luminance >= lo) & (luminance <= hi)]
    linear = (np.median(middle if len(middle) else pixels, axis=0) / 255.0) ** 2.2
    used = None
    for name in ("eye_l", "eye_r"):
        part = model.parts.get(name)
        if part is None or part.vertex_colors is None:
            continue
        colours = np.asarray(part.vertex_colors, dtype=np.float32)
        base = np.all(np.isclose(colours, np.asarray(part.color, np.float32)[None]), axis=1)
        darkest = colours[:, :3].sum(axis=1) <= colours[:, :3].sum(axis=1).min() + 1e-6
        iris = ~base & ~darkest
        if iris.any():
            colours = colours.copy()
            colours[iris, :3] = linear
            part.vertex_colors = colours
            used = [float(v) for v in linear]
    return used
