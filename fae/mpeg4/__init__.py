"""Facts of the MPEG-4 FA standard: FAP table, feature points, FAPU, visemes, expressions."""

from fae.mpeg4.faps import FAP_COUNT, FAPS, LIP_PARTNER_FAP, MASK_GROUPS, MIRROR_FAP, FapInfo, fap_by_name, fap_info, mirror_fap
from fae.mpeg4.fapu import fapu0_from_positions, fapu_from_fapu0
from fae.mpeg4.fdps import FEATURE_POINTS, FeaturePoint, feature_point, mirror_point
from fae.mpeg4.highlevel import EXPRESSIONS, VISEMES, Expression, Viseme, expression_info, viseme_info

__all__ = [
    "FAP_COUNT", "FAPS", "LIP_PARTNER_FAP", "MASK_GROUPS", "MIRROR_FAP", "FapInfo", "fap_by_name", "fap_info",
    "mirror_fap", "fapu0_from_positions", "fapu_from_fapu0", "FEATURE_POINTS", "FeaturePoint", "feature_point",
    "mirror_point", "EXPRESSIONS", "VISEMES", "Expression", "Viseme", "expression_info", "viseme_info",
]
