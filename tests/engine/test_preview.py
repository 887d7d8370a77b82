"""Previews (relight_cli/preview.py): exposure, contact sheets, cube crosses, SH probes, the
``--preview`` of bake-features, dgsm-build, sh-probe, synth-capture and envmap, and every preview
readable (issue 24): a tiny picture enlarged to at least ``MIN_PICTURE`` pixels under a caption
strip naming what it shows and its tone mapping; bake-features' sheets name the UV charts."""

from __future__ import annotations

import json
import math
import struct

import numpy as np
import pytest
from click.testing import CliRunner

from relight_cli import preview as PV
from relight_cli.cli import cli


def invoke(*args):
    return CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)


def read_png(path) -> np.ndarray:
    from relight_cli.formats.image import read_image
    pixels, _ = read_image(str(path))
    return np.rint(pixels * 255).astype(int)


def png_chunks(path) -> list[tuple[bytes, bytes]]:
    data = open(path, "rb").read()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    out, i = [], 8
    while i < len(data):
        n = struct.unpack(">I", data[i:i + 4])[0]
        out.append((data[i + 4:i + 8], data[i + 8:i + 8 + n]))
        i += 12 + n
    return out


def grid_size(columns: int, rows: int, cell_w: int, cell_h: int, title_lines: int = 1):
    """(width, height) of a sheet by the layout rules of PV.sheet."""
    band = 2 * (PV.LABEL_SIZE + 4) + 4
    title = title_lines * (PV.TITLE_SIZE + 5) + PV.PAD if title_lines else 0
    return (PV.PAD + columns * (cell_w + PV.PAD),
            PV.PAD + title + rows * (band + cell_h + PV.PAD))


def on_grid(image, columns: int, rows: int, cell_w: int, cell_h: int) -> bool:
    """``image`` is a sheet of this grid under a title of any number of lines (a title
    that names a temporary folder wraps onto as many lines as the path needs)."""
    width, untitled = grid_size(columns, rows, cell_w, cell_h, title_lines=0)
    extra = image.shape[0] - untitled - PV.PAD
    return (image.shape[1] == width and extra > 0 and extra % (PV.TITLE_SIZE + 5) == 0)


# ------------------------------------------------------------------ exposure


def test_auto_exposure_puts_the_99th_percentile_at_white():
    values = np.ones((40, 25))
    values.flat[:5] = 100.0                      # 0.5 % hot texels: the 99th percentile ignores them
    display, note, white = PV.expose(values)
    assert white == pytest.approx(1.0)
    assert "white = " in note
    assert display[20, 20, 0] == pytest.approx(1.0)      # 1 = white
    half, _, _ = PV.expose(np.full((4, 4), 0.5), white=1.0)
    # sRGB OETF of 0.5 (IEC 61966-2-1), an independent constant
    assert half[0, 0, 0] == pytest.approx(1.055 * 0.5 ** (1 / 2.4) - 0.055)


@pytest.mark.parametrize("mode", PV.MODES)
def test_exposure_survives_nan_inf_and_huge_dynamic_range(mode):
    v = np.random.default_rng(0).random((16, 16, 3))
    v[0, 0] = np.nan
    v[0, 1] = np.inf
    v[0, 2] = -np.inf
    v[1, 1] = 1e30                                # beyond any exposure: clips, does not poison it
    v[1, 2] = 1e-30
    v[2, 2] = -1e38
    with np.errstate(all="raise"):                # no overflow / invalid warnings either
        display, note, white = PV.expose(v, mode)
    assert np.isfinite(display).all() and display.min() >= 0 and display.max() <= 1
    assert math.isfinite(white) and white > 0
    assert tuple(display[0, 0]) == PV.NONFINITE and tuple(display[0, 1]) == PV.NONFINITE
    assert "3 NaN/Inf" in note
    if mode == "auto":
        assert white < 2                          # set by the bulk in [0, 1), not by 1e30


def test_exposure_of_degenerate_images():
    for values in (np.zeros((4, 4)), np.full((4, 4), np.nan), np.full((4, 4), -1.0),
                   np.zeros((0, 0))):
        display, _, white = PV.expose(values)
        assert display.shape == values.shape + (3,) and white == 1.0
    with pytest.raises(ValueError):
        PV.expose(np.zeros((4, 4, 2)))
    with pytest.raises(ValueError):
        PV.expose(np.zeros((4, 4)), "bogus")


def test_mask_greys_out_and_region_sets_the_exposure():
    v = np.full((4, 4), 0.25)
    v[:, 2:] = 50.0                               # bright outside the mask
    mask = np.zeros((4, 4))
    mask[:, :2] = 1
    display, _, white = PV.expose(v, mask=mask)
    assert white == pytest.approx(0.25)           # measured inside the mask only
    assert np.allclose(display[:, 2:], PV.OUTSIDE)
    assert np.allclose(display[:, :2], 1.0)


def test_auto_exposure_counts_negative_values():
    v = np.ones((10, 10))
    v[:3] = -0.5
    display, note, _ = PV.expose(v)
    assert "30% < 0 (black)" in note and display[:3].max() == 0


def test_large_cube_faces_are_shown_at_most_max_face():
    from relight_cli.formats.envmap import EnvMap
    n = PV.MAX_FACE + 8
    radiance, inside, _ = PV.cube_cross(EnvMap(np.ones((6 * n, n, 3), np.float32), "cube"))
    assert radiance.shape[:2] == (3 * PV.MAX_FACE, 4 * PV.MAX_FACE)


def test_fixed_ranges():
    unit, note, _ = PV.expose(np.array([[-1.0, 0.0, 0.5, 2.0]]), "unit")
    assert np.allclose(unit[0, :, 0], [0, 0, 0.5, 1]) and "0" in note
    signed, _, _ = PV.expose(np.array([[[-1.0, 0.0, 1.0]]]), "signed")
    assert np.allclose(signed[0, 0], [0, 0.5, 1])


# ------------------------------------------------------------------ sheets


def _tiles(n, h=20, w=30):
    rng = np.random.default_rng(1)
    return [PV.Tile(rng.random((h, w, 3)), f"tile {k}", f"note {k}") for k in range(n)]


def test_sheet_grid_size_and_tiles_in_place():
    tiles = _tiles(5)
    image = PV.sheet([tiles], "a title", columns=3)
    factor = math.ceil(PV.MIN_TILE / 20)            # short side 20 → ≥ 160 px
    assert image.shape[:2][::-1] == grid_size(3, 2, 30 * factor, 20 * factor)
    # the first tile, upscaled by nearest neighbour, sits under its band
    band = 2 * (PV.LABEL_SIZE + 4) + 4
    y0 = PV.PAD + PV.TITLE_SIZE + 5 + PV.PAD + band
    x0 = PV.PAD
    got = image[y0:y0 + 20 * factor, x0:x0 + 30 * factor]
    want = np.repeat(np.repeat(tiles[0].image, factor, 0), factor, 1)
    assert np.abs(got - np.rint(want * 255) / 255).max() < 1e-9


def test_labels_are_drawn():
    a = PV.sheet([[PV.Tile(np.zeros((32, 32, 3)), "diffuse", "white = 1")]])
    b = PV.sheet([[PV.Tile(np.zeros((32, 32, 3)), "phong64", "white = 7")]])
    band = slice(PV.PAD, PV.PAD + 2 * (PV.LABEL_SIZE + 4))
    assert a[band].std() > 0.05                   # text, not a flat band
    assert not np.array_equal(a[band], b[band])  # and the text differs with the label
    assert np.array_equal(a[band.stop + 8:], b[band.stop + 8:])   # tiles alike
    # symbols the built-in font lacks are spelt out, never drawn as boxes
    assert PV._printable("−1…1 × → α²") == "-1...1 x -> alpha^2"


def test_long_labels_are_cut_to_their_cell():
    text = "a very long label " * 10
    font = PV._font(PV.LABEL_SIZE)
    cut = PV._fit(text, font, 100)
    assert cut.endswith("...") and font.getlength(cut) <= 100


def test_chart_names_stay_inside_their_chart():
    """Issue 53: a chart's name was drawn at its deepest texel and could run off the
    chart ("pinky" off its chart).  A short wide chart under a tall one: the tall chart's
    deepest texel is near its top edge here (a notch), and its name's dark box lies
    inside the chart's bounds on the sheet."""
    region = np.full((40, 24), -1)
    region[2:38, 2:8] = 0                      # tall and narrow: a vertical label
    region[2:6, 2:7] = -1                      # a notch ...
    region[6:10, 2:8] = 0
    region[2:38, 10:22] = 1
    tile = PV.chart_tile(region, ["pinky", "palm"])
    x, y, name, vertical, box = tile.marks[0]
    assert name == "pinky" and vertical and box == (2.0, 2.0, 8.0, 38.0)
    image = PV.sheet([[tile]])
    k = PV.zoom(region.shape)
    band = 2 * (PV.LABEL_SIZE + 4) + 4
    left = PV.PAD + 0                          # one tile: it fills its cell
    top = PV.PAD + band
    dark = np.all(np.abs(image - 20 / 255) < 1e-6, axis=2)
    ys, xs = np.nonzero(dark[top:top + 40 * k, left:left + 8 * k + 40])
    assert len(ys) > 0
    assert ys.min() >= 2 * k and ys.max() < 38 * k and xs.min() >= 2 * k and xs.max() < 8 * k


def test_long_titles_wrap_instead_of_being_cut():
    """Issue 53: a command line with a long path was cut ("... -> /tmp/h/st...").  It
    now wraps, long words after a '/', and every character is still there."""
    font = PV._font(PV.TITLE_SIZE)
    text = "envmap ../shared/data/envmaps/polyhaven/studio_small_03_1k.hdr -> example/studio.exr"
    lines = PV._wrap(text, font, 220, PV.TITLE_LINES)
    assert len(lines) > 1 and all(font.getlength(t) <= 220 for t in lines)
    assert "".join(lines).replace(" ", "") == text.replace(" ", "")
    assert lines[1].startswith("envmaps/") or "/" in lines[0][-1:]       # broken after a '/'
    tall = PV.sheet([[PV.Tile(np.zeros((20, 20, 3)), "x")]], text)
    short = PV.sheet([[PV.Tile(np.zeros((20, 20, 3)), "x")]], "envmap")
    assert tall.shape[0] > short.shape[0] and tall.shape[1] == short.shape[1]


def test_capture_sheet_names_each_columns_pose():
    """Issue 53: the capture sheet set different poses side by side unlabelled.  Each
    column's note names its pose; the grouped column takes the fully lit frame's pose
    where a grouped frame has it; the env columns say their pose is held out."""
    from types import SimpleNamespace as NS

    from relight_cli.formats.capture import CaptureFrame
    frames = [CaptureFrame(0, 0.0, 0, "full", [0, 1, 2], ["a"]),
              CaptureFrame(1, 0.1, 1, "group", [0], ["a"]),
              CaptureFrame(2, 0.2, 0, "group", [1], ["a"])]
    renders = [{"camera": "a", "pose": 0, "env": "sky", "image": "eval/sky_a.exr"}]
    capture = NS(cameras=[NS(name="a")], frames=frames, evaluation={"renders": renders})
    cameras, columns = PV.capture_views(capture)
    assert cameras == ["a"]
    assert [(label, note) for label, note, _ in columns] == [
        ("fully lit, frame 0", "pose 0, 3 LEDs"), ("grouped, frame 2", "pose 0, 1 LEDs"),
        ("env sky", "held-out pose 0")]
    capture.frames = frames[:2]              # no grouped frame of pose 0: the first one
    assert PV.capture_views(capture)[1][1][:2] == ("grouped, frame 1", "pose 1, 1 LEDs")


def test_a_long_picture_label_moves_into_the_note_not_cut():
    """Issue 53: "wave-3_studio_small_03_1k: linear radiance" was cut to "linear radian..."
    over a 256-pixel picture.  The name stays on the label line and the rest leads the
    note, which wraps; a label that fits is left alone."""
    long = "wave-3_studio_small_03_1k: linear radiance"
    got = {}
    real = PV.sheet

    def spy(rows, *args, **kwargs):
        got["tile"] = rows[0][0]
        return real(rows, *args, **kwargs)
    import unittest.mock
    with unittest.mock.patch.object(PV, "sheet", spy):
        PV.picture(np.zeros((256, 256, 3)), long, "Reinhard, key 0.18 (scale 0.467)")
        assert got["tile"].label == "wave-3_studio_small_03_1k"
        assert got["tile"].note.startswith("linear radiance, Reinhard, key 0.18")
        PV.picture(np.zeros((256, 256, 3)), "hand: linear radiance", "x")
        assert got["tile"].label == "hand: linear radiance"


def test_png_is_byte_identical_and_has_no_time_stamp(tmp_path):
    rows = [_tiles(3)]
    PV.write_sheet(str(tmp_path / "a.png"), rows, "title")
    PV.write_sheet(str(tmp_path / "b.png"), rows, "title")
    assert (tmp_path / "a.png").read_bytes() == (tmp_path / "b.png").read_bytes()
    chunks = png_chunks(tmp_path / "a.png")
    kinds = {k for k, _ in chunks}
    assert b"tIME" not in kinds
    text = b" ".join(v for k, v in chunks if k in (b"tEXt", b"iTXt", b"zTXt"))
    assert b"date" not in text.lower() and b"time" not in text.lower()


# ------------------------------------------------------------------ cube crosses


def _smooth_env(layout="cube", n=16):
    """An env map whose radiance is its direction, (d + 1)/2: smooth everywhere."""
    from relight_cli import envmap as E
    from relight_cli.formats.envmap import EnvMap
    d = E.directions(layout, 6 * n if layout == "cube" else n, n if layout == "cube" else 2 * n)
    return EnvMap(((d + 1) / 2).astype(np.float32), layout)


@pytest.mark.parametrize("layout", ["horizontal", "vertical"])
def test_cube_cross_faces_are_where_they_belong_and_seams_are_continuous(layout):
    n = 16
    env = _smooth_env("cube", n)
    radiance, inside, corners = PV.cube_cross(env, layout=layout)
    cols, rows = PV.CROSS[layout]["cells"]
    assert radiance.shape == (rows * n, cols * n, 3) and inside.sum() == 6 * n * n
    axes = {"+X": [1, 0, 0], "-X": [-1, 0, 0], "+Y": [0, 1, 0], "-Y": [0, -1, 0],
            "+Z": [0, 0, 1], "-Z": [0, 0, -1]}
    for x, y, name in corners:
        centre = radiance[y + n // 2 - 1:y + n // 2 + 1, x + n // 2 - 1:x + n // 2 + 1]
        direction = centre.mean(axis=(0, 1)) * 2 - 1
        assert np.dot(direction / np.linalg.norm(direction), axes[name]) > 0.99, name
    # +X is left of +Z (OpenEXR's lat-long order: +X a quarter from the left, +Z central)
    cells = {name: (x // n, y // n) for x, y, name in corners}
    assert cells["+X"][0] < cells["+Z"][0] < cells["-X"][0] and cells["+Y"][1] < cells["+Z"][1]
    # every step between neighbouring pixels inside the cross, seams included, is small:
    # a face turned the wrong way would jump across its seam
    step = 2.0 / (n - 1)
    for axis in (0, 1):
        both = inside & np.roll(inside, -1, axis=axis)
        if axis == 0:
            both[-1] = False
        else:
            both[:, -1] = False
        jump = np.abs(radiance - np.roll(radiance, -1, axis=axis)).max(axis=-1)[both]
        assert jump.max() < 1.5 * step, (layout, axis)


def test_cross_of_a_cube_map_shows_its_own_texels():
    from relight_cli import envmap as E
    from relight_cli.formats.envmap import EnvMap
    n = 8
    rng = np.random.default_rng(2)
    env = EnvMap(rng.random((6 * n, n, 3)).astype(np.float32), "cube")
    radiance, inside, _ = PV.cube_cross(env)
    # each face pixel is a texel of that face (face pixel centres span the face edge to edge)
    face_values = {tuple(v) for v in env.radiance.reshape(-1, 3).astype(np.float64)}
    assert all(tuple(v) in face_values for v in radiance[inside])
    assert E.FACES == ("+X", "-X", "+Y", "-Y", "+Z", "-Z")


# ------------------------------------------------------------------ SH probes


def test_probe_latlong_against_the_closed_form_of_degree_one():
    from relight_cli import envmap as E
    c = np.zeros((4, 3))
    c[0] = 1.0                     # Y_0^0 = 1/(2√π)
    c[2, 1] = 1.0                  # Y_1^0 = √(3/4π)·z, green only
    image = PV.probe_latlong(c, 16)
    d = E.latlong_directions(16, 32)
    assert image.shape == (16, 32, 3)
    assert np.allclose(image[..., 0], 0.5 / math.sqrt(math.pi))
    assert np.allclose(image[..., 1], 0.5 / math.sqrt(math.pi) + math.sqrt(3 / (4 * math.pi))
                       * d[..., 2])


def test_probe_sheet_has_source_and_probe_rows():
    from relight_cli.builtin_envs import builtin_envmap
    from relight_cli.gaussians import probe as P
    env = builtin_envmap("builtin:studio")
    c = P.fit_probe(P.env_samples(env), 2)
    image = PV.probe_sheet(c, 2, "builtin:studio", env, height=32)
    cell = 64 * math.ceil(PV.MIN_TILE / 32)
    # the title ("sh-probe of scene.ply at (0, 1, 0): lat-long maps, ...") is wider
    # than the one-column sheet: it wraps there onto two lines
    assert image.shape[:2][::-1] == grid_size(2, 2, cell, cell // 2, title_lines=1)
    alone = PV.probe_sheet(c, 2, "scene.ply", None, position=(0, 1, 0), height=32)
    assert alone.shape[:2][::-1] == grid_size(1, 2, cell, cell // 2, title_lines=2)


def test_negative_reconstruction_is_marked_not_black():
    """Issue 53: a probe's negative lobes were drawn black, like a dark part of the scene.
    mark_negative draws them as green stripes (black between), brighter where deeper, and
    leaves every pixel ≥ 0 as exposed; the note gives the share and the deepest dip."""
    values = np.zeros((8, 8, 3))
    values[:, :4] = 0.5                                  # left half lit
    values[:, 4:6] = -0.1                                # a shallow dip
    values[:, 6:] = -2.0                                 # a dip deeper than white
    display, note, white = PV.expose(np.maximum(values, 0), white=1.0)
    marked, note = PV.mark_negative(display, values, white, mean=np.full(3, 0.25))
    np.testing.assert_array_equal(marked[:, :4], display[:, :4])
    stripes = marked[:, 4:].reshape(-1, 3)
    green = stripes[stripes.any(axis=1)]
    assert 0.3 * len(stripes) <= len(green) <= 0.7 * len(stripes)          # striped, not filled
    np.testing.assert_allclose(green / np.linalg.norm(green, axis=1, keepdims=True),
                               np.tile(PV.NEGATIVE / np.linalg.norm(PV.NEGATIVE), (len(green), 1)))
    assert marked[:, 6:].max() > marked[:, 4:6].max()                        # deeper is brighter
    assert note == "green stripes: < 0 on 50%, to -8.00x mean"
    assert PV.mark_negative(display, np.abs(values), white) == (display, "")


def test_probe_sheet_marks_the_ringing_of_a_sun():
    """builtin:sky at degree 2 rings below zero over ~half the sphere: the probe's radiance
    tile shows green stripes and says so, the source's tile none."""
    from relight_cli.builtin_envs import builtin_envmap
    from relight_cli.gaussians import probe as P
    env = builtin_envmap("builtin:sky")
    c = P.fit_probe(P.env_samples(env), 2)
    image = PV.probe_sheet(c, 2, "builtin:sky", env, height=32)
    half = image.shape[1] // 2
    green = (image[..., 1] > 0.5) & (image[..., 0] < 0.25) & (image[..., 2] < 0.45)
    assert green[:, half:].mean() > 0.05 and not green[:, :half].any()


# ------------------------------------------------------------------ commands


SMALL = ["--res", "16", "--env-res", "8x4"]


def test_bake_features_contact_sheet(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)               # short paths: a one-line title
    png = tmp_path / "f.png"
    r = invoke("bake-features", "builtin:right", "builtin:sky", *SMALL, "--specular", "both",
               "-o", "f.exr", "--preview", "f.png", "-q")
    assert r.exit_code == 0, r.output
    image = read_png(png)
    # 7 layers (diffuse, phong16/32/64, ggx, visibility, mask) + the UV charts on 4 + 4 tiles,
    # 16 px → 128 px; the title (command, frame, env, view) wraps onto two lines
    assert image.shape[:2][::-1] == grid_size(4, 2, 128, 128, title_lines=2)
    # every layer's band carries text
    band = 2 * (PV.LABEL_SIZE + 4)
    y0 = PV.PAD + 2 * (PV.TITLE_SIZE + 5) + PV.PAD
    for row in range(2):
        for col in range(4 if row == 0 else 3):
            x0 = PV.PAD + col * (128 + PV.PAD)
            y = y0 + row * (band + 4 + 128 + PV.PAD)
            assert image[y:y + band, x0:x0 + 128].std() > 10, (row, col)


def test_bake_features_two_hands_get_a_row_each(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)               # short paths: a one-line title
    png = tmp_path / "f.png"
    r = invoke("bake-features", "builtin:two:fist", "builtin:sky", *SMALL,
               "-o", "f.exr", "--preview", "f.png", "-q")
    assert r.exit_code == 0, r.output
    # per hand: diffuse, phong16/32/64, visibility, mask, charts → 7 tiles, 4 a line, 2 lines each
    assert read_png(png).shape[:2][::-1] == grid_size(4, 4, 128, 128, title_lines=2)


def test_envmap_cube_preview_is_a_cross(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)               # short paths: a one-line title
    png = tmp_path / "c.png"
    r = invoke("envmap", "builtin:studio", "--to", "cube", "--size", "16", "-o",
               "c.exr", "--preview", "c.png", "-q")
    assert r.exit_code == 0, r.output
    factor = math.ceil(PV.MIN_TILE / 2 / 16)            # faces of 16 px → 80 px
    cross = (3 * 16 * factor, 4 * 16 * factor)
    # the cross tile is upscaled again to a short side of at least MIN_TILE
    tile = math.ceil(PV.MIN_TILE / cross[0])
    assert read_png(png).shape[:2][::-1] == grid_size(1, 1, cross[1] * tile, cross[0] * tile)


def test_sh_probe_preview(tmp_path):
    png = tmp_path / "p.png"
    r = invoke("sh-probe", "builtin:sky", "--degree", "2", "-o", tmp_path / "p.json",
               "--preview", png, "-q")
    assert r.exit_code == 0, r.output
    assert read_png(png).shape[:2][::-1] == grid_size(2, 2, 512, 256)   # 256×128, ×2
    assert json.loads((tmp_path / "p.json").read_text())["degree"] == 2


def test_sh_probe_preview_of_a_scene_shows_its_cube_faces(small_scene, tmp_path):
    png = tmp_path / "p.png"
    r = invoke("sh-probe", small_scene / "floor.ply", "--at", "0,0.3,0", "--face-size", "8",
               "--degree", "1", "-o", tmp_path / "p.json", "--preview", png, "-q")
    assert r.exit_code == 0, r.output
    image = read_png(png)
    assert image.shape[:2][::-1] == grid_size(2, 2, 512, 256)
    # the source tile: the floor below (bottom half) is lit, the empty sky above is black
    y0 = PV.PAD + PV.TITLE_SIZE + 5 + PV.PAD + 2 * (PV.LABEL_SIZE + 4) + 4
    source = image[y0:y0 + 256, PV.PAD:PV.PAD + 512]
    assert source[200:].mean() > 50 and source[:40].mean() < 5


@pytest.fixture(scope="module")
def small_scene(tmp_path_factory):
    import trimesh

    from relight_cli.formats.gaussians_ply import write_gaussians
    from relight_cli.gaussians.from_mesh import gaussians_from_mesh
    folder = tmp_path_factory.mktemp("scene")
    ball = trimesh.creation.icosphere(subdivisions=1, radius=0.1)
    write_gaussians(str(folder / "ball.ply"),
                    gaussians_from_mesh(ball.vertices + [0, 0.25, 0], ball.faces))
    floor = trimesh.creation.box((1.0, 0.02, 1.0)).subdivide().subdivide()
    write_gaussians(str(folder / "floor.ply"), gaussians_from_mesh(floor.vertices, floor.faces))
    (folder / "lights.json").write_text(json.dumps(
        {"format": "relight/lights", "version": 1, "lights": [{"position": [0.2, 1.0, 0.1]}]}))
    return folder


def test_dgsm_build_preview_shows_the_shadow(small_scene, tmp_path):
    d = small_scene
    png = tmp_path / "s.png"
    r = invoke("dgsm-build", d / "ball.ply", "--receivers", d / "floor.ply", "--lights",
               d / "lights.json", "--size", "32", "--bins", "8", "-o", tmp_path / "s.exr",
               "--preview", png, "-q")
    assert r.exit_code == 0, r.output
    image = read_png(png)
    assert image.shape[:2][::-1] == grid_size(3, 1, 320, 240, title_lines=3)
    # the matte (second tile) holds a shadow: some receivers are bright
    y0 = PV.PAD + 3 * (PV.TITLE_SIZE + 5) + PV.PAD + 2 * (PV.LABEL_SIZE + 4) + 4
    matte = image[y0:y0 + 240, PV.PAD + 320 + PV.PAD:PV.PAD + 2 * 320 + PV.PAD]
    assert matte.max() > 128 and np.median(matte) < 20
    # a given camera is used as given
    from relight_cli.formats.camera import Camera, write_cameras
    write_cameras(str(tmp_path / "cam.json"),
                  [Camera.look_at([0.6, 0.6, 0.6], [0, 0, 0], width=64, height=48)])
    png2 = tmp_path / "s2.png"
    r = invoke("dgsm-build", d / "ball.ply", "--receivers", d / "floor.ply", "--lights",
               d / "lights.json", "--size", "32", "--bins", "8", "-o", tmp_path / "s2.exr",
               "--preview", png2, "--preview-camera", tmp_path / "cam.json", "-q")
    assert r.exit_code == 0, r.output
    cell = 48 * math.ceil(PV.MIN_TILE / 48)
    assert read_png(png2).shape[1] == grid_size(3, 1, 64 * cell // 48, cell)[0]


def test_dgsm_build_preview_without_receivers_shows_the_atlas(small_scene, tmp_path):
    d = small_scene
    png = tmp_path / "s.png"
    r = invoke("dgsm-build", d / "ball.ply", "--t-max", "2", "--lights", d / "lights.json",
               "--size", "16", "--bins", "4", "--no-roi", "-o", tmp_path / "s.exr",
               "--preview", png, "-q")
    assert r.exit_code == 0, r.output
    assert on_grid(read_png(png), 1, 1, 128, 128)                   # 16 px, ×8 at most


def test_synth_capture_contact_sheet(tmp_path):
    png = tmp_path / "cap.png"
    args = ["synth-capture", "-o", tmp_path / "cap", "--cameras", "3", "--leds", "4",
            "--group", "2", "--n-frames", "2", "--size", "16", "--tex-res", "16", "--aa", "1",
            "--eval-poses", "1", "--eval-cameras", "1", "--eval-envs", "builtin:sky", "-q",
            "--preview", png]
    r = invoke(*args)
    assert r.exit_code == 0, r.output
    image = read_png(png)
    # 3 cameras × (fully lit, grouped, env sky); 16 px → 128 px
    assert on_grid(image, 3, 3, 128, 128)
    first = image.tobytes()
    png.unlink()
    r = invoke(*args)                       # resumed: nothing rendered, the same sheet
    assert r.exit_code == 0, r.output
    assert read_png(png).tobytes() == first


@pytest.mark.parametrize("args", [
    ["envmap", "builtin:sky", "-o", "{t}/e.exr", "--preview", "{t}/e.jpg"],
    ["bake-features", "builtin:right", "builtin:sky", "-o", "{t}/f.exr", "--preview", "{t}/f.jpg"],
    ["sh-probe", "builtin:sky", "-o", "{t}/p.json", "--preview", "{t}/p.PNG.txt"],
    ["dgsm-build", "builtin:sphere", "--t-max", "1", "--lights", "{d}/lights.json",
     "-o", "{t}/s.exr", "--preview", "{t}/s.tif"],
    ["synth-capture", "-o", "{t}/cap", "--preview", "{t}/cap"],
    ["fit-geometry", "-o", "{t}/h.npz", "--preview", "{t}/h.jpeg"],
    ["relight", "builtin:right", "builtin:sky", "-o", "{t}/r.exr", "--preview", "{t}/r.jpg"],
    ["dgsm-build", "builtin:sphere", "--t-max", "1", "--lights", "{d}/lights.json",
     "-o", "{t}/s.exr", "--preview-camera", "{d}/lights.json"],
], ids=lambda a: a[0] + (" --preview-camera" if "--preview-camera" in a else ""))
def test_preview_must_be_a_png(small_scene, tmp_path, args):
    argv = [a.format(t=tmp_path, d=small_scene) for a in args]
    r = invoke(*argv)
    assert r.exit_code == 2
    line = r.output.strip()
    assert "\n" not in line and ("name it .png" in line or "needs --preview" in line), line
    assert list(tmp_path.iterdir()) == []


@pytest.fixture
def drawn(monkeypatch):
    """Every text the previews draw (PIL ImageDraw.text and the chart marks)."""
    from PIL import ImageDraw
    texts = []
    text = ImageDraw.ImageDraw.text

    def spy(self, xy, t, *args, **kwargs):
        texts.append(t)
        return text(self, xy, t, *args, **kwargs)
    monkeypatch.setattr(ImageDraw.ImageDraw, "text", spy)
    return texts


def _read(path) -> np.ndarray:
    from relight_cli.formats.image import read_image
    pixels, _ = read_image(str(path))
    return pixels


def test_a_tiny_render_is_enlarged_and_captioned(tmp_path, drawn):
    from relight_cli.preview import write_preview
    rng = np.random.default_rng(0)
    radiance = rng.random((6, 9, 3)).astype(np.float32) * 4
    write_preview(str(tmp_path / "tiny.png"), radiance)
    png = _read(tmp_path / "tiny.png")
    x0, y0, k = PV.picture_box(png.shape, 6, 9)
    assert k * 6 >= PV.MIN_PICTURE and min(png.shape[:2]) >= PV.MIN_PICTURE
    # the picture is the data, enlarged by nearest neighbour (one grey level: 8 bits)
    shown = png[y0:y0 + 6 * k, x0:x0 + 9 * k]
    assert shown.shape[:2] == (6 * k, 9 * k)
    assert np.array_equal(shown, np.repeat(np.repeat(shown[::k, ::k], k, 0), k, 1))
    # the caption strip above it carries text (rows not uniform) ...
    strip = png[PV.PAD:y0 - 2, x0:x0 + 9 * k]
    assert strip.std() > 0.05 and (strip.max(-1) > 0.6).any()
    # ... naming the file, the quantity and the tone mapping with its scale
    caption = " ".join(drawn)
    assert "tiny: linear radiance" in caption
    assert f"Reinhard, key 0.18 (scale {PV.reinhard_scale(radiance):.3g})" in caption
    assert f"9x6 px shown {k}x (nearest)" in caption


def test_the_caption_says_what_the_caller_names():
    a = PV.render_picture(np.ones((20, 30, 3)), "view: relit room", exposure=2.0)
    b = PV.render_picture(np.ones((20, 30, 3)), "matte: something else", exposure=2.0)
    assert a.shape == b.shape
    x0, y0, k = PV.picture_box(a.shape, 20, 30)
    assert not np.array_equal(a[:y0], b[:y0]) and np.array_equal(a[y0:], b[y0:])
    # a picture already large enough is not enlarged
    big = PV.picture(np.zeros((300, 400, 3)), "big")
    assert PV.picture_box(big.shape, 300, 400)[2] == 1 and big.shape[1] == 400 + 2 * PV.PAD


def test_envmap_latlong_preview_is_readable(tmp_path, drawn):
    png = tmp_path / "sky.png"
    r = CliRunner().invoke(cli, ["envmap", "builtin:sky", "--to", "latlong", "--size", "32x16",
                                 "-o", str(tmp_path / "sky.exr"), "--preview", str(png), "-q"],
                           catch_exceptions=False)
    assert r.exit_code == 0, r.output
    image = _read(png)
    x0, y0, k = PV.picture_box(image.shape, 16, 32)
    assert k == 16 and image.shape[1] == 32 * 16 + 2 * PV.PAD
    caption = " ".join(drawn)
    assert "lat-long map 32x16" in caption and "Reinhard" in caption


def _rest_hand():
    from relight_cli.hand.model import builtin_hand
    return builtin_hand("right", pose=None)


def test_uv_charts_name_palm_back_and_each_finger_where_they_are():
    """Checked against the rest pose's geometry, not the naming rule: the palm faces
    +Z, the back −Z, the fingers lie along +Y beyond the palm, thumb at +X and
    index … pinky from +X to −X (relight_cli.hand.model's rest pose)."""
    from relight_cli.uvraster import rasterize_uv
    hand = _rest_hand()
    mesh = hand.coarse
    region, names = PV.uv_charts(mesh, hand.label_names, hand.joint_names, (48, 48))
    assert sorted(names) == sorted(["palm", "back", *PV.FINGER_NAMES])
    raster = rasterize_uv(mesh.uv, mesh.faces_uv, (48, 48))
    assert np.array_equal(region >= 0, raster.face >= 0)       # exactly the feature charts
    tri = mesh.vertices[mesh.faces]
    centre = tri.mean(axis=1)
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    where = {n: raster.face[region == k] for k, n in enumerate(names)}
    mean = {n: centre[f].mean(axis=0) for n, f in where.items()}
    facing = {n: normal[f].sum(axis=0) / np.linalg.norm(normal[f], axis=1).sum()
              for n, f in where.items()}
    assert facing["palm"][2] > 0.5 and facing["back"][2] < -0.5
    for finger in ("index", "middle", "ring", "pinky"):
        assert mean[finger][1] > mean["palm"][1] + 0.04, finger
    assert mean["thumb"][0] > mean["index"][0] > mean["middle"][0] > mean["ring"][0] \
        > mean["pinky"][0]


def test_a_hand_without_region_labels_gets_palm_and_back_as_one_chart():
    from dataclasses import replace
    hand = _rest_hand()
    _, names = PV.uv_charts(replace(hand.coarse, labels=None), [], hand.joint_names, (16, 16))
    assert sorted(names) == sorted(["palm + back", *PV.FINGER_NAMES])


def test_feature_sheet_draws_the_chart_names(monkeypatch):
    hand = _rest_hand()
    charts = PV.uv_charts(hand.coarse, hand.label_names, hand.joint_names, (16, 16))
    marks = []
    draw = PV._draw_mark
    monkeypatch.setattr(PV, "_draw_mark", lambda canvas, x, y, text, vertical, font, box: (
        marks.append((x, y, text)), draw(canvas, x, y, text, vertical, font, box)))
    layers = {"diffuse": np.ones((16, 16, 3)), "mask": (charts[0] >= 0).astype(float)}
    image = PV.feature_sheet(layers, "t", charts=charts)
    assert sorted(m[2] for m in marks) == sorted(charts[1])
    # the names sit inside the charts tile (the third, last in the row)
    band = 2 * (PV.LABEL_SIZE + 4) + 4
    x_tile = PV.PAD + 2 * (128 + PV.PAD)
    y_tile = PV.PAD + PV.TITLE_SIZE + 5 + PV.PAD + band
    assert image.shape[1] == PV.PAD + 3 * (128 + PV.PAD)
    for x, y, _ in marks:
        assert x_tile <= x <= x_tile + 128 and y_tile <= y <= y_tile + 128
