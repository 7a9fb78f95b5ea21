"""Why a pixel is (not) solved: one enum with its code, name and preview colour.

=====  ===============  ================  =========================================
code   member           name              meaning
=====  ===============  ================  =========================================
0      SOLVED           "solved"          normal and albedo recovered
1      BACKGROUND       "background"      outside the scene mask
2      TOO_DARK         "too dark"        an OV norm at or below the dark threshold
3      CLIPPED          "clipped"         a measurement at or above the clip level
4      INVALID_VALUE    "invalid value"   a NaN, Inf or far negative measurement
5      NO_GOOD_MATCH    "no good match"   no light subset explains it within the noise
6      SOLVED_FROM_...  "solved from a    solved from the remaining lights after
       LIGHT_SUBSET     light subset"     dropping one or a few (shadow, highlight)
7      SOLVED_POOR_...  "solved, poor     solved, but the gauge explains it worse
       MATCH            match"            than ``max_residual``: its uncertainty
                                          says how far off it may be
=====  ===============  ================  =========================================

Codes 0, 6 and 7 are solved pixels. When an unsolved pixel has several problems
the larger code wins (a clipped and dark pixel is reported as clipped). ``invalid.png`` shows each reason in its
``colour`` (8-bit sRGB).
"""

from __future__ import annotations

import enum

import numpy as np

__all__ = ["Reason", "reason_counts", "reason_picture"]


class Reason(enum.IntEnum):
    """Per-pixel outcome of a reconstruction (values are the ``reason`` map's codes).

    Attributes
    ----------
    label : str
        Human-readable name, as in report.json.
    colour : (int, int, int)
        8-bit sRGB colour of the reason in invalid.png.

    Examples
    --------
    >>> from colorps import Reason
    >>> Reason.CLIPPED.label, int(Reason.CLIPPED), Reason(5).name
    ('clipped', 3, 'NO_GOOD_MATCH')
    """

    def __new__(cls, code: int, label: str, colour: tuple[int, int, int]):
        member = int.__new__(cls, code)
        member._value_ = code
        member.label = label
        member.colour = colour
        return member

    SOLVED = 0, "solved", (0, 0, 0)
    BACKGROUND = 1, "background", (64, 64, 64)
    TOO_DARK = 2, "too dark", (40, 90, 255)
    CLIPPED = 3, "clipped", (255, 220, 0)
    INVALID_VALUE = 4, "invalid value", (255, 0, 255)
    NO_GOOD_MATCH = 5, "no good match", (255, 40, 40)
    SOLVED_FROM_LIGHT_SUBSET = 6, "solved from a light subset", (0, 150, 110)
    SOLVED_POOR_MATCH = 7, "solved, poor match", (255, 140, 0)


def reason_counts(reason: np.ndarray) -> dict[str, int]:
    """Number of pixels per reason, keyed by label, every reason present."""
    counts = np.bincount(np.asarray(reason, dtype=np.uint8).ravel(), minlength=len(Reason))
    return {r.label: int(counts[r]) for r in Reason}


def reason_picture(reason: np.ndarray) -> np.ndarray:
    """(H, W, 3) float32 picture (0..1, sRGB-encoded) of a reason map."""
    table = np.zeros((256, 3), dtype=np.float32)
    for r in Reason:
        table[r] = np.array(r.colour) / 255.0
    return table[np.asarray(reason, dtype=np.uint8)]
