"""README "Use from Python": its three examples run as written, through relight_cli.jobs,
and give what their comments say (shapes, a trained teacher's scores, a render of the hand)."""

from __future__ import annotations

import os
import re

import numpy as np
import pytest

from conftest import ROOT
from models import JOBS_CAPTURE, copy_entry

pytest.importorskip("torch")

CAPTURE_ARGS = JOBS_CAPTURE     # made once per run (tests/models.py)


def readme_python_blocks() -> list:
    text = (ROOT / "README.md").read_text()
    section = text.split("## Use from Python", 1)[1].split("\n## ", 1)[0]
    return re.findall(r"```python\n(.*?)```", section, flags=re.S)


def test_the_readme_python_examples_run_as_written(tmp_path, tiny_models, monkeypatch):
    blocks = readme_python_blocks()
    assert len(blocks) == 3
    copy_entry(tiny_models.get("capture", CAPTURE_ARGS), tmp_path / "capture")
    monkeypatch.chdir(tmp_path)
    scope = {}
    for block in blocks:
        exec(compile(block, "README.md", "exec"), scope)
    assert scope["diffuse"].shape == (64, 64, 3) and scope["diffuse"].dtype == np.float32
    assert np.isfinite(scope["diffuse"]).all() and scope["diffuse"].max() > 0
    heldout = scope["heldout"]
    assert np.isfinite(heldout["psnr"]) and heldout["ceiling"]["psnr"] > heldout["psnr"]
    assert scope["checkpoint"]["kind"] == "teacher" and scope["checkpoint"]["step"] == 20
    image, alpha = scope["image"], scope["alpha"]
    assert image.shape == (128, 128, 3) and alpha.shape == (128, 128)
    inside = alpha > 0.5
    assert 0.02 < inside.mean() < 0.9                   # the hand is in the frame
    assert image[inside].mean() > 0 and np.isfinite(image).all()
    assert os.listdir(tmp_path) == ["capture"]          # the jobs wrote nothing
