"""The generic head as signed distance fields: skin, skull, teeth, tongue.

Anthropometric numbers are written in millimetres, as the tables they come from are; the
fields here take and return millimetres, and `fae.anatomy.template` converts every mesh
to metres once. Frame: the face looks along +Z, y is up, its left is +x; the origin lies
midway between the eye centres' level and the braincase centre line (y = 0 at the eye
centres, z = 0 near the middle of the braincase).

Every field is symmetric about x = 0 (it reads |x|), so a half mesh mirrors exactly.
"""

from __future__ import annotations

import numpy as np

from fae.anatomy.geometry import (
    sdf_capsule,
    sdf_column,
    sdf_ellipsoid,
    sdf_polyline,
    sdf_round_box,
    sdf_sphere,
    smooth_intersect,
    smooth_subtract,
    smooth_union,
)

# --- landmarks of the design (mm) ---------------------------------------------------------
EYE_CENTER = np.array([32.0, 0.0, 72.0])  # left eye; ES0 = 64 mm
EYE_RADIUS = 12.0
IRIS_RADIUS = 5.6  # IRISD0 = 11.2 mm
PUPIL_RADIUS = 1.9  # a third of the iris diameter (standard neutral face)
EYE_GAP = 0.7  # between eyeball and the skin of the lids/socket
LID_THICKNESS = 2.2
FISSURE_HALF_WIDTH = 15.0  # palpebral fissure about 30 mm long
STOMION_Y = -78.0  # lip line (horizontal, MPEG-4 neutral face)
LIP_GAP = 1.5  # closed lips: a slit narrower than two grid steps meshes as touching lips
MOUTH_HALF_WIDTH = 25.0  # MW0 = 50 mm
OCCLUSAL_Y = -80.0  # upper and lower teeth meet here
JAW_PIVOT = np.array([0.0, -18.0, 10.0])  # on the line through both condyles
CONDYLE_X = 50.0
BONE_MARGIN = 2.5  # least soft tissue over any bone
NECK_AXIS_XZ = np.array([0.0, -18.0])  # the neck's upright axis (x, z)
NAPE_FRONT_Z = 30.0  # the nape's column reaches forward to z = -NAPE_FRONT_Z
NAPE_FRONT_BLEND = 30.0  # over which the column's front fades out
NAPE_BLEND = 25.0  # the column's blend into the neck (the sides and back swell by a quarter of it)
PHILTRUM_COLUMN_X = 4.0  # the philtrum's columns, either side of the midline at the lip

# dental arch: half-ellipse in the xz plane (centre z, semi-axes along x and z)
ARCH_CENTER_Z = 44.0
UPPER_ARCH = (27.0, 40.0)
LOWER_ARCH = (25.5, 38.0)


def _mirror(P: np.ndarray) -> np.ndarray:
    """Points with x replaced by |x| (fields below describe the left side)."""
    Q = P.copy()
    Q[:, 0] = np.abs(Q[:, 0])
    return Q


def _ellipse_ring(P: np.ndarray, a: float, b: float, half_width: float) -> np.ndarray:
    """(n,) approximate distance (in xz) to a band of half-width around the dental arch ellipse."""
    x = P[:, 0]
    z = P[:, 2] - ARCH_CENTER_Z
    k0 = np.sqrt((x / a) ** 2 + (z / b) ** 2)
    k1 = np.sqrt((x / a**2) ** 2 + (z / b**2) ** 2)
    d = k0 * (k0 - 1.0) / np.maximum(k1, 1e-9)
    return np.abs(d) - half_width


def _arch_band(P: np.ndarray, arch: tuple[float, float], half_width, y_lo: float, y_hi: float, z_back: float) -> np.ndarray:
    ring = _ellipse_ring(P, arch[0], arch[1], half_width)
    slab = np.abs(P[:, 1] - 0.5 * (y_lo + y_hi)) - 0.5 * (y_hi - y_lo)
    back = z_back - P[:, 2]
    return smooth_intersect(smooth_intersect(ring, slab, 1.0), back, 2.0)


# --- skin ----------------------------------------------------------------------------------

def _skull_mass(P: np.ndarray, reshaped: bool = False) -> np.ndarray:
    """Cranium and face volume without the features (P already mirrored); reshaped: the
    back of the neck rises into the occiput (see skin_sdf)."""
    cranium = sdf_ellipsoid(P, (0.0, 22.0, -6.0), (75.0, 98.0, 100.0))
    # flatten the temples a little and the back of the head less
    temples = sdf_ellipsoid(P, (0.0, 10.0, 10.0), (71.0, 110.0, 104.0))
    cranium = smooth_intersect(cranium, temples, 20.0)
    face = sdf_ellipsoid(P, (0.0, -40.0, 32.0), (65.0, 74.0, 66.0))
    head = smooth_union(cranium, face, 18.0)
    # lower face and jaw: from the angle of the jaw to the chin
    jaw = sdf_polyline(P, [(50.0, -28.0, 8.0), (49.0, -86.0, 10.0), (34.0, -104.0, 52.0), (14.0, -111.0, 78.0)],
                       [12.0, 13.0, 14.0, 14.0])
    head = smooth_union(head, jaw, 20.0)
    chin = sdf_ellipsoid(P, (0.0, -108.0, 80.0), (20.0, 14.0, 14.0))
    head = smooth_union(head, chin, 14.0)
    under_jaw = sdf_ellipsoid(P, (0.0, -112.0, 18.0), (44.0, 18.0, 52.0))
    head = smooth_union(head, under_jaw, 20.0)
    # muzzle: the maxilla and teeth push the lips forward
    muzzle = sdf_ellipsoid(P, (0.0, -74.0, 70.0), (34.0, 28.0, 28.0))
    head = smooth_union(head, muzzle, 10.0)
    # cheekbones and cheeks
    cheekbone = sdf_ellipsoid(P, (50.0, -14.0, 54.0), (14.0, 10.0, 22.0))
    head = smooth_union(head, cheekbone, 16.0)
    cheek = sdf_ellipsoid(P, (42.0, -50.0, 60.0), (20.0, 26.0, 20.0))
    head = smooth_union(head, cheek, 20.0)
    # neck
    neck = sdf_round_box(P, (NECK_AXIS_XZ[0], -160.0, NECK_AXIS_XZ[1]), (56.0, 70.0, 58.0), 44.0)
    if reshaped:  # the neck's back half as a column up to the skull: the box's round top left a notch
        column = sdf_column(P, NECK_AXIS_XZ, (56.0, 58.0), 44.0, -186.0, -60.0, 24.0)
        # blended into the neck's rounded top and the jaw behind (a plain union left a groove
        # under the ear where the column's side met them)
        neck = smooth_union(neck, smooth_intersect(column, P[:, 2] + NAPE_FRONT_Z, NAPE_FRONT_BLEND), NAPE_BLEND)
    head = smooth_union(head, neck, 30.0)
    return head


def _brow(P: np.ndarray) -> np.ndarray:
    return sdf_polyline(P, [(0.0, 14.0, 92.0), (16.0, 16.0, 90.0), (32.0, 17.0, 86.0), (46.0, 14.0, 76.0)],
                        [7.0, 7.0, 6.0, 3.5])


def _nose(P: np.ndarray) -> np.ndarray:
    bridge = sdf_capsule(P, (0.0, 8.0, 88.0), (0.0, -36.0, 110.0), 4.2, 6.0)
    sides = sdf_capsule(P, (0.0, -4.0, 84.0), (0.0, -38.0, 99.0), 6.0, 11.0)
    tip = sdf_ellipsoid(P, (0.0, -42.0, 110.0), (8.5, 8.0, 9.0))
    ala = sdf_ellipsoid(P, (12.5, -47.0, 99.0), (6.0, 5.8, 8.0))
    columella = sdf_capsule(P, (0.0, -46.0, 110.0), (0.0, -53.0, 101.0), 3.2, 3.5)
    nose = smooth_union(bridge, sides, 6.0)
    nose = smooth_union(nose, tip, 5.0)
    nose = smooth_union(nose, ala, 6.0)
    nose = smooth_union(nose, columella, 3.0)
    return nose


def _nostrils(P: np.ndarray) -> np.ndarray:
    return sdf_ellipsoid(P, (7.0, -52.0, 103.0), (3.6, 4.5, 5.5))


def _lips(P: np.ndarray, reshaped: bool = False) -> np.ndarray:
    """The lips and the skin between the upper one and the nose (P already mirrored);
    reshaped: a philtrum of two columns with a groove between them (see skin_sdf)."""
    y0 = STOMION_Y
    upper = sdf_polyline(P, [(0.0, y0 + 3.8, 98.5), (12.0, y0 + 3.5, 96.5), (22.0, y0 + 1.5, 91.0), (MOUTH_HALF_WIDTH, y0, 86.0)],
                         [4.6, 4.3, 3.0, 1.5])
    lower = sdf_polyline(P, [(0.0, y0 - 4.4, 96.0), (12.0, y0 - 4.0, 94.5), (21.0, y0 - 2.0, 90.0), (MOUTH_HALF_WIDTH, y0, 86.0)],
                         [5.2, 4.8, 3.4, 1.5])
    if reshaped:
        x = PHILTRUM_COLUMN_X
        philtrum = sdf_capsule(P, (x, y0 + 6.0, 94.5), (0.7 * x, -55.0, 97.0), 2.5, 2.5)
    else:  # one ridge down the middle: a keel 4 mm high, whose steep sides shaded as dark streaks
        philtrum = sdf_capsule(P, (0.0, y0 + 6.0, 96.5), (0.0, -55.0, 99.0), 3.0, 3.0)
    lips = smooth_union(upper, lower, 2.0)
    return smooth_union(lips, philtrum, 4.0)


def _mouth_cavity(P: np.ndarray) -> np.ndarray:
    """Air inside the mouth: the slit between the lips, the vestibule around the teeth, the oral space."""
    vestibule = _arch_band(P, (27.0, 40.5), 6.5, OCCLUSAL_Y - 13.0, OCCLUSAL_Y + 13.0, 30.0)
    oral = sdf_ellipsoid(P, (0.0, OCCLUSAL_Y - 3.0, 44.0), (23.0, 10.0, 34.0))
    cavity = smooth_union(vestibule, oral, 4.0)
    slit_x = np.maximum(P[:, 0] - (MOUTH_HALF_WIDTH - 0.5), 0.0)
    slit = np.maximum(np.sqrt((P[:, 1] - STOMION_Y) ** 2 + slit_x**2) - 0.5 * LIP_GAP, 80.0 - P[:, 2])
    return np.minimum(cavity, slit)


def _ear(P: np.ndarray) -> np.ndarray:
    """The left pinna: a tilted dish with a rim, a lobe and a concha, joined to the head."""
    c = np.array([71.0, -14.0, -8.0])
    Q = P - c
    # local frame: tilt the ear back 15 degrees about x, flare it 25 degrees out from the head
    a = np.radians(-15.0)
    ca, sa = np.cos(a), np.sin(a)
    y = ca * Q[:, 1] - sa * Q[:, 2]
    z = sa * Q[:, 1] + ca * Q[:, 2]
    x = Q[:, 0]
    b = np.radians(28.0)
    cb, sb = np.cos(b), np.sin(b)
    xl = cb * x + sb * z  # across the ear's thickness
    zl = -sb * x + cb * z  # front-back in the ear plane
    L = np.stack([xl, y, zl], axis=1)
    outer = sdf_ellipsoid(L, (0.0, 4.0, -2.0), (5.0, 31.0, 17.0))
    lobe = sdf_ellipsoid(L, (0.0, -22.0, 2.0), (4.5, 9.0, 9.0))
    pinna = smooth_union(outer, lobe, 5.0)
    bowl = sdf_ellipsoid(L, (6.5, 4.0, -1.0), (5.5, 25.0, 12.5))
    pinna = smooth_subtract(pinna, bowl, 1.5)
    concha = sdf_ellipsoid(L, (4.5, -4.0, 3.0), (5.0, 9.0, 7.5))
    pinna = smooth_subtract(pinna, concha, 1.5)
    root = sdf_ellipsoid(L, (-6.0, -6.0, 4.0), (8.0, 18.0, 9.0))
    return smooth_union(pinna, root, 3.0)


def _aperture(P: np.ndarray) -> np.ndarray:
    """Almond-shaped wedge in front of the left eye: the gap between the lids."""
    e = EYE_CENTER
    u = (P[:, 0] - e[0]) / FISSURE_HALF_WIDTH
    s = np.clip(1.0 - u**2, 0.0, None)
    # the upper lid arches higher and peaks slightly lateral of the pupil; the lower is flatter
    upper = e[1] + 0.4 * u + IRIS_RADIUS * (s**0.55) * (1.0 + 0.12 * u)
    lower = e[1] + 0.4 * u - IRIS_RADIUS * (s**0.8) * (1.0 - 0.1 * u)
    mid = 0.5 * (upper + lower)
    half = 0.5 * (upper - lower)
    vertical = np.abs(P[:, 1] - mid) - half
    horizontal = np.abs(P[:, 0] - e[0]) - FISSURE_HALF_WIDTH
    front = e[2] + 4.0 - P[:, 2]
    near = np.linalg.norm(P - e, axis=1) - (EYE_RADIUS + EYE_GAP + LID_THICKNESS + 4.0)
    return np.maximum(np.maximum(np.maximum(vertical, horizontal), front), near)


def skin_sdf(P: np.ndarray, reshaped: bool = False) -> np.ndarray:
    """(n,) signed distance (mm, negative inside the soft tissue) of the whole skin surface.

    reshaped: the skin as shaped, whose neck's back rises into the occiput (the neck's
    rounded box alone leaves a notch 4 cm deep under the skull, which every fit to a scan
    kept as a crease across the nape) and whose philtrum is a groove between two columns
    (not one ridge). The skin is meshed without these and the vertices they change then
    moved onto them (fae.anatomy.template.reshaped_skin): the whole field decimates as one,
    and a field changed anywhere decimated the face into another triangulation, which
    everything tuned on the face's would have to be tuned on again."""
    P = _mirror(P)
    head = _skull_mass(P, reshaped)
    head = smooth_union(head, _brow(P), 9.0)
    # orbit hollow above and below the eye, then lids that wrap the eyeball
    hollow = sdf_ellipsoid(P, EYE_CENTER + np.array([0.0, 1.0, 14.0]), (17.0, 13.0, 9.0))
    head = smooth_subtract(head, hollow, 6.0)
    lids = sdf_sphere(P, EYE_CENTER, EYE_RADIUS + EYE_GAP + LID_THICKNESS)
    head = smooth_union(head, lids, 3.0)
    head = smooth_union(head, _nose(P), 6.0)
    head = smooth_union(head, _lips(P, reshaped), 3.0)
    head = smooth_union(head, _ear(P), 4.0)
    head = smooth_subtract(head, _nostrils(P), 1.5)
    head = smooth_subtract(head, _aperture(P), 0.8)
    head = np.maximum(head, -(sdf_sphere(P, EYE_CENTER, EYE_RADIUS + EYE_GAP)))
    head = np.maximum(head, -_mouth_cavity(P))
    return head


# --- bone, teeth, tongue ---------------------------------------------------------------------

def _face_bone(P: np.ndarray) -> np.ndarray:
    braincase = sdf_ellipsoid(P, (0.0, 22.0, -6.0), (69.0, 92.0, 94.0))
    temples = sdf_ellipsoid(P, (0.0, 10.0, 10.0), (65.0, 104.0, 98.0))
    bone = smooth_intersect(braincase, temples, 20.0)
    brow = sdf_polyline(P, [(0.0, 14.0, 88.0), (16.0, 16.0, 86.0), (32.0, 16.0, 82.0), (46.0, 12.0, 72.0)],
                        [6.0, 6.0, 5.5, 4.0])
    bone = smooth_union(bone, brow, 8.0)
    zygoma = sdf_polyline(P, [(44.0, -10.0, 62.0), (52.0, -14.0, 40.0), (56.0, -14.0, 18.0)], [7.0, 5.5, 4.0])
    bone = smooth_union(bone, zygoma, 6.0)
    maxilla = sdf_ellipsoid(P, (0.0, -46.0, 62.0), (36.0, 24.0, 26.0))
    bone = smooth_union(bone, maxilla, 12.0)
    alveolar = _arch_band(P, UPPER_ARCH, 5.0, OCCLUSAL_Y + 8.0, -50.0, 24.0)
    bone = smooth_union(bone, alveolar, 6.0)
    nasal = sdf_capsule(P, (0.0, 8.0, 86.0), (0.0, -22.0, 99.0), 3.0, 2.5)
    bone = smooth_union(bone, nasal, 5.0)
    occiput = sdf_ellipsoid(P, (0.0, -52.0, -30.0), (44.0, 24.0, 40.0))
    bone = smooth_union(bone, occiput, 14.0)
    # orbits around the eyeballs and the nasal aperture
    bone = smooth_subtract(bone, sdf_sphere(P, EYE_CENTER + np.array([0.0, 0.0, 3.0]), EYE_RADIUS + 4.5), 3.0)
    aperture = sdf_ellipsoid(P, (0.0, -38.0, 96.0), (11.0, 15.0, 14.0))
    bone = smooth_subtract(bone, aperture, 2.0)
    return bone


def cranium_sdf(P: np.ndarray) -> np.ndarray:
    """(n,) signed distance (mm) of the cranium with the maxilla, kept inside the skin."""
    P = _mirror(P)
    bone = _face_bone(P)
    return np.maximum(bone, skin_sdf(P) + BONE_MARGIN)


def mandible_sdf(P: np.ndarray) -> np.ndarray:
    """(n,) signed distance (mm) of the mandible, inside the skin and clear of the cranium."""
    P = _mirror(P)
    lower_border = [(CONDYLE_X, -18.0, 10.0), (48.0, -92.0, 8.0), (32.0, -110.0, 52.0), (14.0, -115.0, 76.0), (0.0, -116.0, 80.0)]
    upper_border = [(46.0, -52.0, 14.0), (44.0, -86.0, 24.0), (28.0, -92.0, 56.0), (12.0, -94.0, 76.0), (0.0, -94.0, 78.0)]
    body = smooth_union(sdf_polyline(P, lower_border, [5.0, 5.5, 5.5, 6.0, 6.0]),
                        sdf_polyline(P, upper_border, [4.0, 4.5, 4.5, 4.5, 4.5]), 12.0)
    alveolar = _arch_band(P, LOWER_ARCH, 4.5, -104.0, OCCLUSAL_Y - 8.0, 26.0)
    bone = smooth_union(body, alveolar, 6.0)
    bone = np.maximum(bone, skin_sdf(P) + BONE_MARGIN)
    return np.maximum(bone, -(_face_bone(P) - 1.5))


def upper_teeth_sdf(P: np.ndarray) -> np.ndarray:
    """(n,) signed distance (mm) of the upper dental arch (crowns and roots into the maxilla)."""
    P = _mirror(P)
    half = 3.0 + 2.2 * np.clip((ARCH_CENTER_Z + UPPER_ARCH[1] - P[:, 2]) / 30.0, 0.0, 1.0)
    return _arch_band(P, UPPER_ARCH, half, OCCLUSAL_Y + 0.15, OCCLUSAL_Y + 15.0, ARCH_CENTER_Z - 8.0)


def lower_teeth_sdf(P: np.ndarray) -> np.ndarray:
    """(n,) signed distance (mm) of the lower dental arch."""
    P = _mirror(P)
    half = 2.8 + 2.2 * np.clip((ARCH_CENTER_Z + LOWER_ARCH[1] - P[:, 2]) / 30.0, 0.0, 1.0)
    return _arch_band(P, LOWER_ARCH, half, OCCLUSAL_Y - 14.0, OCCLUSAL_Y - 0.15, ARCH_CENTER_Z - 8.0)


def tongue_sdf(P: np.ndarray) -> np.ndarray:
    """(n,) signed distance (mm) of the tongue lying flat behind the lower teeth."""
    P = _mirror(P)
    body = sdf_ellipsoid(P, (0.0, OCCLUSAL_Y - 6.5, 48.0), (18.0, 5.0, 28.0))
    return body


# --- fields the region and muscle layout reads ---------------------------------------------

def nose_sdf(P: np.ndarray) -> np.ndarray:
    """(n,) signed distance (mm) of the nose's own volume."""
    return _nose(_mirror(P))


def ear_sdf(P: np.ndarray) -> np.ndarray:
    """(n,) signed distance (mm) of the pinnae (both sides)."""
    return _ear(_mirror(P))


def mouth_cavity_sdf(P: np.ndarray) -> np.ndarray:
    """(n,) signed distance (mm) of the air in the mouth (lip slit, vestibule, oral space)."""
    return _mouth_cavity(_mirror(P))
