"""formats/exr.py: named channels and attributes, the format check, half-float clamping."""

from __future__ import annotations

import numpy as np
import pytest

from relight_cli.errors import DataError
from relight_cli.formats.exr import check_format, read_exr, write_exr
from relight_cli.provenance import provenance


def test_exr_named_channels_attributes_and_format_check(tmp_path):
    path = tmp_path / "x.exr"
    rng = np.random.default_rng(3)
    chans = {"diffuse.R": rng.random((5, 7)), "diffuse.G": rng.random((5, 7)),
             "diffuse.B": rng.random((5, 7)), "mask.Y": np.ones((5, 7))}
    prov = provenance("relight/test", 2, settings={"k": 1})
    write_exr(str(path), chans, attributes={"relight.shininess": [16, 32], "relight.note": "hi"},
              provenance=prov)
    img = read_exr(str(path))
    np.testing.assert_array_equal(img.layer("diffuse"), np.stack(
        [chans[f"diffuse.{c}"].astype(np.float32) for c in "RGB"], -1))
    assert img.attributes["relight.shininess"] == [16.0, 32.0]
    assert img.provenance()["settings"] == {"k": 1}
    assert check_format(img, "relight/test", 2) == 2
    with pytest.raises(DataError, match="newer"):
        check_format(img, "relight/test", 1)
    with pytest.raises(DataError, match="not a relight/other"):
        check_format(img, "relight/other", 1)
    with pytest.raises(DataError, match="missing channel"):
        img.layer("specular")


def test_half_exr_clamps_instead_of_overflowing(tmp_path):
    path = tmp_path / "h.exr"
    write_exr(str(path), {"Y": np.array([[1e6, 1.0]])}, half=True)
    y = read_exr(str(path)).channels["Y"]
    assert np.isfinite(y).all() and y[0, 0] == 65504.0
