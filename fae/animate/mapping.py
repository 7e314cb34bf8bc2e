"""The layout of a head's FAP -> control mapping (`FaceModel.fap_mapping`), shared by
calibration, which writes it (fae.animate.calibrate), and the controls, which read it
(fae.animate.controls).

    FORMAT_VERSION    the solver the mapping was calibrated for (another moves the feature
                      points by other amounts: a mismatch means calibrating again)
    JAW_CONTROLS      jaw controls at the end of each row: angle (rad), thrust (m), shift (m)
    field_faps(face)  the FAPs that get a pull field on this head, in control order
"""

from __future__ import annotations

from fae.animate.ears import EAR_FAPS
from fae.animate.faptables import FAP_FEATURE_POINT, JAW_FAPS, SKIN_TRANSLATION_FAPS

# 3: the skin solver with the fold guard, crease smoothing and lip contact (fae.sim.folds)
# and pull fields preferred to muscles; 2: implicit anchors, blended holds and derived ear
# tables
FORMAT_VERSION = 3
JAW_CONTROLS = 3


def field_faps(face) -> list[int]:
    """FAPs that get a pull field on this head: skin-bound translations except the jaw's and
    the ears' (fae.animate.ears)."""
    return [k for k in SKIN_TRANSLATION_FAPS
            if k not in JAW_FAPS and k not in EAR_FAPS and FAP_FEATURE_POINT[k - 1] in face.feature_points
            and face.feature_points[FAP_FEATURE_POINT[k - 1]].part == "skin"]
