"""Every preview is readable (issue 24): a tiny picture is enlarged to at least
``MIN_PICTURE`` pixels on its short side (integer factor, nearest), under a caption
strip that names what it shows and its tone mapping; bake-features' sheets name the
UV charts (palm, back, each finger).  formats/preview.md states the rule."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from relight_cli import preview as PV
from relight_cli.cli import cli


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
    monkeypatch.setattr(PV, "_draw_mark", lambda canvas, x, y, text, vertical, font: (
        marks.append((x, y, text)), draw(canvas, x, y, text, vertical, font)))
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
