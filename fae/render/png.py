"""PNG images written atomically (Pillow)."""

from __future__ import annotations

import os

import numpy as np
from PIL import Image

from fae.io.atomic import atomic_path


def write_png(path: str | os.PathLike, image: np.ndarray, compress_level: int = 6, sweep: bool = False) -> None:
    """Write (H, W, 3) or (H, W, 4) uint8 `image` to `path`; the file appears only when complete.

    compress_level  zlib level 0-9 (1 is several times faster, files about 30% larger)
    sweep           first remove dead writers' temporary files of `path` (one picture; a
                    writer of a frame sequence leaves it off: each sweep lists the folder)
    """
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] not in (3, 4) or image.dtype != np.uint8:
        raise ValueError(f"{path}: expected an (H, W, 3|4) uint8 image, got {image.shape} {image.dtype}")
    with atomic_path(path, suffix=".png", sweep=sweep) as tmp:
        Image.fromarray(image, mode="RGB" if image.shape[2] == 3 else "RGBA").save(tmp, format="PNG", compress_level=int(compress_level))
