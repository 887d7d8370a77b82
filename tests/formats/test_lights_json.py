"""The one light record (formats/lights_json.py): what the renderers shade with (radiant
intensity), subsets, the RGB/scalar constructor, and a file round trip."""

from __future__ import annotations

import json

import numpy as np
import pytest

from relight_cli.errors import DataError

from relight_cli.formats.lights_json import Lights, read_lights, write_lights


def test_radiant_intensity_is_colour_times_intensity():
    lights = Lights([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]], [[1.0, 0.9, 0.8], [0.2, 0.4, 1.0]],
                    [0.6, 1.5])
    rad = lights.radiant_intensity()
    assert rad.dtype == np.float64 and rad.shape == (2, 3)
    np.testing.assert_array_equal(rad, lights.colors * lights.intensities[:, None])
    np.testing.assert_array_equal(Lights([[0.0, 0.0, 0.0]]).radiant_intensity(), [[1.0, 1.0, 1.0]])


def test_from_radiant_intensity_gives_it_back_exactly():
    pos = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    rgb = np.array([[0.1, 0.2, 0.3], [1e-300, 7.0, 1.0 / 3.0], [4 * np.pi / 7, 0.0, 2.5]])
    lights = Lights.from_radiant_intensity(pos, rgb)
    np.testing.assert_array_equal(lights.radiant_intensity(), rgb)       # bit-exact: I·1.0
    rgb[0, 0] = 99.0                                                       # copied, not aliased
    assert lights.colors[0, 0] == 0.1
    # a scalar or one value per light: white lights of that intensity
    white = Lights.from_radiant_intensity(pos, 0.7)
    np.testing.assert_array_equal(white.radiant_intensity(), np.full((3, 3), 0.7))
    np.testing.assert_array_equal(white.colors, np.ones((3, 3)))
    per = Lights.from_radiant_intensity(pos, [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(per.radiant_intensity(), [[1.0] * 3, [2.0] * 3, [3.0] * 3])
    one = Lights.from_radiant_intensity([[0.0, 0.0, 0.1]], [0.5, 0.25, 1.0])   # L = 1: RGB
    np.testing.assert_array_equal(one.radiant_intensity(), [[0.5, 0.25, 1.0]])


def test_subset_keeps_the_lights_chosen():
    lights = Lights([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]],
                    [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], [1.0, 2.0, 3.0],
                    ["a", "b", "c"], {"note": 1}, {"tool": "x"})
    sub = lights.subset([2, 0])
    assert isinstance(sub, Lights) and len(sub) == 2
    np.testing.assert_array_equal(sub.positions, lights.positions[[2, 0]])
    np.testing.assert_array_equal(sub.radiant_intensity(), lights.radiant_intensity()[[2, 0]])
    assert sub.names == ["c", "a"] and sub.extra == {"note": 1} and sub.provenance is None
    assert len(lights.subset([])) == 0


def test_round_trip(tmp_path):
    lights = Lights([[0.3, 0.5, 0.6]], [[1.0, 0.9, 0.8]], [0.6], ["key"], {"estimator": "e"})
    path = str(tmp_path / "lights.json")
    write_lights(path, lights)
    back = read_lights(path)
    np.testing.assert_array_equal(back.radiant_intensity(), lights.radiant_intensity())
    assert back.names == ["key"] and back.extra == {"estimator": "e"}


@pytest.mark.parametrize("value", [[1], [1.0, 1.0, 1.0], [], "1", True, {"v": 1}])
def test_intensity_must_be_one_number(tmp_path, value):
    """``intensity`` is a number ≥ 0 (formats/lights_json.md); a one-element list, an RGB
    triple (that is ``color``'s job), a string or a bool is one line naming the file and
    the field, not silently unwrapped."""
    path = tmp_path / "lights.json"
    path.write_text(json.dumps({"format": "relight/lights", "version": 1, "lights": [
        {"position": [0, 1, 0]}, {"position": [0, 2, 0], "intensity": value}]}))
    with pytest.raises(DataError) as info:
        read_lights(str(path))
    text = str(info.value)
    assert "lights[1].intensity" in text and str(path) in text and "\n" not in text

