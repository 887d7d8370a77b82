"""The relight/features EXR and relight/vertex-features npz: round trips and rejections."""

from __future__ import annotations

import numpy as np
import pytest

from relight_cli.errors import DataError
from relight_cli.formats.exr import write_exr
from relight_cli.formats.features_exr import (FORMAT, VERTEX_FORMAT, read_features,
                                              read_vertex_features, write_features,
                                              write_vertex_features)
from relight_cli.provenance import provenance


def _layers(prefix=""):
    rng = np.random.default_rng(0)
    return {prefix + "diffuse": rng.random((4, 5, 3)) * 1e6,       # beyond half's range
            prefix + "phong16": rng.random((4, 5, 3)),
            prefix + "phong2.5": rng.random((4, 5, 3)),
            prefix + "visibility": rng.random((4, 5)),
            prefix + "mask": (rng.random((4, 5)) > 0.5).astype(float)}


def test_round_trip_single_and_two_hands(tmp_path):
    for prefixes in ([""], ["left.", "right."]):
        layers = {}
        for p in prefixes:
            layers.update(_layers(p))
        path = tmp_path / "f.exr"
        write_features(str(path), layers, {"relight.frame": 3}, provenance(FORMAT, 1))
        back = read_features(str(path))
        assert set(back.layers) == set(layers)
        for k, v in layers.items():
            np.testing.assert_array_equal(back.layers[k], v.astype(np.float32))
        assert back.attributes["relight.frame"] == 3
        assert back.hands == sorted(p.rstrip(".") for p in prefixes)


def test_rejects_newer_version_and_wrong_format(tmp_path):
    path = tmp_path / "f.exr"
    write_features(str(path), _layers(), provenance=provenance(FORMAT, 2))
    with pytest.raises(DataError, match="version 2.*f.exr"):
        read_features(str(path))
    write_features(str(path), _layers(), provenance=provenance("relight/other", 1))
    with pytest.raises(DataError, match="not a relight/features"):
        read_features(str(path))


@pytest.mark.parametrize("mutate, message", [
    (lambda c: c.pop("mask.Y"), "missing mask"),
    (lambda c: c.pop("diffuse.G"), "channels R, G, B"),
    (lambda c: c.update({"bogus.R": c["diffuse.R"], "bogus.G": c["diffuse.R"],
                         "bogus.B": c["diffuse.R"]}), "unknown feature layer"),
    (lambda c: c["visibility.Y"].__setitem__((0, 0), np.nan), "NaN"),
])
def test_rejects_damaged_content(tmp_path, mutate, message):
    channels = {}
    for name, v in _layers().items():
        if v.ndim == 3:
            for i, c in enumerate("RGB"):
                channels[f"{name}.{c}"] = v[..., i].astype(np.float32)
        else:
            channels[f"{name}.Y"] = v.astype(np.float32)
    mutate(channels)
    path = tmp_path / "bad.exr"
    write_exr(str(path), channels, provenance=provenance(FORMAT, 1))
    with pytest.raises(DataError, match=message):
        read_features(str(path))


def test_vertex_npz_round_trip_and_rejection(tmp_path):
    path = tmp_path / "v.npz"
    arrays = {"vertices": np.random.rand(5, 3), "faces": np.array([[0, 1, 2]]),
              "diffuse": np.random.rand(5, 3), "visibility": np.random.rand(5)}
    write_vertex_features(str(path), arrays, provenance(VERTEX_FORMAT, 1))
    back = read_vertex_features(str(path))
    np.testing.assert_array_equal(back["vertices"], arrays["vertices"])   # float64 kept
    np.testing.assert_allclose(back["diffuse"], arrays["diffuse"], rtol=1e-7)
    np.savez(tmp_path / "other.npz", format=np.array("x"), version=np.array(1))
    with pytest.raises(DataError, match="other.npz"):
        read_vertex_features(str(tmp_path / "other.npz"))
    (tmp_path / "junk.npz").write_bytes(b"junk")
    with pytest.raises(DataError, match="junk.npz"):
        read_vertex_features(str(tmp_path / "junk.npz"))
