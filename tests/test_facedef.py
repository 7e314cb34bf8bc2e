"""FaceDefTables as the standard applies them (fae.animate.facedef.FaceDefOffsets): a FAP
value moves each listed vertex by the integral from 0 of a piecewise-constant rate, so the
motion is zero at 0, linear within each interval, continuous across the borders and held
beyond the last ones."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fae.animate.facedef import FaceDefOffsets
from fae.io.facemodel import FaceDefTable
from fae.mpeg4.faps import FAP_COUNT

VERTICES = 7
FAST = settings(max_examples=40, deadline=None)


@st.composite
def tables(draw):
    """A table of FAP 31 over 1..4 intervals whose borders hold 0, on 1..4 of VERTICES."""
    below = sorted(draw(st.sets(st.integers(1, 2000), max_size=2)), reverse=True)
    above = sorted(draw(st.sets(st.integers(1, 2000), max_size=2)))
    borders = [-float(b) for b in below] + [0.0] + [float(b) for b in above]
    if len(borders) == 1:
        borders.append(float(draw(st.integers(1, 2000))))
    vertices = draw(st.lists(st.integers(0, VERTICES - 1), min_size=1, max_size=4, unique=True))
    rates = draw(st.lists(st.floats(-1e-4, 1e-4), min_size=3 * len(vertices) * (len(borders) - 1),
                          max_size=3 * len(vertices) * (len(borders) - 1)))
    D = np.array(rates).reshape(len(borders) - 1, len(vertices), 3)
    return FaceDefTable(31, "skin", np.array(vertices, dtype=np.int32), np.array(borders), D)


def at(offsets: FaceDefOffsets, value: float) -> np.ndarray:
    values = np.zeros(FAP_COUNT)
    values[30] = value
    out = offsets.offsets(values)
    return np.zeros((VERTICES, 3)) if out is None else out


def integral(table: FaceDefTable, value: float) -> np.ndarray:
    """The standard's definition, one interval at a time: each interval between 0 and the
    (held) value contributes its rate times the part of it that is crossed."""
    b = table.borders
    v = float(np.clip(value, b[0], b[-1]))
    out = np.zeros((VERTICES, 3))
    for j in range(len(b) - 1):
        lo, hi = b[j], b[j + 1]
        crossed = max(0.0, min(v, hi) - max(0.0, lo)) - max(0.0, min(0.0, hi) - max(v, lo))
        out[table.vertices] += crossed * table.displacements[j]
    return out


@FAST
@given(tables(), st.floats(-3000.0, 3000.0))
def test_a_value_moves_the_vertices_by_the_integral_of_the_rates(table, value):
    offsets = FaceDefOffsets([table], VERTICES)
    assert np.allclose(at(offsets, value), integral(table, value), atol=1e-12, rtol=1e-9)
    assert not at(offsets, 0.0).any()  # neutral: no motion


@FAST
@given(tables(), st.data())
def test_the_motion_is_linear_in_each_interval_and_continuous_at_its_borders(table, data):
    offsets = FaceDefOffsets([table], VERTICES)
    b = table.borders
    j = data.draw(st.integers(0, len(b) - 2))
    t = data.draw(st.floats(0.0, 1.0))
    lo, hi = at(offsets, b[j]), at(offsets, b[j + 1])
    assert np.allclose(at(offsets, b[j] + t * (b[j + 1] - b[j])), (1 - t) * lo + t * hi, atol=1e-12, rtol=1e-9)
    eps = 1e-6
    for border in b:
        assert np.allclose(at(offsets, border - eps), at(offsets, border), atol=1e-9)
        assert np.allclose(at(offsets, border + eps), at(offsets, border), atol=1e-9)
    # held beyond the outermost borders
    assert np.array_equal(at(offsets, b[-1] + 500.0), at(offsets, b[-1]))
    assert np.array_equal(at(offsets, b[0] - 500.0), at(offsets, b[0]))


@FAST
@given(tables(), st.floats(0.0, 1.0), st.booleans())
def test_in_the_intervals_next_to_zero_the_motion_scales_with_the_value(table, t, positive):
    offsets = FaceDefOffsets([table], VERTICES)
    b = table.borders
    k = int(np.flatnonzero(b == 0.0)[0])
    if positive and k + 1 < len(b):
        edge = b[k + 1]
    elif not positive and k > 0:
        edge = b[k - 1]
    else:
        return
    assert np.allclose(at(offsets, t * edge), t * at(offsets, edge), atol=1e-12, rtol=1e-9)


def test_tables_of_one_fap_on_shared_vertices_add_up_and_other_parts_and_faps_are_ignored():
    a = FaceDefTable(31, "skin", np.array([0, 1]), np.array([0.0, 100.0]), np.full((1, 2, 3), 1e-5))
    b = FaceDefTable(31, "skin", np.array([1, 2]), np.array([-50.0, 0.0, 100.0]), np.full((2, 2, 3), 2e-5))
    other_part = FaceDefTable(31, "tongue", np.array([0]), np.array([0.0, 100.0]), np.full((1, 1, 3), 1.0))
    other_fap = FaceDefTable(32, "skin", np.array([3]), np.array([0.0, 100.0]), np.full((1, 1, 3), 1.0))
    out = at(FaceDefOffsets([a, b, other_part, other_fap], VERTICES), 50.0)
    assert np.allclose(out[:3, 0], [5e-4, 5e-4 + 1e-3, 1e-3]) and not out[3:].any()


@pytest.mark.parametrize("borders, shape", [([10.0, 20.0], (1, 1, 3)), ([0.0, 5.0, 5.0], (2, 1, 3)),
                                            ([0.0, 5.0], (2, 1, 3))])
def test_tables_the_standard_cannot_mean_are_refused(borders, shape):
    with pytest.raises(ValueError, match="FaceDefTable of FAP 31"):
        FaceDefOffsets([FaceDefTable(31, "skin", np.array([0]), np.array(borders), np.zeros(shape))], VERTICES)


def test_a_posed_face_is_the_rigid_pose_of_rest_plus_offsets():
    table = FaceDefTable(31, "skin", np.array([0]), np.array([0.0, 100.0]), np.full((1, 1, 3), 1e-4))
    offsets = FaceDefOffsets([table], VERTICES)
    rest = np.arange(VERTICES * 3, dtype=np.float64).reshape(VERTICES, 3) * 0.01
    pose = np.eye(4)
    pose[:3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    pose[:3, 3] = (0.1, 0.2, 0.3)
    values = np.zeros(FAP_COUNT)
    values[30] = 50.0
    expected = (rest + at(offsets, 50.0)) @ pose[:3, :3].T + pose[:3, 3]
    assert np.allclose(offsets.displaced(values, rest, pose), expected, atol=1e-15)
