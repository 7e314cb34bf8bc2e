"""High-level FAPs: visemes (FAP 1) and expressions (FAP 2).

FAP 1 carries ``viseme_select1, viseme_select2`` (0..14), ``viseme_blend`` (0..63) and
``viseme_def`` (1 bit); the face shows ``viseme1 * blend/63 + viseme2 * (1 - blend/63)``.
FAP 2 carries ``expression_select1, expression_intensity1, expression_select2,
expression_intensity2`` (selects 0..6, intensities 0..63), ``init_face`` and
``expression_def`` (1 bit each); the face shows
``expr1 * intensity1/63 + expr2 * intensity2/63``.
"""

from __future__ import annotations

from dataclasses import dataclass

VISEME_SELECT_MAX = 14
EXPRESSION_SELECT_MAX = 6
BLEND_MAX = 63  # viseme_blend and expression intensities


@dataclass(frozen=True)
class VisemeInfo:
    code: int
    name: str
    phonemes: str
    examples: str


@dataclass(frozen=True)
class ExpressionInfo:
    code: int
    name: str
    description: str


VISEMES: tuple[VisemeInfo, ...] = (
    VisemeInfo(0, "sil", "none (neutral)", ""),
    VisemeInfo(1, "PP", "p, b, m", "put, bed, mill"),
    VisemeInfo(2, "FF", "f, v", "far, voice"),
    VisemeInfo(3, "TH", "T, D", "think, that"),
    VisemeInfo(4, "DD", "t, d", "tip, doll"),
    VisemeInfo(5, "kk", "k, g", "call, gas"),
    VisemeInfo(6, "CH", "tS, dZ, S", "chair, join, she"),
    VisemeInfo(7, "SS", "s, z", "sir, zeal"),
    VisemeInfo(8, "nn", "n, l", "lot, not"),
    VisemeInfo(9, "RR", "r", "red"),
    VisemeInfo(10, "aa", "A:", "car"),
    VisemeInfo(11, "E", "e", "bed"),
    VisemeInfo(12, "ih", "I", "tip"),
    VisemeInfo(13, "oh", "Q", "top"),
    VisemeInfo(14, "ou", "U", "book"),
)

EXPRESSIONS: tuple[ExpressionInfo, ...] = (
    ExpressionInfo(0, "neutral", "no expression"),
    ExpressionInfo(1, "joy", "eyebrows relaxed; mouth open, mouth corners pulled back toward the ears"),
    ExpressionInfo(2, "sadness", "inner eyebrows bent upward; eyes slightly closed; mouth relaxed"),
    ExpressionInfo(3, "anger", "inner eyebrows pulled downward and together; eyes wide open; lips pressed "
                               "together or opened to expose teeth"),
    ExpressionInfo(4, "fear", "eyebrows raised and pulled together; inner eyebrows bent upward; eyes tense and alert"),
    ExpressionInfo(5, "disgust", "eyebrows and eyelids relaxed; upper lip raised and curled, often asymmetrically"),
    ExpressionInfo(6, "surprise", "eyebrows raised; upper eyelids wide open, lower relaxed; jaw opened"),
)


def viseme_info(code: int) -> VisemeInfo:
    """The viseme with `code` 0..14; ValueError otherwise."""
    if isinstance(code, bool) or not isinstance(code, int) or not 0 <= code <= VISEME_SELECT_MAX:
        raise ValueError(f"viseme code must be an integer 0..{VISEME_SELECT_MAX}, got {code!r}")
    return VISEMES[code]


def expression_info(code: int) -> ExpressionInfo:
    """The expression with `code` 0..6; ValueError otherwise."""
    if isinstance(code, bool) or not isinstance(code, int) or not 0 <= code <= EXPRESSION_SELECT_MAX:
        raise ValueError(f"expression code must be an integer 0..{EXPRESSION_SELECT_MAX}, got {code!r}")
    return EXPRESSIONS[code]


def viseme_by_name(name: str) -> VisemeInfo:
    """The viseme called `name` (``"PP"``, ``"aa"``...; case-sensitive as the standard writes them)."""
    for info in VISEMES:
        if info.name == name:
            return info
    raise KeyError(f"no viseme is called {name!r} (known: {', '.join(v.name for v in VISEMES)})")


def expression_by_name(name: str) -> ExpressionInfo:
    """The expression called `name` (``"joy"``, ``"anger"``...)."""
    for info in EXPRESSIONS:
        if info.name == name.lower():
            return info
    raise KeyError(f"no expression is called {name!r} (known: {', '.join(e.name for e in EXPRESSIONS)})")


@dataclass(frozen=True)
class Viseme:
    """The FAP 1 record of one frame: two visemes and their blend.

    select1, select2  viseme codes 0..14; blend 0..63 (63 = select1 only); definition 0/1
    """

    select1: int
    select2: int
    blend: int
    definition: int

    def weights(self) -> tuple[tuple[int, float], tuple[int, float]]:
        """((select1, w1), (select2, w2)) with w1 = blend/63 and w2 = 1 - w1."""
        w = self.blend / BLEND_MAX
        return ((self.select1, w), (self.select2, 1.0 - w))


@dataclass(frozen=True)
class Expression:
    """The FAP 2 record of one frame: two expressions with their intensities.

    select1, select2  expression codes 0..6; intensity1, intensity2 0..63;
    init_face, definition 0/1
    """

    select1: int
    intensity1: int
    select2: int
    intensity2: int
    init_face: int
    definition: int

    def weights(self) -> tuple[tuple[int, float], tuple[int, float]]:
        """((select1, intensity1/63), (select2, intensity2/63))."""
        return ((self.select1, self.intensity1 / BLEND_MAX), (self.select2, self.intensity2 / BLEND_MAX))
