"""A small bitmap font for the preview's labels: 5x7 glyphs (lowercase descenders two rows below), drawn with
an integer scale factor into a numpy image, clipped at its edges.

The glyphs are this project's own design. A character without a glyph is drawn as a box.
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np
import numpy.typing as npt

GLYPH_W = 5
"""Glyph width (px at scale 1)."""
CAP_H = 7
"""Height of capitals and digits above the baseline (px at scale 1)."""
LINE_H = 9
"""Height of a line of text: capitals and the two rows of descenders (g, j, p, q, y, comma, underscore)."""
ADVANCE = GLYPH_W + 1
"""Horizontal step from one character to the next (px at scale 1): the glyph and one column of space."""

# Rows from the top, '#' = ink; 7 rows (nothing below the baseline) or 9 (with descenders).
_GLYPH_ROWS: dict[str, str] = {
    " ": "..... ..... ..... ..... ..... ..... .....",
    "0": ".###. #...# #..## #.#.# ##..# #...# .###.",
    "1": "..#.. .##.. ..#.. ..#.. ..#.. ..#.. .###.",
    "2": ".###. #...# ....# ...#. ..#.. .#... #####",
    "3": ".###. #...# ....# ..##. ....# #...# .###.",
    "4": "...#. ..##. .#.#. #..#. ##### ...#. ...#.",
    "5": "##### #.... ####. ....# ....# #...# .###.",
    "6": "..##. .#... #.... ####. #...# #...# .###.",
    "7": "##### ....# ...#. ..#.. .#... .#... .#...",
    "8": ".###. #...# #...# .###. #...# #...# .###.",
    "9": ".###. #...# #...# .#### ....# ...#. .##..",
    "A": ".###. #...# #...# ##### #...# #...# #...#",
    "B": "####. #...# #...# ####. #...# #...# ####.",
    "C": ".###. #...# #.... #.... #.... #...# .###.",
    "D": "###.. #..#. #...# #...# #...# #..#. ###..",
    "E": "##### #.... #.... ####. #.... #.... #####",
    "F": "##### #.... #.... ####. #.... #.... #....",
    "G": ".###. #...# #.... #.### #...# #...# .####",
    "H": "#...# #...# #...# ##### #...# #...# #...#",
    "I": ".###. ..#.. ..#.. ..#.. ..#.. ..#.. .###.",
    "J": "..### ...#. ...#. ...#. ...#. #..#. .##..",
    "K": "#...# #..#. #.#.. ##... #.#.. #..#. #...#",
    "L": "#.... #.... #.... #.... #.... #.... #####",
    "M": "#...# ##.## #.#.# #.#.# #...# #...# #...#",
    "N": "#...# #...# ##..# #.#.# #..## #...# #...#",
    "O": ".###. #...# #...# #...# #...# #...# .###.",
    "P": "####. #...# #...# ####. #.... #.... #....",
    "Q": ".###. #...# #...# #...# #.#.# #..#. .##.#",
    "R": "####. #...# #...# ####. #.#.. #..#. #...#",
    "S": ".#### #.... #.... .###. ....# ....# ####.",
    "T": "##### ..#.. ..#.. ..#.. ..#.. ..#.. ..#..",
    "U": "#...# #...# #...# #...# #...# #...# .###.",
    "V": "#...# #...# #...# #...# #...# .#.#. ..#..",
    "W": "#...# #...# #...# #.#.# #.#.# #.#.# .#.#.",
    "X": "#...# #...# .#.#. ..#.. .#.#. #...# #...#",
    "Y": "#...# #...# .#.#. ..#.. ..#.. ..#.. ..#..",
    "Z": "##### ....# ...#. ..#.. .#... #.... #####",
    "a": "..... ..... .###. ....# .#### #...# .####",
    "b": "#.... #.... ####. #...# #...# #...# ####.",
    "c": "..... ..... .###. #.... #.... #.... .###.",
    "d": "....# ....# .#### #...# #...# #...# .####",
    "e": "..... ..... .###. #...# ##### #.... .###.",
    "f": "..##. .#... ####. .#... .#... .#... .#...",
    "g": "..... ..... .#### #...# #...# #...# .#### ....# .###.",
    "h": "#.... #.... ####. #...# #...# #...# #...#",
    "i": "..#.. ..... .##.. ..#.. ..#.. ..#.. .###.",
    "j": "...#. ..... ..##. ...#. ...#. ...#. ...#. #..#. .##..",
    "k": "#.... #.... #..#. #.#.. ##... #.#.. #..#.",
    "l": ".##.. ..#.. ..#.. ..#.. ..#.. ..#.. .###.",
    "m": "..... ..... ##.#. #.#.# #.#.# #.#.# #.#.#",
    "n": "..... ..... ####. #...# #...# #...# #...#",
    "o": "..... ..... .###. #...# #...# #...# .###.",
    "p": "..... ..... ####. #...# #...# #...# ####. #.... #....",
    "q": "..... ..... .#### #...# #...# #...# .#### ....# ....#",
    "r": "..... ..... #.##. ##..# #.... #.... #....",
    "s": "..... ..... .#### #.... .###. ....# ####.",
    "t": ".#... .#... ####. .#... .#... .#..# ..##.",
    "u": "..... ..... #...# #...# #...# #..## .##.#",
    "v": "..... ..... #...# #...# #...# .#.#. ..#..",
    "w": "..... ..... #...# #...# #.#.# #.#.# .#.#.",
    "x": "..... ..... #...# .#.#. ..#.. .#.#. #...#",
    "y": "..... ..... #...# #...# #...# #...# .#### ....# .###.",
    "z": "..... ..... ##### ...#. ..#.. .#... #####",
    "-": "..... ..... ..... .###. ..... ..... .....",
    "_": "..... ..... ..... ..... ..... ..... ..... #####",
    ".": "..... ..... ..... ..... ..... .##.. .##..",
    ":": "..... .##.. .##.. ..... .##.. .##.. .....",
    "/": "....# ....# ...#. ..#.. .#... #.... #....",
    "+": "..... ..#.. ..#.. ##### ..#.. ..#.. .....",
    ",": "..... ..... ..... ..... .##.. .##.. ..#.. .#...",
    "(": "...#. ..#.. .#... .#... .#... ..#.. ...#.",
    ")": ".#... ..#.. ...#. ...#. ...#. ..#.. .#...",
    "%": "##... ##..# ...#. ..#.. .#... #..## ...##",
    "!": "..#.. ..#.. ..#.. ..#.. ..#.. ..... ..#..",
    "?": ".###. #...# ....# ...#. ..#.. ..... ..#..",
    "=": "..... ..... ##### ..... ##### ..... .....",
    "'": "..#.. ..#.. .#... ..... ..... ..... .....",
    "*": "..... ..#.. #.#.# .###. #.#.# ..#.. .....",
    "#": ".#.#. .#.#. ##### .#.#. ##### .#.#. .#.#.",
    "[": ".###. .#... .#... .#... .#... .#... .###.",
    "]": ".###. ...#. ...#. ...#. ...#. ...#. .###.",
}
_BOX_ROWS = "##### #...# #...# #...# #...# #...# #####"

CHARACTERS = "".join(_GLYPH_ROWS)
"""Every character with a glyph of its own."""


def text_size(text: str, scale: int = 1) -> tuple[int, int]:
    """Width and height (px) of the box that :func:`draw_text` draws ``text`` in.

    Parameters
    ----------
    text : str
        One line of text.
    scale : int
        Integer magnification (>= 1): each font pixel is ``scale`` x ``scale`` px.

    Returns
    -------
    (int, int)
        ``(w, h)``: ``w = (6 * len(text) - 1) * scale`` (0 for no text), ``h = 9 * scale`` (capitals and
        descenders).
    """
    _check_scale(scale)
    return max(0, ADVANCE * len(text) - 1) * scale, LINE_H * scale


def draw_text(
    canvas: npt.NDArray[Any], text: str, x: int, y: int, colour: tuple[int, ...] | int, scale: int = 1
) -> None:
    """Draw ``text`` into ``canvas`` in place, its box's top-left corner at (``x``, ``y``); clipped at the edges.

    Parameters
    ----------
    canvas : ndarray, shape (H, W) or (H, W, C)
        The image (px); only the glyphs' pixels change.
    text : str
        One line of text; characters without a glyph (see :data:`CHARACTERS`) are drawn as a box.
    x, y : int
        Column and row (px) of the top-left corner of the text's box (:func:`text_size`); may lie outside.
    colour : int or tuple of int
        Value of the ink: one per channel (e.g. BGR), or one for all.
    scale : int
        Integer magnification (>= 1).
    """
    _check_scale(scale)
    if canvas.ndim not in (2, 3):
        raise ValueError(f"canvas shape = {canvas.shape}: must be (H, W) or (H, W, C)")
    ink = np.asarray(colour, canvas.dtype)
    h, w = canvas.shape[:2]
    gh, gw = LINE_H * scale, GLYPH_W * scale
    y0, y1 = max(y, 0), min(y + gh, h)
    if y0 >= y1:
        return
    for i, ch in enumerate(text):
        gx = x + i * ADVANCE * scale
        x0, x1 = max(gx, 0), min(gx + gw, w)
        if x0 >= x1:
            if gx >= w:
                break
            continue
        mask = _glyph_mask(ch if ch in _GLYPH_ROWS else "", scale)[y0 - y : y1 - y, x0 - gx : x1 - gx]
        canvas[y0:y1, x0:x1][mask] = ink


def _check_scale(scale: int) -> None:
    if not isinstance(scale, int) or scale < 1:
        raise ValueError(f"scale = {scale!r}: must be an integer >= 1")


@functools.cache
def _glyph_mask(ch: str, scale: int) -> npt.NDArray[np.bool_]:
    """Ink of one character ("" for the box), (LINE_H * scale, GLYPH_W * scale) bool, read-only."""
    rows = _GLYPH_ROWS.get(ch, _BOX_ROWS).split()
    mask = np.zeros((LINE_H, GLYPH_W), bool)
    mask[: len(rows)] = [[c == "#" for c in r] for r in rows]
    mask = mask.repeat(scale, axis=0).repeat(scale, axis=1)
    mask.flags.writeable = False
    return mask
