"""The quality gate: a small deterministic pipeline on built-in data, its metrics, and a
comparison with the checked-in baseline ``tests/baseline/quality.json``.

A change that silently degrades quality makes ``relight metrics compare`` exit 3
and this test fail.  To accept a deliberate change of the numbers, regenerate
the baseline on purpose and commit it with the change that explains it::

    RELIGHT_REGEN_BASELINE=1 .venv/bin/python -m pytest tests/system/test_quality_gate.py

Adding a pipeline stage is one entry in :data:`STAGES`: a name, a function
that runs the stage through the installed ``relight`` command and returns the
path of a ``relight/metrics`` JSON, and optional per-metric tolerances.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import pytest

from conftest import run_relight

BASELINE = Path(__file__).resolve().parents[1] / "baseline" / "quality.json"
REGEN = os.environ.get("RELIGHT_REGEN_BASELINE") == "1"
# The pipeline is deterministic, so the same machine reproduces the numbers to the
# last bit; the slack only absorbs BLAS/libm differences between platforms.
DEFAULT_RTOL = 1e-4


def _ok(result):
    assert result.returncode == 0, result.stderr
    return result


@dataclass
class Stage:
    name: str
    run: Callable[[Path], Path]          # workdir -> metrics JSON path
    rtol: dict[str, float] = field(default_factory=dict)   # metric (leaf or dotted) -> rtol
    atol: dict[str, float] = field(default_factory=dict)


def envmap_cube_roundtrip(work: Path) -> Path:
    """builtin:sky → cube 32 → lat-long 128×64, against the direct lat-long resampling."""
    _ok(run_relight("envmap", "builtin:sky", "--to", "cube", "--size", "32", "-o", work / "cube.exr", "-q"))
    _ok(run_relight("envmap", work / "cube.exr", "--to", "latlong", "--size", "128x64",
                    "-o", work / "back.exr", "-q"))
    _ok(run_relight("envmap", "builtin:sky", "--to", "latlong", "--size", "128x64",
                    "-o", work / "direct.exr", "-q"))
    out = work / "envmap_cube_roundtrip.json"
    _ok(run_relight("metrics", "image", work / "back.exr", work / "direct.exr", "--space", "srgb",
                    "-o", out, "-q"))
    return out


def dgsm_shadow_resolution(work: Path) -> Path:
    """The built-in hand as Gaussians over a Gaussian room, one light: the relit render
    with a 128² DGSM atlas against the same render with a 512² atlas (the reference)."""
    lights = work / "lights.json"
    lights.write_text(json.dumps({"format": "relight/lights", "version": 1, "lights": [
        {"position": [0.35, 1.3, 0.45], "color": [1.0, 0.95, 0.9], "intensity": 5.0}]}))
    from relight_cli.formats.camera import Camera, write_cameras
    write_cameras(str(work / "cam.json"), [Camera.look_at([0.45, 0.55, 0.6], [0, 0.15, 0],
                                                          width=96, height=72, fov_y_deg=45)])
    _ok(run_relight("sh-probe", "builtin:sky", "--degree", "2", "-o", work / "probe.json", "-q"))
    renders = {}
    for size in (128, 512):
        shadows = work / f"shadows{size}.exr"
        _ok(run_relight("dgsm-build", "builtin:hand", "--translate", "0,0.25,0", "--receivers",
                        "builtin:room", "--lights", lights, "--size", str(size), "--bins", "32",
                        "-o", shadows, "--occluders-out", work / "hand.ply",
                        "--receivers-out", work / "room.ply", "-q"))
        renders[size] = work / f"render{size}.exr"
        _ok(run_relight("relight", work / "hand.ply", "--probe", work / "probe.json", "--dgsm", shadows,
                        "--receivers", work / "room.ply", "--camera", work / "cam.json",
                        "-o", renders[size], "-q"))
    out = work / "dgsm_shadow_resolution.json"
    _ok(run_relight("metrics", "image", renders[128], renders[512], "--space", "srgb", "-o", out, "-q"))
    return out


def hand_render_env_resolution(work: Path) -> Path:
    """The default hand (fist) rendered with the physical model under builtin:studio:
    the default 16×32 env discretization against a 32×64 reference, foreground only."""
    _ok(run_relight("fit-geometry", "--pose", "fist", "-o", work / "hand.npz", "-q"))
    renders = {}
    for res in ("32x16", "64x32"):
        renders[res] = work / f"render_{res}.exr"
        _ok(run_relight("relight", work / "hand.npz", "builtin:studio", "--model", "physical",
                        "--size", "96x96", "--env-res", res, "-o", renders[res], "-q"))
    from relight_cli.formats.exr import read_exr
    from relight_cli.formats.image import write_png
    mask = read_exr(str(renders["64x32"])).channels["A"]
    write_png(str(work / "mask.png"), mask[..., None])
    out = work / "hand_render_env_resolution.json"
    _ok(run_relight("metrics", "image", renders["32x16"], renders["64x32"], "--mask", work / "mask.png",
                    "-o", out, "-q"))
    return out


# One entry per pipeline stage; later stages append here.
STAGES: list[Stage] = [
    Stage("envmap_cube_roundtrip", envmap_cube_roundtrip),
    Stage("dgsm_shadow_resolution", dgsm_shadow_resolution),
    Stage("hand_render_env_resolution", hand_render_env_resolution),
]


def _combined_record(parts: dict[str, dict]) -> dict:
    from relight_cli.formats.metrics_json import FORMAT, VERSION, make_record
    metrics = {name: rec["metrics"] for name, rec in parts.items()}
    settings = {name: rec.get("settings", {}) for name, rec in parts.items()}
    provenance = {"format": FORMAT, "version": VERSION, "tool": "tests/system/test_quality_gate.py",
                  "stages": list(parts)}
    return make_record("gate", metrics, {}, settings, provenance)


def test_stage_names_unique():
    names = [s.name for s in STAGES]
    assert len(names) == len(set(names))


def test_quality_gate(tmp_path):
    from relight_cli.formats.metrics_json import dumps
    parts = {}
    for stage in STAGES:
        work = tmp_path / stage.name
        work.mkdir()
        parts[stage.name] = json.loads(stage.run(work).read_text())
    new = tmp_path / "quality.json"
    new.write_text(dumps(_combined_record(parts)))
    if REGEN:
        BASELINE.write_text(new.read_text())
        pytest.skip(f"baseline regenerated on request: {BASELINE} (review and commit it)")
    if not BASELINE.exists():
        pytest.fail(f"no baseline {BASELINE}; create it with RELIGHT_REGEN_BASELINE=1")
    args = ["metrics", "compare", new, BASELINE, "--rtol", str(DEFAULT_RTOL)]
    for stage in STAGES:
        for key, value in stage.rtol.items():
            args += ["--rtol", f"{key if '.' in key else stage.name + '.' + key}={value}"]
        for key, value in stage.atol.items():
            args += ["--atol", f"{key if '.' in key else stage.name + '.' + key}={value}"]
    result = run_relight(*args)
    assert result.returncode in (0, 3), result.stderr
    assert result.returncode == 0, "quality regressed against tests/baseline/quality.json:\n" + result.stdout


def test_gate_detects_a_regression(tmp_path):
    """The gate can fail: a degraded copy of the baseline must make compare exit 3."""
    from relight_cli.formats.metrics_json import dumps, read_metrics
    if not BASELINE.exists():
        pytest.skip("no baseline yet")
    record = read_metrics(str(BASELINE))
    worse = json.loads(json.dumps(record))
    stage = STAGES[0].name
    worse["metrics"][stage]["psnr"] = record["metrics"][stage]["psnr"] - 1.0
    path = tmp_path / "worse.json"
    path.write_text(dumps(worse))
    result = run_relight("metrics", "compare", path, BASELINE, "--rtol", str(DEFAULT_RTOL))
    assert result.returncode == 3 and f"{stage}.psnr" in result.stdout
