"""The skin's texture from a photo (paper 002 §2.2), in the skin's own texture coordinates.

    photo_texture(model, image, face_outline, seen, size) -> ((H, W, 3) uint8, report)

Every texel of the skin's (cylindrical) texture map is a point of the skin: the visible
skin's vertices, laid out by their texture coordinates, are triangulated (Delaunay, with
the vertices next to the seam repeated across it) and each texel centre interpolates its
point and normal. The point goes through the head's scan_transform (face frame -> photo
pixels, fae.adapt.photo) and takes the photo's colour there, with a weight that is

  - 0 where the skin faces away from the camera, fading in as it turns towards it (a
    grazing view stretches a few pixels over much skin);
  - 0 where other skin lies in front of it on the photo (a depth buffer of the texels
    themselves);
  - 0 outside the face's outline on the photo (the landmark model's face oval: hair,
    ears and background lie beyond it), fading in over FEATHER_SHARE of the face's width
    (the paper's feathered border).

Where the weight is below 1, the photo's colours are blended into a fill: the face's
colours spread outwards by normalized convolution (so the forehead's colour carries up
into the scalp, the jaw's down the neck), turning into the face's median colour further
away. Nothing is left unpainted, and no seam shows where the photo ends.

Hair: over a cap above the head's hairline (fae.adapt.photo.hair_cap, evaluated at each
texel), the photo's colour where it sees the cap decides (hair_colours): a median far
from the skin's is hair, which then covers the whole cap, the crown and the back the photo
never saw included, with the photo's own strands where it sees them; a median near the
skin's is a bald head, left as the skin's fill.
"""

from __future__ import annotations

import numpy as np

TEXTURE_SIZE = (1024, 1024)  # width, height in texels
FACING_FULL = 0.55  # cosine between normal and view at which the photo counts fully
FACING_NONE = 0.2  # ... and below which it does not count
FEATHER_SHARE = 0.12  # of the face's width on the photo: the outline's soft border
OUTLINE_SHRINK = 0.92  # the outline pulled towards its centre: its own pixels are often hair or background
DEPTH_TOLERANCE = 0.008  # metres: skin this far behind the nearest is still seen (a grazing cheek beside the nose)
SPREAD_TEXELS = 48.0  # Gaussian sigma of the fill's spreading, texels
BORDER_COLOUR_SPREAD = 45.0  # RGB levels: how far from the face's colour a border texel may be
HOLE_TEXELS = 6.0  # ... and of the close fill of the eyes' and mouth's holes


def texel_surface(V: np.ndarray, N: np.ndarray, uv: np.ndarray, size: tuple[int, int]
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points and normals of the surface at texel centres.

    V (n, 3) metres, N (n, 3) unit normals, uv (n, 2) in [0, 1] (u wraps around); size
    (width, height). Returns (inside (H, W) bool: texels within the laid-out surface,
    P (H, W, 3), NN (H, W, 3); nan outside). Texel row r, column c is uv ((c + .5) / W,
    (r + .5) / H).
    """
    from scipy.interpolate import LinearNDInterpolator

    width, height = size
    near_seam_low = uv[:, 0] < 0.1
    near_seam_high = uv[:, 0] > 0.9
    UV = np.concatenate([uv, uv[near_seam_low] + [1.0, 0.0], uv[near_seam_high] - [1.0, 0.0]])
    per_vertex = np.hstack([V, N])
    values = np.concatenate([per_vertex, per_vertex[near_seam_low], per_vertex[near_seam_high]])
    interp = LinearNDInterpolator(UV, values)
    u = (np.arange(width) + 0.5) / width
    v = (np.arange(height) + 0.5) / height
    uu, vv = np.meshgrid(u, v)
    out = interp(np.column_stack([uu.ravel(), vv.ravel()])).reshape(height, width, 6)
    inside = np.all(np.isfinite(out), axis=2)
    NN = out[:, :, 3:]
    NN = NN / np.maximum(np.linalg.norm(NN, axis=2, keepdims=True), 1e-12)
    return inside, out[:, :, :3], NN


def outline_weight(outline: np.ndarray, image_size: tuple[int, int], feather_px: float) -> np.ndarray:
    """(H, W) float in [0, 1] over the photo: 1 well inside the polygon outline (k, 2)
    pixels, falling to 0 at its edge over feather_px pixels (a raised sine)."""
    from scipy.ndimage import distance_transform_edt
    from skimage.draw import polygon

    width, height = image_size
    mask = np.zeros((height, width), dtype=bool)
    rr, cc = polygon(outline[:, 1], outline[:, 0], shape=mask.shape)
    mask[rr, cc] = True
    depth = distance_transform_edt(mask)
    x = np.clip(depth / max(feather_px, 1e-9), 0.0, 1.0)
    return 0.5 - 0.5 * np.cos(np.pi * x)


def bilinear_samples(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(k, C) float samples of image (H, W, C) at pixel coordinates x, y (k,) (pixel
    centres at +0.5), clamped at the border."""
    from scipy.ndimage import map_coordinates

    coords = np.vstack([y - 0.5, x - 0.5])
    return np.stack([map_coordinates(image[:, :, c].astype(np.float64), coords, order=1, mode="nearest")
                     for c in range(image.shape[2])], axis=1)


def polygon_mask(polygon: np.ndarray, image_size: tuple[int, int]) -> np.ndarray:
    """(H, W) bool: pixels inside the polygon (k, 2) pixels, of an image of size (W, H)."""
    from skimage.draw import polygon as fill

    width, height = image_size
    mask = np.zeros((height, width), dtype=bool)
    rr, cc = fill(polygon[:, 1], polygon[:, 0], shape=mask.shape)
    mask[rr, cc] = True
    return mask


def _spread(W: np.ndarray, C: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Normalized convolution of colours C (H, W, 3) with weights W (H, W), wrapping in u:
    (colour (H, W, 3), its weight (H, W))."""
    from scipy.ndimage import gaussian_filter

    mode = ("nearest", "wrap")
    weight = gaussian_filter(W, sigma, mode=mode)
    colour = np.stack([gaussian_filter(W * C[:, :, c], sigma, mode=mode) for c in range(3)], axis=2)
    return colour / np.maximum(weight, 1e-9)[:, :, None], weight


def photo_texture(V: np.ndarray, N: np.ndarray, uv: np.ndarray, to_photo: np.ndarray, image: np.ndarray,
                  face_outline: np.ndarray, holes=(), size: tuple[int, int] = TEXTURE_SIZE,
                  hair=None) -> tuple[np.ndarray, dict]:
    """The texture (H, W, 3) uint8 of a skin coloured from a photo, and a report.

    V (n, 3) metres, N (n, 3) unit normals, uv (n, 2): the visible skin (leave out what no
    camera sees: inside the mouth, behind the eyes); to_photo (4, 4): face frame -> photo
    pixels (x right, y down, z away, the head's scan_transform); image (h, w, 3) uint8;
    face_outline (k, 2) photo pixels around the face; holes: polygons (k, 2) of photo
    pixels whose colours are not the skin's (the eyes, the open mouth: their colours on
    the lids or lips would stay painted there whatever the face does); the skin there
    takes its neighbours' colours; hair: where the head's hair grows, a function of points
    (k, 3) in the face frame giving weights (k,) in [0, 1] (fae.adapt.photo.hair_cap),
    coloured by hair_colours when the photo shows hair there.
    """
    from scipy.ndimage import binary_dilation

    width, height = size
    image = np.asarray(image)[:, :, :3]
    ih, iw = image.shape[:2]
    inside, P, NN = texel_surface(np.asarray(V, np.float64), np.asarray(N, np.float64),
                                  np.asarray(uv, np.float64), size)
    at = np.flatnonzero(inside.ravel())
    X = P.reshape(-1, 3)[at]
    Nx = NN.reshape(-1, 3)[at]
    q = X @ to_photo[:3, :3].T + to_photo[:3, 3]
    # the camera looks along +z of the photo frame (z away): a surface faces it when its
    # normal, carried by the same rotation, points along -z
    scale = np.cbrt(abs(np.linalg.det(to_photo[:3, :3])))
    facing = -(Nx @ to_photo[:3, :3].T)[:, 2] / scale
    w = np.clip((facing - FACING_NONE) / (FACING_FULL - FACING_NONE), 0.0, 1.0)
    w = w * w * (3.0 - 2.0 * w)
    # depth buffer of the texels themselves, one cell per photo pixel
    cell = 1.0
    gx = np.clip((q[:, 0] / cell).astype(np.int64), 0, int(iw / cell))
    gy = np.clip((q[:, 1] / cell).astype(np.int64), 0, int(ih / cell))
    key = gy * (int(iw / cell) + 1) + gx
    nearest = np.full(key.max() + 1, np.inf)
    front = facing > 0.0
    np.minimum.at(nearest, key[front], q[front, 2])
    seen = w * (q[:, 2] <= nearest[key] + DEPTH_TOLERANCE * scale)  # facing the camera, not hidden
    w = seen.copy()
    # inside the face's outline on the photo, feathered
    centre = face_outline.mean(axis=0)
    outline = centre + OUTLINE_SHRINK * (face_outline - centre)
    face_width = float(np.ptp(outline[:, 0]))
    ow = outline_weight(outline, (iw, ih), FEATHER_SHARE * face_width)
    for hole in holes:  # a pixel's margin: the contour points sit on the edge itself
        ow[binary_dilation(polygon_mask(np.asarray(hole, np.float64), (iw, ih)), iterations=1)] = 0.0
    px = np.clip(q[:, 0], 0, iw - 1).astype(np.int64)
    py = np.clip(q[:, 1], 0, ih - 1).astype(np.int64)
    on_image = (q[:, 0] >= 0) & (q[:, 0] < iw) & (q[:, 1] >= 0) & (q[:, 1] < ih)
    edge = np.where(on_image, ow[py, px], 0.0)
    w *= edge
    colour = bilinear_samples(image, q[:, 0], q[:, 1])
    # in the outline's soft border the photo often shows hair, a hat's brim or background:
    # there a colour far from the face's own counts less (inside, brows and lips keep theirs)
    core = (edge >= 1.0) & (w > 0.5)
    if core.sum() >= 100:
        face_colour = np.median(colour[core], axis=0)
        likeness = np.exp(-(np.linalg.norm(colour - face_colour, axis=1) / BORDER_COLOUR_SPREAD) ** 2)
        w *= np.where(edge < 1.0, likeness, 1.0)

    W = np.zeros(height * width)
    W[at] = w
    C = np.zeros((height * width, 3))
    C[at] = colour
    W = W.reshape(height, width)
    C = C.reshape(height, width, 3)
    trusted = W > 0.5
    if trusted.sum() < 100:
        raise ValueError("the photo colours too little of the skin (is the head's scan_transform the photo's camera?)")
    median = np.median(C[trusted], axis=0)
    # fill: the photo's colours spread outwards (normalized convolution, wrapping around in
    # u): close neighbours first (the holes of the eyes and mouth), then the wide surround
    near, near_w = _spread(W, C, HOLE_TEXELS)
    far, far_w = _spread(W, C, SPREAD_TEXELS)
    confidence = np.clip(far_w / 0.05, 0.0, 1.0)[:, :, None]
    fill = confidence * far + (1.0 - confidence) * median
    confidence = np.clip(near_w / 0.3, 0.0, 1.0)[:, :, None]
    fill = confidence * near + (1.0 - confidence) * fill
    out = W[:, :, None] * C + (1.0 - W[:, :, None]) * fill
    report = {"texture_size": [int(width), int(height)], "texels_on_skin": int(len(at)),
              "texels_from_photo": int((W > 0.5).sum()), "median_colour": [float(c) for c in median]}
    if hair is not None:
        cap = hair(X)
        on_photo = seen * on_image
        colours, hair_weight, report["hair"] = hair_colours(cap, on_photo, colour, median)
        if colours is not None:
            H = np.zeros(height * width)
            H[at] = hair_weight
            hair_rgb = np.zeros((height * width, 3))
            hair_rgb[at] = colours
            H = H.reshape(height, width, 1)
            out = H * hair_rgb.reshape(height, width, 3) + (1.0 - H) * out
    return np.clip(np.round(out), 0, 255).astype(np.uint8), report


HAIR_CONTRAST = 60.0  # RGB levels between the skin's median and the scalp's: hair, not a bald head
HAIR_SAMPLE = 0.9  # cap weight from which a seen texel's colour counts towards the hair's
HAIR_MIN_TEXELS = 200  # seen texels of the cap at least, for its colour to be trusted
HAIR_COLOUR_SPREAD = 45.0  # RGB levels: how far from the hair's median a seen pixel may be and still show


def hair_colours(cap: np.ndarray, seen: np.ndarray, photo_colour: np.ndarray, skin_colour: np.ndarray
                 ) -> tuple[np.ndarray | None, np.ndarray | None, dict]:
    """The hair over the scalp, from what the photo shows of it.

    cap (k,) in [0, 1]: where hair grows, per texel; seen (k,) in [0, 1]: how well the
    photo sees the texel (facing, not hidden); photo_colour (k, 3): the photo there;
    skin_colour (3,): the skin's median. The hair's colour is the median of the photo
    over the cap where it is seen; when that is within HAIR_CONTRAST of the skin's (a bald
    head, a bare forehead where the cap begins) or the photo sees too little of the cap,
    there is no hair. Otherwise each texel takes the hair's colour, with the photo's own
    where it sees the texel and shows a colour near the hair's (strands, highlights;
    not the background beyond a head smaller than the template's).
    Returns (colours (k, 3) or None, weights (k,) or None, report).
    """
    sample = (cap >= HAIR_SAMPLE) & (seen > 0.5)
    report = {"texels_seen": int(sample.sum()), "found": False}
    if sample.sum() < HAIR_MIN_TEXELS:
        return None, None, report
    hair = np.median(photo_colour[sample], axis=0)
    contrast = float(np.linalg.norm(hair - skin_colour))
    report.update({"colour": [float(c) for c in hair], "contrast_to_skin": contrast})
    if contrast < HAIR_CONTRAST:
        return None, None, report
    likeness = np.exp(-(np.linalg.norm(photo_colour - hair, axis=1) / HAIR_COLOUR_SPREAD) ** 2)
    own = (seen * likeness)[:, None]
    report["found"] = True
    return own * photo_colour + (1.0 - own) * hair, cap, report
