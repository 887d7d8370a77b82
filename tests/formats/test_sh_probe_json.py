"""The relight/sh-probe JSON format (formats/sh_probe_json.py): round trip and rejections."""

from __future__ import annotations

import json

import numpy as np
import pytest

from relight_cli.errors import DataError
from relight_cli.formats.sh_probe_json import ShProbe, read_probe, write_probe


def known_coefficients(degree, seed=0):
    rng = np.random.default_rng(seed)
    c = rng.normal(size=((degree + 1) ** 2, 3)) * 0.3
    c[0] = 3.0                                      # keeps radiance positive
    return c


# ------------------------------------------------------------------ format


def test_probe_json_round_trip(tmp_path):
    c = known_coefficients(2)
    p = ShProbe(c, 2, 0.1, "builtin:sky", np.array([0.0, 1.0, 2.0]), {"face_size": 8},
                {"format": "relight/sh-probe", "version": 1})
    path = tmp_path / "p.json"
    write_probe(str(path), p)
    q = read_probe(str(path))
    np.testing.assert_array_equal(q.coefficients, c)     # repr floats round-trip exactly
    assert (q.degree, q.ridge, q.source, q.extra) == (2, 0.1, "builtin:sky", {"face_size": 8})
    np.testing.assert_array_equal(q.position, [0.0, 1.0, 2.0])


@pytest.mark.parametrize("patch, message", [
    ({"version": 2}, "version 2 is newer"),
    ({"format": "relight/lights"}, "not a relight/sh-probe file"),
    ({"degree": 3}, "must be 16 rows of 3 for degree 3"),
    ({"coefficients": [[1, 2]] * 9}, "must be 9 rows of 3"),
    ({"coefficients": [[float("nan"), 0, 0]] + [[0, 0, 0]] * 8}, "NaN/Inf"),
    ({"degree": "two"}, "'degree' must be an integer"),
    ({"ridge": -1}, "'ridge' must be"),
])
def test_probe_json_bad(tmp_path, patch, message):
    obj = {"format": "relight/sh-probe", "version": 1, "degree": 2,
           "coefficients": [[0.0, 0.0, 0.0]] * 9, "ridge": 0.0}
    obj.update(patch)
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(obj))
    with pytest.raises(DataError) as exc:
        read_probe(str(path))
    assert message in str(exc.value) and str(path) in str(exc.value)
