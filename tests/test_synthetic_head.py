"""The tests' synthetic head (tests/synthetic_head.py) looks like a face where the tests rely on it."""

from __future__ import annotations

import numpy as np

from synthetic_head import synthetic_head


def test_synthetic_head_is_consistent():
    fm = synthetic_head(personalized=False, subdivisions=4, complete=False)
    pos = fm.feature_point_positions()
    assert pos["8.3"][0] > 0 > pos["8.4"][0]            # the face's left is +x
    assert pos["2.2"][1] > pos["2.3"][1]                # upper inner lip above lower
    assert 0.007 < pos["3.1"][1] - pos["3.3"][1] < 0.013  # an iris-sized eye opening
    assert np.all(fm.skin_vertices[fm.skin_mirror][:, 0] * fm.skin_vertices[:, 0] <= 1e-9)


def test_a_complete_head_has_every_feature_point_and_field():
    fm = synthetic_head()
    assert len(fm.feature_points) == 84
    assert fm.face_def_tables and fm.fap_mapping and not np.array_equal(fm.scan_transform, np.eye(4))
    assert all(p.vertex_colors is not None for name, p in fm.parts.items() if name.startswith("eye"))
