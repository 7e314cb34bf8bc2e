"""Visemes and expressions (FAPs 1 and 2): the standard's tables and their blending into
low-level FAP values (fae.mpeg4.highlevel, fae.animate.highlevel)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fae.mpeg4.faptables import FAP_LIMITS
from fae.animate.highlevel import EXPRESSION_FAPS, VISEME_FAPS, highlevel_values
from fae.mpeg4.faps import MIRROR_FAP
from fae.mpeg4.highlevel import (BLEND_MAX, EXPRESSION_SELECT_MAX, EXPRESSIONS, VISEME_SELECT_MAX, VISEMES,
                                 Expression, Viseme, expression_by_name, expression_info, viseme_by_name,
                                 viseme_info)

FAST = settings(max_examples=80, deadline=None)
visemes = st.integers(0, VISEME_SELECT_MAX)
expressions = st.integers(0, EXPRESSION_SELECT_MAX)
weights = st.integers(0, BLEND_MAX)


def test_the_standards_tables_are_complete():
    assert [v.code for v in VISEMES] == list(range(15)) and [e.code for e in EXPRESSIONS] == list(range(7))
    assert [v.name for v in VISEMES] == ["sil", "PP", "FF", "TH", "DD", "kk", "CH", "SS", "nn", "RR", "aa", "E",
                                         "ih", "oh", "ou"]
    assert [e.name for e in EXPRESSIONS] == ["neutral", "joy", "sadness", "anger", "fear", "disgust", "surprise"]
    assert VISEME_FAPS.shape == (15, 68) and EXPRESSION_FAPS.shape == (7, 68)
    for info in VISEMES:
        assert viseme_info(info.code) is info and viseme_by_name(info.name) is info
    for info in EXPRESSIONS:
        assert expression_info(info.code) is info and expression_by_name(info.name.upper()) is info
    for bad in (-1, 15, True, 1.0):
        with pytest.raises(ValueError):
            viseme_info(bad)
    with pytest.raises(ValueError):
        expression_info(7)
    with pytest.raises(KeyError):
        viseme_by_name("pp")


def test_each_viseme_and_expression_but_the_neutral_ones_moves_the_face_within_range():
    assert not VISEME_FAPS[0].any() and not EXPRESSION_FAPS[0].any()
    for table in (VISEME_FAPS, EXPRESSION_FAPS):
        assert np.all(table[1:].any(axis=1))
        assert not table[:, :2].any()  # no high-level FAP inside a high-level one
        assert np.all((FAP_LIMITS[:, 0] <= table) & (table <= FAP_LIMITS[:, 1]))
    # the mouth opens for the open vowels, not for the bilabial closure
    assert VISEME_FAPS[10, 2] > VISEME_FAPS[13, 2] > VISEME_FAPS[1, 2] == 0.0


def test_the_symmetric_expressions_move_both_sides_alike():
    """All but disgust (asymmetric by the standard's description) give each left/right FAP pair one value."""
    for code, row in enumerate(EXPRESSION_FAPS):
        if EXPRESSIONS[code].name == "disgust":
            continue
        for fap, partner in MIRROR_FAP.items():
            assert row[fap - 1] == row[partner - 1], (EXPRESSIONS[code].name, fap, partner)
    for row in VISEME_FAPS:
        for fap, partner in MIRROR_FAP.items():
            assert row[fap - 1] == row[partner - 1]


@FAST
@given(visemes, visemes, weights)
def test_a_viseme_blend_is_a_convex_mix_of_its_two_visemes(a, b, blend):
    out = highlevel_values(viseme=Viseme(a, b, blend, 0))
    w = blend / BLEND_MAX
    assert np.allclose(out, w * VISEME_FAPS[a] + (1 - w) * VISEME_FAPS[b])
    low = np.minimum(VISEME_FAPS[a], VISEME_FAPS[b])
    high = np.maximum(VISEME_FAPS[a], VISEME_FAPS[b])
    assert np.all((low - 1e-9 <= out) & (out <= high + 1e-9))
    assert np.array_equal(highlevel_values(viseme=(a, b, blend)), out)  # the record as a tuple
    if a == b:
        assert np.allclose(out, VISEME_FAPS[a])


@FAST
@given(expressions, weights, expressions, weights)
def test_expression_intensities_scale_each_expression_and_zero_is_neutral(a, ia, b, ib):
    out = highlevel_values(expression=Expression(a, ia, b, ib, 0, 0))
    assert np.allclose(out, ia / BLEND_MAX * EXPRESSION_FAPS[a] + ib / BLEND_MAX * EXPRESSION_FAPS[b])
    assert not highlevel_values(expression=Expression(a, 0, b, 0, 0, 0)).any()
    full = np.abs(EXPRESSION_FAPS[a]) + np.abs(EXPRESSION_FAPS[b])
    assert np.all(np.abs(out) <= full + 1e-9)
    one = highlevel_values(expression=Expression(a, ia, 0, 0, 0, 0))
    assert np.all(np.abs(one) <= np.abs(EXPRESSION_FAPS[a]) + 1e-9)
    assert np.all(np.sign(one) * np.sign(EXPRESSION_FAPS[a]) >= 0)


@FAST
@given(visemes, visemes, weights, expressions, weights, expressions, weights)
def test_a_viseme_and_an_expression_add_up(va, vb, blend, ea, ia, eb, ib):
    v, e = Viseme(va, vb, blend, 0), Expression(ea, ia, eb, ib, 0, 0)
    both = highlevel_values(viseme=v, expression=e)
    assert np.allclose(both, highlevel_values(viseme=v) + highlevel_values(expression=e))


def test_no_record_is_the_neutral_face_and_out_of_range_weights_are_bounded():
    assert not highlevel_values().any()
    assert np.allclose(highlevel_values(viseme=(10, 0, 500)), VISEME_FAPS[10])  # blend beyond 63 counts as 63
    assert np.allclose(highlevel_values(expression=(1, -40, 0, 0)), 0.0)  # a negative intensity as 0


@pytest.mark.parametrize("viseme, expression", [((15, 0, 10), None), ((0, -1, 10), None), (None, (7, 63, 0, 0)),
                                                (None, (0, 0, -2, 63))])
def test_codes_outside_the_tables_are_refused(viseme, expression):
    with pytest.raises(ValueError, match="outside"):
        highlevel_values(viseme=viseme, expression=expression)


@pytest.mark.parametrize("pose", ["PP", "anger"])
def test_lips_pressed_meet_along_their_width_and_keep_apart(pose):
    """PP (p, b, m) and anger (lips pressed, by the standard's description) held on the
    shipped head: the lips meet at the middle and halfway to the corners (inner lip points
    2.2/2.3, 2.6/2.8, 2.7/2.9 within 0.5 mm, from 1.5-1.8 mm at rest) and never cross; PP
    breaks nothing at all (with the midlip FAPs alone the sides stayed 0.8 mm open and the
    middles pressed through each other; anger's brows crease its upper lip's wall either way)."""
    from fae.animate.player import Player, playable_head
    from fae.animate.skin_check import SkinCheck, in_head_frame, what_breaks
    from fae.data import shipped_head_path
    from fae.io.facemodel_gltf import read_facemodel
    from fae.io.frames import DenseFrame
    from fae.mpeg4.highlevel import expression_by_name

    face = read_facemodel(shipped_head_path())
    player, check = Player(playable_head(face)), SkinCheck(face)
    F = np.asarray(face.skin_faces)
    row = VISEME_FAPS[1] if pose == "PP" else EXPRESSION_FAPS[expression_by_name(pose).code]

    def gap(V, upper, lower):
        a, b = face.feature_points[upper], face.feature_points[lower]
        return float(np.asarray(a.bary) @ V[F[a.triangle], 1] - np.asarray(b.bary) @ V[F[b.triangle], 1])

    rest = np.asarray(face.skin_vertices)
    assert all(gap(rest, u, d) > 0.0014 for u, d in (("2.2", "2.3"), ("2.6", "2.8"), ("2.7", "2.9")))
    frames = [DenseFrame(index=i, time=i / 25, values=row * min(1.0, i / 5), viseme=None, expression=None)
              for i in range(20)]
    for frame in player.play(frames, fps=25):
        V = in_head_frame(frame.skin_vertices, frame.bone_transforms["head"])
        r = check.frame(V)
        assert r.lip_crossings == 0, frame.index
        if pose == "PP":
            assert not what_breaks(r), frame.index
    for upper, lower in (("2.2", "2.3"), ("2.6", "2.8"), ("2.7", "2.9")):
        assert 0.0 < gap(V, upper, lower) < 0.0005, (upper, lower, gap(V, upper, lower))
