"""Pictures to look at instead of numbers to read: labelled contact sheets (PNG only).

Data stays in EXR; everything here is display-referred.  A sheet is a grid of
tiles, each with a band above it in which its label (what it shows: a layer,
camera or light) and its exposure (how values became grey levels) are drawn,
so a sheet read alone says what it is.  Exposure modes (:func:`expose`):

* ``auto``: a linear scale making the 99th percentile of the tile's finite
  luminance (inside its region) white, then the sRGB transfer function, like a
  photograph exposed for its highlights; the note says ``white = V``.  Robust
  to a few hot texels and to any dynamic range (a 1e30 outlier only clips).
* ``unit``: values in [0, 1] shown linearly as grey levels (fractions:
  visibility, masks, shadow mattes, transmittance); note ``0…1 linear``.
* ``signed``: [−1, 1] mapped linearly onto [0, 1] per channel (normals,
  directions); note ``−1…1 linear``.
* ``reinhard``: :func:`relight_cli.tonemap.tonemap` (Reinhard's global operator,
  key 0.18), for environment maps whose sun would clip under ``auto``.

Every preview is labelled and readable: a single picture (a render, a
lat-long map: :func:`picture`, :func:`render_picture`) is enlarged by an
integer factor (nearest neighbour, texels stay square) until its short side is
at least ``MIN_PICTURE`` (256) pixels, under a caption band naming what it
shows and how it was exposed; a sheet's tiles are enlarged to at least
``MIN_TILE`` (160) pixels each.  Names can also be drawn *inside* a tile
(:attr:`Tile.marks`: the UV charts of a feature sheet, :func:`uv_charts`).

NaN/Inf values are drawn magenta and counted in the note; texels outside a
display mask are slate grey.  Sheets are deterministic: the text is
Pillow's built-in font (no system fonts, no time stamps) and PNGs are written
by :func:`relight_cli.formats.image.write_png` (no time chunk).

Shapes: images are [H, W, 3] float64 display values in [0, 1] (row 0 at the top).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

BACKGROUND = 0.10                   # display grey of the sheet
OUTSIDE = (0.24, 0.25, 0.30)        # slate: texels outside a display mask (not data)
NONFINITE = (1.0, 0.0, 1.0)         # magenta: NaN/Inf
LUMA = np.array([0.2126, 0.7152, 0.0722])   # Rec. 709 luminance weights
LABEL_SIZE = 13                     # pixels; legible at 100 % on any screen
TITLE_SIZE = 14
TITLE_LINES = 3                     # a title line wider than the sheet wraps onto this many
MIN_TILE = 160                      # tiles are upscaled (nearest) to at least this many pixels
MAX_TILE = 1024
MAX_FACTOR = 8                      # … by at most this factor (a sheet's tiles)
MIN_PICTURE = 256                   # a single picture's short side, at least (pixels) …
MAX_PICTURE_FACTOR = 64             # … by at most this factor (long side ≤ 2 MAX_TILE)
PAD = 6
MODES = ("auto", "unit", "signed", "reinhard")
MAX_FACE = 192                      # a cube cross is at most 4 × 192 pixels wide


@dataclass
class Tile:
    """One cell of a sheet: ``image`` [H, W, 3] display values in [0, 1], a label
    (first line, e.g. the layer name) and a note (second line, e.g. the exposure).

    ``marks``: names drawn inside the picture after it is enlarged, each
    ``(x, y, text, vertical)`` with (x, y) the centre of the text in the
    image's own pixel units (column, row; 0.5 = the centre of the first
    pixel) and ``vertical`` True to run the text bottom to top (narrow charts),
    optionally a fifth item ``(x0, y0, x1, y1)``: the box (same units) the text
    is kept inside (a chart's bounds).
    """

    image: np.ndarray
    label: str
    note: str = ""
    marks: list = field(default_factory=list)


def expose(values, mode: str = "auto", mask=None, region=None, white: float | None = None,
           percentile: float = 99.0) -> tuple[np.ndarray, str, float]:
    """Linear data [H, W], [H, W, 1] or [H, W, 3] → (display [H, W, 3], note, white).

    ``mask`` [H, W] (> 0.5 inside) greys out the texels outside it; ``region``
    [H, W] (default: ``mask``) is where ``auto`` measures its percentile;
    ``white`` fixes the value shown white instead (``auto`` only: several tiles
    on one exposure).  ``white`` comes back as used (1 for other modes).
    """
    if mode not in MODES:
        raise ValueError(f"exposure mode must be one of {MODES}, got {mode!r}")
    v = np.asarray(values, np.float64)
    if v.ndim == 2:
        v = v[..., None]
    if v.ndim != 3 or v.shape[-1] not in (1, 3):
        raise ValueError(f"values must be [H, W], [H, W, 1] or [H, W, 3], got {v.shape}")
    if v.shape[-1] == 1:
        v = np.repeat(v, 3, axis=-1)
    finite = np.isfinite(v).all(axis=-1)
    clean = np.where(finite[..., None], v, 0.0)
    inside = None if mask is None else np.asarray(mask) > 0.5
    measure = finite if region is None and inside is None else (
        finite & (inside if region is None else np.asarray(region) > 0.5))
    notes = []
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        if mode == "auto":
            if white is None:
                white = _robust_white(clean @ LUMA, measure, percentile)
            display = _srgb(clean / white)
            notes.append(f"white = {white:.3g}")
            negative = (clean < 0).any(axis=-1) & measure
            if negative.any():
                notes.append(f"{negative.sum() / max(measure.sum(), 1):.0%} < 0 (black)")
        elif mode == "unit":
            display, white = np.clip(clean, 0.0, 1.0), 1.0
            notes.append("0…1 linear")
        elif mode == "signed":
            display, white = np.clip((clean + 1.0) / 2.0, 0.0, 1.0), 1.0
            notes.append("−1…1 linear")
        else:
            from relight_cli.tonemap import tonemap
            display, white = tonemap(clean), 1.0
            notes.append("Reinhard, key 0.18")
    if inside is not None:
        display[~inside] = OUTSIDE
    bad = int((~finite).sum())
    if bad:
        display[~finite] = NONFINITE
        notes.append(f"{bad} NaN/Inf (magenta)")
    return display, ", ".join(notes), float(white)


def _robust_white(luminance: np.ndarray, region: np.ndarray, percentile: float) -> float:
    sample = luminance[region]
    if sample.size == 0:
        return 1.0
    white = float(np.percentile(sample, percentile))
    if not white > 0:                   # mostly black (a shadow map, a dim corner): the maximum
        white = float(sample.max())
    return white if white > 0 and math.isfinite(white) else 1.0


def _srgb(x: np.ndarray) -> np.ndarray:
    from relight_cli.tonemap import srgb_oetf
    return srgb_oetf(np.nan_to_num(x, nan=0.0, posinf=1.0, neginf=0.0))


def tile(values, label: str, mode: str = "auto", mask=None, region=None,
         white: float | None = None, note: str = "") -> Tile:
    """A :class:`Tile` of linear data exposed by :func:`expose`; ``note`` goes first."""
    display, exposure, _ = expose(values, mode, mask, region, white)
    return Tile(display, label, ", ".join(filter(None, (note, exposure))))


# ------------------------------------------------------------------ sheets


@lru_cache(maxsize=4)
def _font(size: int):
    from PIL import ImageFont
    return ImageFont.load_default(size=size)


# Pillow's built-in font covers Latin-1 but few symbols: the ones our labels use, spelt out.
_SPELLED = {"−": "-", "–": "-", "—": "-", "→": "->", "×": "x", "²": "^2", "³": "^3",
            "≤": "<=", "≥": ">=", "Σ": "sum ", "α": "alpha", "σ": "sigma", "Δ": "d", "τ": "tau",
            "κ": "kappa", "λ": "lambda", "ω": "w", "…": "..."}


def _printable(text: str) -> str:
    """``text`` with every character the font lacks spelt out (or '?')."""
    return "".join(_SPELLED.get(ch, ch if _has_glyph(ch) else "?") for ch in text)


@lru_cache(maxsize=512)
def _has_glyph(ch: str) -> bool:
    if ch.isascii():
        return True
    font = _font(LABEL_SIZE)
    missing = np.asarray(font.getmask("\uffff"))
    mask = np.asarray(font.getmask(ch))
    return not (mask.shape == missing.shape and (mask == missing).all())


def _fit(text: str, font, width: int) -> str:
    """``text`` (printable), cut with an ellipsis to fit ``width`` pixels."""
    text = _printable(text)
    if font.getlength(text) <= width:
        return text
    while text and font.getlength(text + "...") > width:
        text = text[:-1]
    return text + "..."


def _wrap(text: str, font, width: int, lines: int) -> list[str]:
    """``text`` (printable) on at most ``lines`` lines of ``width`` pixels, broken at
    spaces, and a word wider than a line (a long path) broken inside it, after a '/'
    where one fits; a line that still does not fit (the last one takes the rest) ends in
    '...'."""
    tokens = []                                   # (text, a space before it)
    for i, word in enumerate(_printable(text).split(" ") if text else []):
        tokens += [(piece, i > 0 and j == 0) for j, piece in enumerate(_pieces(word, font, width))]

    def joined(part):
        return "".join((" " if space and n else "") + t for n, (t, space) in enumerate(part))
    out: list[str] = []
    while tokens and len(out) < lines:
        k = 1
        while k < len(tokens) and font.getlength(joined(tokens[:k + 1])) <= width:
            k += 1
        if len(out) == lines - 1:
            k = len(tokens)
        out.append(_fit(joined(tokens[:k]), font, width))
        tokens = tokens[k:]
    return out


def _pieces(word: str, font, width: int) -> list[str]:
    """``word`` cut into pieces no wider than ``width`` (each the longest that fits,
    ending after its last '/' when it has one)."""
    pieces = []
    while word and font.getlength(word) > width:
        n = 1
        while n < len(word) and font.getlength(word[:n + 1]) <= width:
            n += 1
        cut = word.rfind("/", 0, n)
        n = cut + 1 if cut > 0 else n
        pieces.append(word[:n])
        word = word[n:]
    return pieces + ([word] if word else [])


def _upscale(image: np.ndarray, factor: int) -> np.ndarray:
    if factor == 1:
        return image
    return np.repeat(np.repeat(image, factor, axis=0), factor, axis=1)


def _to_bytes(display: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(np.asarray(display, np.float64) * 255.0), 0, 255).astype(np.uint8)


def zoom(shape, min_tile: int = MIN_TILE, max_factor: int = MAX_FACTOR,
         max_side: int = MAX_TILE) -> int:
    """The integer factor a picture of ``shape`` (H, W, …) is enlarged by: the
    smallest that brings its short side to ``min_tile`` pixels, at most
    ``max_factor`` and keeping its long side within ``max_side`` (never < 1)."""
    small, large = min(shape[:2]), max(shape[:2])
    return max(1, min(math.ceil(min_tile / max(small, 1)), max_factor,
                      max_side // max(large, 1)))


def sheet(rows: list[list[Tile]], title: str = "", min_tile: int = MIN_TILE,
          columns: int | None = None, max_factor: int = MAX_FACTOR,
          max_side: int = MAX_TILE, note_lines: int = 1) -> np.ndarray:
    """Tiles laid out row by row, each under its label band (the label, then the
    note on up to ``note_lines`` lines, wrapped at spaces); ``title`` (may hold
    newlines; a line wider than the sheet wraps onto up to :data:`TITLE_LINES`, long
    paths broken after a '/') in a band across the top.  → display [H, W, 3] in [0, 1].
    A row longer than ``columns`` wraps onto the next lines.

    Each tile is upscaled by an integer factor (nearest, so texels stay crisp)
    until its short side reaches ``min_tile`` pixels (at most ``max_factor`` ×,
    its long side at most ``max_side``: :func:`zoom`).  Cells are as large as
    the largest tile; labels too long for their cell are cut with an ellipsis.
    A tile's :attr:`Tile.marks` are drawn on it after the enlargement.
    """
    from PIL import Image, ImageDraw

    rows = [list(r) for r in rows if r]
    if columns:
        rows = [r[k:k + columns] for r in rows for k in range(0, len(r), columns)]
    tiles = [t for r in rows for t in r]
    if not tiles:
        raise ValueError("a sheet needs at least one tile")

    def factor(t):
        return zoom(t.image.shape, min_tile, max_factor, max_side)

    cell_w = max(t.image.shape[1] * factor(t) for t in tiles)
    cell_h = max(t.image.shape[0] * factor(t) for t in tiles)
    font, title_font = _font(LABEL_SIZE), _font(TITLE_SIZE)
    line = LABEL_SIZE + 4
    band = (1 + note_lines) * line + 4
    columns = max(len(r) for r in rows)
    width = PAD + columns * (cell_w + PAD)
    title_lines = [part for text in (title.splitlines() if title else [])
                   for part in (_wrap(text, title_font, width - 2 * PAD, TITLE_LINES) or [""])]
    title_h = (len(title_lines) * (TITLE_SIZE + 5) + PAD) if title_lines else 0
    height = PAD + title_h + len(rows) * (band + cell_h + PAD)
    grey = int(round(BACKGROUND * 255))
    canvas = Image.new("RGB", (width, height), (grey, grey, grey))
    draw = ImageDraw.Draw(canvas)
    for k, text in enumerate(title_lines):
        draw.text((PAD, PAD + k * (TITLE_SIZE + 5)), text, fill=(255, 255, 255),
                  font=title_font)
    for r, row in enumerate(rows):
        y0 = PAD + title_h + r * (band + cell_h + PAD)
        for c, t in enumerate(row):
            x0 = PAD + c * (cell_w + PAD)
            draw.rectangle([x0, y0, x0 + cell_w - 1, y0 + band - 3], fill=(40, 40, 40))
            draw.text((x0 + 4, y0 + 2), _fit(t.label, font, cell_w - 8), fill=(255, 255, 255),
                      font=font)
            for j, text in enumerate(_wrap(t.note, font, cell_w - 8, note_lines)):
                draw.text((x0 + 4, y0 + 2 + (1 + j) * line), text, fill=(190, 190, 190),
                          font=font)
            k = factor(t)
            pixels = _to_bytes(_upscale(np.asarray(t.image), k))
            h, w = pixels.shape[:2]
            left = x0 + (cell_w - w) // 2
            canvas.paste(Image.fromarray(np.ascontiguousarray(pixels), "RGB"), (left, y0 + band))
            for x, y, text, vertical, *box in t.marks:
                if box:                    # (x0, y0, x1, y1) image pixels → canvas pixels
                    box = (left + box[0][0] * k, y0 + band + box[0][1] * k,
                           left + box[0][2] * k, y0 + band + box[0][3] * k)
                _draw_mark(canvas, left + x * k, y0 + band + y * k, text, vertical, font,
                           box or None)
    return np.asarray(canvas, np.float64) / 255.0


def _draw_mark(canvas, cx: float, cy: float, text: str, vertical: bool, font,
               box=None) -> None:
    """``text`` in white on a dark box centred on (cx, cy) of ``canvas`` (PIL image),
    turned to run bottom to top when ``vertical``; with ``box`` (x0, y0, x1, y1) moved
    the least that keeps it inside the box (centred on the box along an axis it does not
    fit)."""
    from PIL import Image, ImageDraw
    text = _printable(text)
    left, top, right, bottom = font.getbbox(text)
    w, h = int(right - left) + 6, int(bottom - top) + 4
    label = Image.new("RGB", (w, h), (20, 20, 20))
    ImageDraw.Draw(label).text((3 - left, 2 - top), text, fill=(255, 255, 255), font=font)
    if vertical:
        label = label.transpose(Image.Transpose.ROTATE_90)
    if box is not None:
        def inside(c, lo, hi, size):
            return (lo + hi) / 2 if hi - lo < size else min(max(c, lo + size / 2), hi - size / 2)
        cx = inside(cx, box[0], box[2], label.width)
        cy = inside(cy, box[1], box[3], label.height)
    canvas.paste(label, (int(round(cx - label.width / 2)), int(round(cy - label.height / 2))))


def draw_labels(display: np.ndarray, labels: list[tuple[int, int, str]]) -> np.ndarray:
    """``display`` [H, W, 3] with each (x, y, text) drawn at its top-left corner on a
    dark box (face names on a cube cross, …)."""
    from PIL import Image, ImageDraw
    canvas = Image.fromarray(_to_bytes(display), "RGB")
    draw = ImageDraw.Draw(canvas)
    font = _font(LABEL_SIZE)
    for x, y, text in labels:
        text = _printable(text)
        box = draw.textbbox((x + 3, y + 2), text, font=font)
        draw.rectangle([box[0] - 3, box[1] - 2, box[2] + 3, box[3] + 2], fill=(20, 20, 20))
        draw.text((x + 3, y + 2), text, fill=(255, 255, 255), font=font)
    return np.asarray(canvas, np.float64) / 255.0


def write_sheet(path: str, rows: list[list[Tile]], title: str = "") -> None:
    """:func:`sheet` written as a PNG, atomically."""
    from relight_cli.formats.image import write_png
    write_png(path, sheet(rows, title))


# ------------------------------------------------------------------ single pictures


def picture(display, label: str, note: str = "", title: str = "", marks=()) -> np.ndarray:
    """One picture (display [H, W, 3] in [0, 1]) as a preview: enlarged by an integer
    factor (nearest) until its short side is at least ``MIN_PICTURE`` pixels (at most
    ``MAX_PICTURE_FACTOR`` ×, long side at most 2048), under a caption band whose first
    line is ``label`` (what it shows; one wider than the picture moves what follows its
    first ': ' into the note) and then ``note`` (its exposure; the picture's own size and
    enlargement are added), wrapped onto up to three lines.
    → display [H', W', 3] in [0, 1] (:func:`picture_box` finds the picture in it)."""
    display = np.asarray(display, np.float64)
    k = zoom(display.shape, MIN_PICTURE, MAX_PICTURE_FACTOR, 2 * MAX_TILE)
    if ": " in label and _font(LABEL_SIZE).getlength(_printable(label)) > display.shape[1] * k - 8:
        # a label wider than the picture ("NAME: linear radiance") keeps its name on the
        # first line and moves what follows to the note, which wraps, instead of being cut
        label, rest = label.split(": ", 1)
        note = ", ".join(filter(None, (rest, note)))
    note, lines, _ = _picture_layout(display.shape, note)
    return sheet([[Tile(display, label, note, list(marks))]], title, min_tile=MIN_PICTURE,
                 max_factor=MAX_PICTURE_FACTOR, max_side=2 * MAX_TILE, note_lines=lines)


def _picture_layout(shape, note: str) -> tuple[str, int, int]:
    """(the full note, its number of lines, the enlargement) of :func:`picture`."""
    k = zoom(shape, MIN_PICTURE, MAX_PICTURE_FACTOR, 2 * MAX_TILE)
    h, w = shape[:2]
    note = ", ".join(filter(None, (note, f"{w}x{h} px" + (f" shown {k}x (nearest)"
                                                           if k > 1 else ""))))
    return note, len(_wrap(note, _font(LABEL_SIZE), w * k - 8, 3)), k


def picture_box(preview_shape, height: int, width: int) -> tuple[int, int, int]:
    """Where :func:`picture` put a [height, width] picture in a preview of
    ``preview_shape`` (H', W', …): (left, top, factor); the rows above ``top`` are the
    caption band (and the title)."""
    k = zoom((height, width), MIN_PICTURE, MAX_PICTURE_FACTOR, 2 * MAX_TILE)
    return PAD, int(preview_shape[0]) - PAD - height * k, k


def reinhard_scale(rgb, key: float = 0.18) -> float:
    """The scale :func:`relight_cli.tonemap.tonemap` applies before Reinhard's curve
    when no exposure is given: ``key`` over the log-average of the positive luminance."""
    v = np.clip(np.nan_to_num(np.asarray(rgb, np.float64), nan=0.0, posinf=0.0, neginf=0.0),
                0, None)
    lum = v @ LUMA
    positive = lum[lum > 0]
    log_avg = float(np.exp(np.mean(np.log(positive + 1e-9)))) if positive.size else 1.0
    return key / max(log_avg, 1e-12)


def render_picture(linear_rgb, label: str, exposure: float | None = None, note: str = "",
                   title: str = "") -> np.ndarray:
    """Linear radiance [H, W, 3] tone-mapped (Reinhard's global operator, then sRGB:
    :func:`relight_cli.tonemap.tonemap`) as a :func:`picture`; the caption's note says
    the operator and the scale it used (``exposure``, or key 0.18 over the
    log-average luminance)."""
    from relight_cli.tonemap import tonemap
    rgb = np.asarray(linear_rgb, np.float64)
    if rgb.ndim == 2:
        rgb = rgb[..., None]
    if rgb.shape[-1] == 1:
        rgb = np.repeat(rgb, 3, axis=-1)
    rgb = rgb[..., :3]
    return picture(tonemap(rgb, exposure), label, render_note(rgb, exposure, note), title)


def render_note(linear_rgb, exposure: float | None = None, note: str = "") -> str:
    """The caption note of :func:`render_picture`: the tone mapping and its scale,
    the count of NaN/Inf pixels (shown black), then ``note``."""
    rgb = np.asarray(linear_rgb, np.float64)
    if exposure is None:
        how = f"Reinhard, key 0.18 (scale {reinhard_scale(rgb):.3g})"
    else:
        how = f"Reinhard, fixed exposure {exposure:g}"
    bad = int((~np.isfinite(rgb)).any(axis=-1).sum())
    if bad:
        how += f", {bad} NaN/Inf (black)"
    return ", ".join(filter(None, (how, note)))


def default_label(path: str) -> str:
    """A caption for a picture written to ``path`` by a caller that gave none:
    the file's name and what it holds (linear radiance, tone-mapped)."""
    name = os.path.basename(str(path))
    stem = name[:-4] if name.lower().endswith(".png") else name
    return f"{stem}: linear radiance" if stem else "linear radiance"


def write_preview(path: str, linear_rgb: np.ndarray, exposure: float | None = None,
                  label: str | None = None, note: str = "", title: str = "") -> None:
    """Tone-map linear radiance [H, W, 3] (Reinhard + sRGB) and write it as a PNG
    preview: enlarged to a readable size under a caption band (formats/preview.md).
    ``label`` says what it shows (default: the PNG's name and "linear radiance");
    the note gets the tone mapping and its scale after ``note``."""
    from relight_cli.formats.image import write_png
    write_png(path, render_picture(linear_rgb, default_label(path) if label is None else label,
                                   exposure, note, title))


# ------------------------------------------------------------------ environment maps and probes

# Horizontal cross (4 × 3 faces) and vertical cross (3 × 4): per face its cell
# (column, row) and the world vectors (forward F, right R, down D) of the view
# from the centre of the cube, d = F + a·R + b·D for a, b ∈ [−1, 1] left→right,
# top→bottom.  Side faces are seen upright (+Y up) in lat-long order (+X, +Z,
# −X, −Z: the lat-long image's own order), so every shared edge is continuous;
# the vertical cross shows −Z upside down below −Y.
_X, _Y, _Z = np.eye(3)
CROSS = {
    "horizontal": {"cells": (4, 3),
                   "+Y": ((1, 0), _Y, -_X, _Z), "+X": ((0, 1), _X, _Z, -_Y),
                   "+Z": ((1, 1), _Z, -_X, -_Y), "-X": ((2, 1), -_X, -_Z, -_Y),
                   "-Z": ((3, 1), -_Z, _X, -_Y), "-Y": ((1, 2), -_Y, -_X, -_Z)},
    "vertical": {"cells": (3, 4),
                 "+Y": ((1, 0), _Y, -_X, _Z), "+X": ((0, 1), _X, _Z, -_Y),
                 "+Z": ((1, 1), _Z, -_X, -_Y), "-X": ((2, 1), -_X, -_Z, -_Y),
                 "-Y": ((1, 2), -_Y, -_X, -_Z), "-Z": ((1, 3), -_Z, -_X, _Y)},
}


def cube_cross(env, face: int | None = None, layout: str = "horizontal"):
    """An environment map unfolded as a cube cross, as seen from inside.

    ``env``: an EnvMap of either layout (looked up at the nearest texel, so a
    cube map's texels come out exactly: face pixel centres span the face edge to
    edge, as in OpenEXR).  ``face``: face size N (default: the cube's own, or
    H/2 of a lat-long map).  Returns (radiance [3N, 4N, 3] (horizontal) or
    [4N, 3N, 3] float64, inside [.., ..] bool, [(x, y, face name)] corners).
    """
    from relight_cli import envmap as E
    spec = CROSS[layout]
    n = int(face or (env.width if env.layout == "cube" else max(2, env.height // 2)))
    n = min(n, MAX_FACE)
    cols, rows = spec["cells"]
    radiance = np.zeros((rows * n, cols * n, 3))
    inside = np.zeros((rows * n, cols * n), bool)
    corners = []
    t = np.linspace(-1.0, 1.0, n) if n > 1 else np.zeros(1)
    b, a = np.meshgrid(t, t, indexing="ij")
    for name in E.FACES:
        (c, r), forward, right, down = spec[name]
        d = forward + a[..., None] * right + b[..., None] * down
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        values = E.lookup(env, d.reshape(-1, 3)).reshape(n, n, 3)
        radiance[r * n:(r + 1) * n, c * n:(c + 1) * n] = values
        inside[r * n:(r + 1) * n, c * n:(c + 1) * n] = True
        corners.append((c * n, r * n, name))
    return radiance, inside, corners


def cross_sheet(env, title: str = "", layout: str = "horizontal") -> np.ndarray:
    """A cube cross of ``env`` (Reinhard, face names drawn in the faces) as a sheet."""
    radiance, inside, corners = cube_cross(env, layout=layout)
    display, note, _ = expose(radiance, "reinhard", mask=inside)
    n = radiance.shape[0] // CROSS[layout]["cells"][1]
    factor = max(1, min(math.ceil(MIN_TILE / 2 / n), 8))   # a face ≥ 80 px: its name fits
    display = draw_labels(_upscale(display, factor),
                          [(x * factor, y * factor, name) for x, y, name in corners])
    label = (f"cube map, {env.width} px faces" if env.layout == "cube" else
             f"lat-long map {env.width}x{env.height}") + f", as a {layout} cross of {n} px faces"
    return sheet([[Tile(display, label, note + "; seen from inside, +Y up")]], title)


def probe_latlong(coefficients, height: int = 128) -> np.ndarray:
    """The radiance of real SH ``coefficients`` [(d+1)², 3] on a lat-long image
    [H, 2H, 3] float64 (OpenEXR's convention: +Y at the top, +Z in the middle)."""
    from relight_cli import envmap as E
    from relight_cli.sh import evaluate_sh
    d = E.latlong_directions(height, 2 * height)
    return evaluate_sh(coefficients, d.reshape(-1, 3)).reshape(height, 2 * height, 3)


def samples_latlong(directions, radiance, height: int = 64):
    """Radiance samples on the sphere (a scene probe's cube faces: directions [N, 3],
    radiance [N, 3]) as a lat-long EnvMap [H, 2H] by nearest sample, for pictures only."""
    from scipy.spatial import cKDTree

    from relight_cli import envmap as E
    from relight_cli.formats.envmap import EnvMap
    d = np.asarray(directions, np.float64).reshape(-1, 3)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    _, nearest = cKDTree(d).query(E.latlong_directions(height, 2 * height).reshape(-1, 3))
    values = np.asarray(radiance, np.float64).reshape(-1, 3)[nearest]
    return EnvMap(values.reshape(height, 2 * height, 3).astype(np.float32), "latlong")


def probe_sheet(coefficients, degree: int, source: str = "", source_env=None,
                position=None, height: int = 128, window: str = "none", step=None) -> np.ndarray:
    """The probe on a lat-long map, labelled with its degree, window and source.

    Top row: radiance L(ω) of the source env map (when given) and of the probe,
    on the source's exposure, so the detail a low degree drops is seen as it
    is; where the probe's reconstruction is negative (ringing) it is drawn as
    green stripes, brighter where it is deeper (:func:`mark_negative`), not as
    black, which would read as a dark part of the scene.  Bottom row: the
    irradiance E(n)/π both give a surface of normal n (what shading uses; equal
    to L for a uniform env), on one exposure: a good probe matches here even
    where its radiance rings.  ``step`` (callable(int) or None) is called after
    each of the three costly stages (a large cube map takes seconds).
    """
    from relight_cli import envmap as E
    from relight_cli.gaussians.probe import irradiance_from_sh
    step = step or (lambda n: None)
    normals = E.latlong_directions(height, 2 * height).reshape(-1, 3)
    probe_l = probe_latlong(coefficients, height)
    probe_e = irradiance_from_sh(coefficients, normals).reshape(height, 2 * height, 3) / math.pi
    step(1)
    n = (degree + 1) ** 2
    name = f"SH probe, degree {degree} ({n} coefficients" + (
        f", {window} window)" if window != "none" else ")")
    radiance, irradiance = [], []
    white_l = white_e = None
    if source_env is not None:
        fine = E.resample(source_env, "latlong", height, 2 * height)
        src_l = fine.radiance
        step(1)
        # Power-preserving, and E is smooth: from the 128-row map, not again from a large
        # cube map's millions of texels (which took most of a 1k cube's preview).
        coarse = E.resample(fine, "latlong", 32, 64)
        src_e = E.irradiance(coarse, normals).reshape(height, 2 * height, 3) / math.pi
        step(1)
        display, note, white_l = expose(src_l)
        radiance.append(Tile(display, f"source radiance: {source}", note))
        display, note, white_e = expose(src_e)
        irradiance.append(Tile(display, "source irradiance / pi", note))
    else:
        step(2)
    shared = ", as the source" if source_env is not None else ""
    mean = np.asarray(coefficients, np.float64)[0] / math.sqrt(4 * math.pi)
    for values, white, row, what in ((probe_l, white_l, radiance, "radiance"),
                                     (probe_e, white_e, irradiance, "irradiance / pi")):
        display, note, white = expose(np.maximum(values, 0), white=white)
        display, negative_note = mark_negative(display, values, white, mean)
        row.append(Tile(display, f"{name}: {what}",
                        ", ".join(filter(None, (note + shared, negative_note)))))
    where = "" if position is None else " at (" + ", ".join(f"{float(x):.3g}" for x in position) + ")"
    title = f"sh-probe of {source}{where}: lat-long maps, +Y at the top, +Z in the middle"
    return sheet([radiance, irradiance], title)


NEGATIVE = np.array([0.15, 0.9, 0.35])   # green stripes: a reconstruction below zero


def mark_negative(display, values, white: float, mean=None, period: int = 4):
    """Draw where linear ``values`` [H, W, 3] are negative in any channel over ``display``
    [H, W, 3]: diagonal stripes of :data:`NEGATIVE`, dimmed to 30 % where the dip is
    shallow and full where it reaches ``white`` (display is unchanged elsewhere).

    → (display, note): the note names the marking, the part of the picture it
    covers (by pixel count; a lat-long's pixels are not equal areas) and, with
    ``mean`` [3] (the mean radiance per channel), the deepest dip in units of it.
    """
    v = np.asarray(values, np.float64)
    negative = (v < 0).any(axis=-1)
    if not negative.any():
        return display, ""
    out = np.array(display, np.float64, copy=True)
    depth = np.clip(-v.min(axis=-1) / (white if white > 0 else 1.0), 0, 1)    # [H, W]
    rows, cols = np.indices(negative.shape)
    stripe = ((rows + cols) // (period // 2)) % 2 == 0
    colour = NEGATIVE * (0.3 + 0.7 * np.sqrt(depth))[..., None]
    out[negative & stripe] = colour[negative & stripe]
    out[negative & ~stripe] = 0.0
    note = f"green stripes: < 0 on {negative.mean():.0%}"
    if mean is not None:
        m = np.asarray(mean, np.float64)
        lit = m > 0
        if lit.any():
            deepest = float((np.clip(-v.min(axis=(0, 1)), 0, None)[lit] / m[lit]).max())
            note += f", to -{deepest:.2f}x mean"
    return out, note


# ------------------------------------------------------------------ feature maps


def _layer_order(name: str) -> tuple:
    base = name.rsplit(".", 1)[-1]
    rank = {"diffuse": 0, "ggx": 2, "visibility": 3, "mask": 4}.get(
        base, 1 if base.startswith("phong") else 5)
    return rank, name


FINGER_NAMES = ("thumb", "index", "middle", "ring", "pinky")
# display colours of the named UV regions (outside the charts: OUTSIDE)
CHART_COLOURS = {"palm": (0.91, 0.62, 0.35), "back": (0.58, 0.42, 0.74),
                 "palm + back": (0.75, 0.52, 0.55), "thumb": (0.86, 0.36, 0.36),
                 "index": (0.42, 0.72, 0.40), "middle": (0.36, 0.56, 0.88),
                 "ring": (0.87, 0.80, 0.34), "pinky": (0.36, 0.78, 0.78)}


def _joint_group(name: str) -> str:
    """A joint's part of the hand: 'palm' (the wrist and the metacarpals of the four
    fingers, the bones inside the palm), else its finger ('thumb', 'index', …)."""
    base = name.split("-")[0]
    if name == "wrist" or (name.endswith("metacarpal") and base != "thumb"):
        return "palm"
    return base if base in FINGER_NAMES else "palm"


def uv_charts(mesh, label_names, joint_names, shape) -> tuple[np.ndarray, list[str]]:
    """Which part of the hand each texel of a [H, W] UV map shows.

    ``mesh``: a HandMesh (uv, faces_uv, faces, weights, optional per-vertex
    ``labels`` indexing ``label_names``); ``joint_names``: the skeleton's
    (WebXR names).  → (region [H, W] int, −1 outside the charts; names).

    Charts are the connected pieces of the UV layout (faces sharing UV
    vertices; the built-in hand has six: the palm tube and five fingers).  A
    chart is named by the skinning weights of its vertices summed per part of
    the hand, the wrist and the four finger metacarpals counting as the palm
    (:func:`_joint_group`): the part with the most weight names it ('thumb',
    'index', 'middle', 'ring', 'pinky' or the palm).  The palm chart wraps
    round the hand, so it is split by the model's per-vertex region labels
    (hand.npz ``labels``: 'palm' and 'dorsum', shown as 'back'), each face by
    the majority of its corners; a hand without region labels (a glTF import)
    shows that chart as 'palm + back'.  Texels are assigned as the features
    are (:func:`relight_cli.uvraster.rasterize_uv`, same resolution), so the
    regions lie exactly on the feature maps' charts.
    """
    from relight_cli.uvraster import rasterize_uv
    from relight_cli.uvraster import uv_charts as charts_of
    faces_uv = np.asarray(mesh.faces_uv, np.int64)
    faces = np.asarray(mesh.faces, np.int64)
    nf = len(faces_uv)
    chart = charts_of(faces_uv)
    groups = np.array([_joint_group(n) for n in joint_names])
    weights = np.asarray(mesh.weights, np.float64)
    names = ["palm", *FINGER_NAMES]
    per_group = np.stack([weights[:, groups == g].sum(axis=1) for g in names], axis=1)  # [V, 6]
    labels = getattr(mesh, "labels", None)
    label_names = list(label_names or [])
    split = (labels is not None and "palm" in label_names and "dorsum" in label_names)
    if split:
        corner = np.asarray(labels, np.int64)[faces]                                  # [F, 3]
        counts = np.stack([(corner == k).sum(axis=1) for k in range(len(label_names))], axis=1)
        face_label = np.array(label_names)[counts.argmax(axis=1)]
    regions: list[str] = []
    face_region = np.empty(nf, np.int64)

    def region_id(name):
        if name not in regions:
            regions.append(name)
        return regions.index(name)

    for c in range(chart.max() + 1):
        where = np.flatnonzero(chart == c)
        part = names[int(per_group[np.unique(faces[where])].sum(axis=0).argmax())]
        if part != "palm":
            face_region[where] = region_id(part)
        elif split:
            back = face_label[where] == "dorsum"
            face_region[where[~back]] = region_id("palm")
            if back.any():
                face_region[where[back]] = region_id("back")
        else:
            face_region[where] = region_id("palm + back")
    raster = rasterize_uv(np.asarray(mesh.uv, np.float64), faces_uv, tuple(shape))
    region = np.where(raster.face >= 0, face_region[np.maximum(raster.face, 0)], -1)
    return region, regions


def chart_tile(region: np.ndarray, names: list[str], label: str = "UV charts",
               note: str = "") -> Tile:
    """A tile naming the hand's UV charts (:func:`uv_charts`): each region in its
    colour, its name drawn at its most interior texel (along a tall narrow chart,
    bottom to top) and kept inside the chart's bounds; outside the charts slate grey."""
    from scipy import ndimage
    region = np.asarray(region)
    image = np.empty(region.shape + (3,))
    image[...] = OUTSIDE
    marks = []
    for k, name in enumerate(names):
        inside = region == k
        if not inside.any():
            continue
        image[inside] = CHART_COLOURS.get(name, (0.7, 0.7, 0.7))
        pieces, n = ndimage.label(inside)
        largest = 1 + int(np.argmax(ndimage.sum(inside, pieces, range(1, n + 1))))
        piece = pieces == largest
        depth = ndimage.distance_transform_edt(np.pad(piece, 1))[1:-1, 1:-1]
        y, x = np.unravel_index(int(np.argmax(depth)), depth.shape)
        rows, cols = np.flatnonzero(piece.any(axis=1)), np.flatnonzero(piece.any(axis=0))
        tall = (rows[-1] - rows[0] + 1) > 1.5 * (cols[-1] - cols[0] + 1)
        marks.append((x + 0.5, y + 0.5, name, bool(tall),
                      (float(cols[0]), float(rows[0]), float(cols[-1] + 1), float(rows[-1] + 1))))
    return Tile(image, label, note, marks)


def feature_sheet(layers: dict, title: str = "", charts=None) -> np.ndarray:
    """bake-features' layers (``relight/features`` names) as a sheet: one row per
    hand, one tile per layer.  Radiometric layers (diffuse, phong<α>, ggx) are
    ``auto``-exposed inside the UV charts (each has its own scale: the env's
    units times its lobe's normalization); visibility and mask are fractions,
    ``unit``.  Texels outside the charts (dilation fill) are greyed out.

    ``charts``: (region [H, W], names) from :func:`uv_charts` at the layers'
    size (every hand of a scene shares its model's UV layout): a last tile per
    hand names the charts (palm, back, each finger), so the layers' blobs can be
    read by where they lie."""
    hands: dict[str, list[str]] = {}
    for name in layers:
        prefix = name.rsplit(".", 1)[0] if "." in name else ""
        hands.setdefault(prefix, []).append(name)
    rows = []
    for prefix, names in hands.items():
        mask_name = f"{prefix}.mask" if prefix else "mask"
        mask = layers.get(mask_name)
        row = []
        for name in sorted(names, key=_layer_order):
            value = layers[name]
            base = name.rsplit(".", 1)[-1]
            fraction = base in ("visibility", "mask")
            row.append(tile(value, name, "unit" if fraction else "auto",
                            mask=None if base == "mask" else mask))
        if charts is not None:
            row.append(chart_tile(charts[0], charts[1], f"{prefix}.charts" if prefix
                                  else "UV charts", "skinning + labels"))
        rows.append(row)
    longest = max(len(r) for r in rows)
    return sheet(rows, title, columns=math.ceil(longest / math.ceil(longest / 5)))


# ------------------------------------------------------------------ light-stage captures


def capture_views(capture, max_cameras: int = 4) -> tuple[list[str], list[tuple]]:
    """What a capture's contact sheet shows: (camera names, columns).

    Cameras: the evaluation cameras first (they have every column), then the
    others spread over the dome, ``max_cameras`` in all.  Columns, each
    (label, note, {camera: image path relative to the folder}): the first fully
    lit frame, a grouped frame of the same pose (else the first), and the first
    held-out pose (not a training pose) under each evaluation env map; each note
    names its pose.
    """
    import os

    from relight_cli.formats.capture import image_path
    names = [c.name for c in capture.cameras]
    renders = (capture.evaluation or {}).get("renders", [])
    evaluated = [n for n in names if any(r["camera"] == n for r in renders)]
    picked = evaluated[:max_cameras]
    rest = [n for n in names if n not in picked]
    if rest and len(picked) < max_cameras:
        k = min(max_cameras - len(picked), len(rest))
        picked += [rest[int(round(i))] for i in np.linspace(0, len(rest) - 1, k)]
    picked = [n for n in names if n in picked]       # dome order
    columns = []
    full = next((f for f in capture.frames if f.lit == "full"), None)
    groups = [f for f in capture.frames if f.lit == "group"]
    # the grouped frame of the fully lit frame's pose where there is one: a column pair
    # that differs in lighting only
    group = next((f for f in groups if full is not None and f.pose == full.pose),
                 groups[0] if groups else None)
    for frame, label in ((full, "fully lit"), (group, "grouped")):
        if frame is not None:
            columns.append((f"{label}, frame {frame.index}",
                            f"pose {frame.pose}, {len(frame.lights_on)} LEDs",
                            {n: image_path(frame.index, n) for n in picked if n in frame.images}))
    if renders:
        pose = min(r["pose"] for r in renders)
        for env in dict.fromkeys(r["env"] for r in renders):
            paths = {r["camera"]: os.path.normpath(r["image"]) for r in renders
                     if r["pose"] == pose and r["env"] == env and r["camera"] in picked}
            columns.append((f"env {env}", f"held-out pose {pose}", paths))
    return picked, columns


def capture_sheet(capture, read, title: str = "", max_cameras: int = 4) -> np.ndarray:
    """Cameras × lighting contact sheet of a capture (rows: cameras, columns: see
    :func:`capture_views`).  ``read(relative path)`` → (rgb [H, W, 3], mask [H, W]).
    Each tile is ``auto``-exposed over its mask (the hand), the value shown white
    in its note; a camera without an image in a column gets a blank tile."""
    cameras, columns = capture_views(capture, max_cameras)
    rows = []
    for name in cameras:
        row = []
        for label, note, paths in columns:
            cam = capture.camera(name)
            if name in paths:
                rgb, mask = read(paths[name])
                row.append(tile(rgb, f"{name} {label}", region=mask, note=note))
            else:
                row.append(Tile(np.full((cam.height, cam.width, 3), BACKGROUND),
                                f"{name} {label}", "not rendered"))
        rows.append(row)
    return sheet(rows, title)


# ------------------------------------------------------------------ deep Gaussian shadow maps


def _crop_box(pixels, shape, least: int = 48) -> tuple[int, int, int, int]:
    """The ROI's inclusive texel box [x0, y0, x1, y1] grown to ``least`` texels a side
    (and a 25 % margin) inside the atlas [H, W]; the whole atlas without an ROI."""
    h, w = shape
    if not pixels or pixels[2] < pixels[0] or pixels[3] < pixels[1]:
        return 0, 0, w - 1, h - 1
    box = []
    for lo, hi, n in ((pixels[0], pixels[2], w), (pixels[1], pixels[3], h)):
        size = min(n, max(least, math.ceil(1.5 * (hi - lo + 1))))
        start = int(np.clip((lo + hi + 1) // 2 - size // 2, 0, n - size))
        box.append((start, start + size - 1))
    return box[0][0], box[1][0], box[0][1], box[1][1]


def dgsm_camera(occluders, receivers, strength, lights, width: int = 320, height: int = 240,
                fov_y_deg: float = 50.0):
    """A look-at camera that frames the occluders and the shadow they cast.

    Target: the centre of the box around the occluders (2-98 % of their
    centres) and the shadowed receivers (strength > 0.05); the camera frames
    that box's bounding sphere, looking across the shadow from the side of the
    light direction and above (so neither the object nor the light hides the
    shadow), and stays inside the receivers' robust bounding box (a room's
    walls do not hide the view).
    """
    from relight_cli.formats.camera import Camera
    occ = np.asarray(occluders.means, np.float64)
    pts = np.asarray(receivers.means, np.float64)
    shadowed = pts[np.asarray(strength) > 0.05]
    corners = [np.percentile(occ, 2, 0), np.percentile(occ, 98, 0)]
    if len(shadowed):
        corners += [shadowed.min(0), shadowed.max(0)]
    lo_box, hi_box = np.min(corners, axis=0), np.max(corners, axis=0)
    target = (lo_box + hi_box) / 2
    radius = max(float(np.linalg.norm(hi_box - lo_box)) / 2, 0.05)
    distance = 1.15 * radius / math.sin(math.radians(fov_y_deg) / 2)
    down = np.asarray(lights, np.float64).reshape(-1, 3).mean(0) - target
    horizontal = np.array([down[0], 0.0, down[2]])
    if np.linalg.norm(horizontal) < 1e-6 * max(np.linalg.norm(down), 1e-9):
        horizontal = np.array([0.0, 0.0, 1.0])
    horizontal /= np.linalg.norm(horizontal)
    side = np.array([-horizontal[2], 0.0, horizontal[0]])
    lo, hi = np.percentile(pts, 2, 0), np.percentile(pts, 98, 0)
    margin = 0.05 * (hi - lo)
    best = None
    for s in (side, -side):                   # the side with more room in front of it
        direction = 0.75 * s + 0.35 * horizontal + 0.55 * np.array([0.0, 1.0, 0.0])
        eye = target + distance * direction / np.linalg.norm(direction)
        clipped = eye.copy()
        for axis in (0, 2):
            if hi[axis] - lo[axis] > 2 * radius:
                clipped[axis] = np.clip(eye[axis], lo[axis] + margin[axis], hi[axis] - margin[axis])
        clipped[1] = max(clipped[1], lo[1] + radius)
        if hi[1] - lo[1] > 4 * radius:       # a ceiling, maybe: stay under it
            clipped[1] = min(clipped[1], hi[1] - margin[1])
        room = float(np.linalg.norm(clipped - target))
        if best is None or room > best[0] + 1e-9:
            best = (room, clipped)
    return Camera.look_at(best[1], target, width=width, height=height, fov_y_deg=fov_y_deg,
                          name="dgsm-preview")


def dgsm_sheet(shadow_map, occluders, receivers=None, camera=None, footprint: str = "stencil",
               samples: int = 16, seed: int = 0, title: str = "", max_lights: int = 3,
               strength=1.0, probe_coefficients=None, shadowed: list | None = None):
    """A DGSM's result as a sheet.  With receivers: (1) the scene as ``relight``
    draws it (receivers darkened by relight's own shadow factor at shadow ``strength``,
    a number or ``auto`` with the scene's ``probe_coefficients``:
    relight_cli.gaussians.receiver_shadow; the strength in the tile's label; occluders
    in their own colours; the shadowed receivers appended to ``shadowed`` if given),
    ``reinhard`` as relight's own previews; (2) the paper's shadow matte 1 − Σ w_l T_l / Σ w_l
    on the receivers only (Sec. 4.2), ``unit``; both from ``camera`` (default
    :func:`dgsm_camera`).  Then per light (at most ``max_lights``) the atlas
    slice the lookups read, min over radial bins of T (``unit``, black = opaque).
    Returns (display sheet, the camera used or None)."""
    from relight_cli.formats.gaussians_ply import concatenate
    from relight_cli.gaussians import dgsm as D
    from relight_cli.gaussians import shadow_matte as SM
    from relight_cli.gaussians import transfer as TF
    from relight_cli.gaussians.splat import render
    rows = []
    if receivers is not None:
        mode = TF.effective_light_weights("intensity", shadow_map.intensities)
        weights = TF.dgsm_light_weights(mode, shadow_map, receivers)
        T = D.sample_transmittance(shadow_map, receivers.means, receivers.scales,
                                   receivers.rotations, footprint=footprint, samples=samples,
                                   seed=seed)                                    # [L, M]
        factor = TF.shadow_factor(T, weights, 1.0)
        matte_strength = SM.shadow_strength(factor)
        if camera is None:
            camera = dgsm_camera(occluders, receivers, matte_strength, shadow_map.lights)
        from relight_cli.gaussians.receiver_shadow import receiver_shadow
        shadow = receiver_shadow(shadow_map, receivers, T, strength,
                                 probe_coefficients=probe_coefficients)
        darkened = TF.attenuate(receivers, shadow.factor)
        if shadowed is not None:
            shadowed.append(darkened)
        scene = render(concatenate([darkened, occluders]), camera)
        matte = render(receivers, camera, colors=SM.matte_colors(matte_strength))
        where = f"{camera.width}x{camera.height}, camera {camera.name or 'given'}"
        rows.append([tile(scene.image, f"relight's shadow at strength {shadow.describe()}",
                          "reinhard", note=f"receivers + occluders, {where}"),
                     tile(matte.image, "shadow matte on receivers",
                          "unit", note=f"{int((matte_strength > 0.1).sum())} of "
                                       f"{len(matte_strength)} > 0.1")])
    atlas = []
    for li in range(min(len(shadow_map.lights), max_lights)):
        slice_ = shadow_map.transmittance[li].min(axis=0)                      # [H, W]
        roi = shadow_map.roi[li] if li < len(shadow_map.roi) else {}
        x0, y0, x1, y1 = _crop_box(roi.get("pixels"), slice_.shape)
        crop = slice_[y0:y1 + 1, x0:x1 + 1]
        step = max(1, math.ceil(max(crop.shape) / 256))
        where = ("all texels" if crop.shape == slice_.shape else
                 f"texels x {x0}-{x1}, y {y0}-{y1}")
        atlas.append(tile(crop[::step, ::step], f"light {li} atlas: min T over {shadow_map.bins} "
                          f"bins", "unit", note=where))
    return sheet([[t for row in rows for t in row] + atlas], title, columns=3), camera
