"""The ceiling's stage shading in chunks of texels (issue 53, item 6): the same values as
one call, and progress over the texels when a sample's ceiling is long (an env render's
took minutes at 256², silent), never when quiet."""

from __future__ import annotations

import numpy as np
import pytest

from models import TEACHER_CAPTURE


@pytest.fixture(scope="module")
def data(tiny_models):
    from relight_cli.neural.data import CaptureData
    return CaptureData(str(tiny_models.get("capture", TEACHER_CAPTURE)), 32, aa=1)


def _inputs(data, item):
    if item[0] == "env":
        render = item[1]
        pose, held_out, camera = int(render["pose"]), True, render["camera"]
    else:
        pose, held_out, camera = data.frame(item[0]).pose, False, item[1]
    gbuffer = data.gbuffer(pose, data.capture.camera(camera), held_out)
    return [data.texels(pose, held_out)], gbuffer


@pytest.mark.parametrize("split", ["env", "fully_lit"])
def test_chunks_change_no_value_and_say_progress(data, split, monkeypatch, capsys):
    from relight_cli.neural.ceiling import Ceiling
    ceiling = Ceiling(data)
    item = data.splits()[split][0]
    texels, gbuffer = _inputs(data, item)
    monkeypatch.setattr(Ceiling, "CHUNK", 10 ** 9)
    whole = ceiling.predict(item, texels, gbuffer)
    n = len(texels[0].surfaces[0].points)
    assert n > 300
    monkeypatch.setattr(Ceiling, "CHUNK", 97)              # not a divisor: a short last chunk
    monkeypatch.setattr(Ceiling, "PROGRESS_SECONDS", 0.0)  # every sample counts as long
    capsys.readouterr()
    quiet = ceiling.predict(item, texels, gbuffer)         # quiet by default
    assert capsys.readouterr().err == ""
    ceiling.quiet = False
    loud = ceiling.predict(item, texels, gbuffer)
    err = capsys.readouterr().err.splitlines()
    # each texel centre is shaded on its own: chunks give the same bits
    assert np.array_equal(whole, quiet) and np.array_equal(whole, loud)
    # (the command name is the last CLI run's in this process: "relight …")
    assert err[-1].startswith("relight") and \
        err[-1].endswith(f": {n}/{n} ceiling texels (100%)"), err
