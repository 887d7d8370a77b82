"""`relight relight HAND ENV --model physical`: CLI runs, outputs, bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest

from conftest import run_relight
from relight_cli.formats.camera import Camera, write_cameras
from relight_cli.formats.exr import read_exr

FAST = ["--tex-res", "64", "--aa", "1", "--mesh", "coarse"]


@pytest.fixture
def files(tmp_path):
    write_cameras(str(tmp_path / "cam.json"),
                  [Camera.look_at([0.0, 0.06, 0.5], [0.0, 0.06, 0.0], fov_y_deg=30,
                                  width=24, height=20)])
    (tmp_path / "lights.json").write_text(json.dumps({
        "format": "relight/lights", "version": 1,
        "lights": [{"position": [0.2, 0.3, 0.4], "intensity": 0.5},
                   {"position": [-0.3, 0.1, 0.3], "color": [1.0, 0.8, 0.6]}]}))
    return tmp_path


def test_help(run_cli, tmp_path):
    """``relight relight --help`` names the modes; ``relight relight IN --help`` lists the
    options of IN's mode and only those (no table of which option applies where)."""
    r = run_cli("relight", "--help")
    assert r.exit_code == 0
    assert "relight relight IN --help" in r.output
    for mode in ("IN = CAPTURE/", "IN = AVATAR.ply", "IN = HAND.npz"):
        assert mode in r.output
    hand = run_cli("relight", "builtin:right", "--help")
    gaussians = run_cli("relight", "avatar.ply", "--help")
    capture = run_cli("relight", tmp_path, "--help")
    assert hand.exit_code == gaussians.exit_code == capture.exit_code == 0
    for flag in ("--model", "--camera", "--lights", "--env-res", "--no-sss", "--aov",
                 "--frames", "--precision"):
        assert flag in hand.output
    for flag in ("--probe", "--dgsm", "--receivers", "--footprint", "--splits"):
        assert flag not in hand.output
    for flag in ("--probe", "--dgsm", "--receivers", "--footprint", "--camera", "--frames",
                 "--lights", "--video"):   # a clip's (issue 49): its own --frames and --lights
        assert flag in gaussians.output
    for flag in ("--model", "--env-res", "--no-sss", "--splits", "--checkpoint"):
        assert flag not in gaussians.output
    for flag in ("--model", "--checkpoint", "--splits", "--eval-samples"):
        assert flag in capture.output
    for flag in ("--camera", "--lights", "--probe", "--size", "--preview"):
        assert flag not in capture.output


def test_model_help_names_every_model(run_cli):
    """``--model``'s help (issue 53): 'physical' and every learned model of the registry,
    the student included, named up front, each with the command that trains it."""
    from relight_cli.neural.registry import MODELS
    r = run_cli("relight", "builtin:right", "--help")
    assert r.exit_code == 0
    said = " ".join(r.output.split("--model NAME", 1)[1].split("--checkpoint CKPT.pt")[0].split())
    said = said.replace("train- teacher", "train-teacher")    # click wraps at the hyphen
    assert said.startswith("Appearance model: 'physical', 'teacher', 'linear' or 'student' "
                           "[default: physical].")
    assert set(MODELS) == {"teacher", "linear", "student"}
    for name, spec in MODELS.items():
        assert f"{name}: {spec.title}, from {spec.trainer}" in said
    assert "student: RelightableHands' student (or its DRAM baseline), from distill" in said


def test_env_render_with_aovs(run_cli, files):
    out, png = files / "hand.exr", files / "hand.png"
    r = run_cli("relight", "builtin:right", "builtin:sky", "--model", "physical", "--camera",
                files / "cam.json", "-o", out, "--preview", png, "--aov", "normal,uv,depth",
                *FAST, "-q")
    assert r.exit_code == 0, r.output
    image = read_exr(str(out))
    assert image.attributes["relight.format"] == "relight/render"
    assert image.width == 24 and image.height == 20
    for name in ("R", "G", "B", "A", "normal.X", "normal.Y", "normal.Z", "uv.U", "uv.V",
                 "depth.Z"):
        assert name in image.channels
    mask = image.channels["A"]
    assert 0.05 < mask.mean() < 0.95
    rgb = image.layer("")
    assert np.isfinite(rgb).all() and rgb[mask == 1].min() > 0       # sky lights every pixel
    assert (rgb[mask == 0] == 0).all()
    depth = image.channels["depth.Z"][mask == 1]
    assert 0.4 < depth.min() and depth.max() < 0.6                     # camera 0.5 m away
    assert png.exists()
    record = image.provenance()
    assert record["settings"]["model"] == "physical" and "camera" in record["inputs"]


def test_lights_render_and_ablations_differ(run_cli, files):
    base = ["relight", "builtin:right:point", "--lights", files / "lights.json", "--camera",
            files / "cam.json", *FAST, "-q"]
    outs = {}
    for name, extra in (("full", []), ("noshadow", ["--no-shadows"]),
                        ("nospec", ["--no-specular"])):
        outs[name] = files / f"{name}.exr"
        r = run_cli(*base, "-o", outs[name], *extra)
        assert r.exit_code == 0, r.output
    img = {k: read_exr(str(v)).layer("") for k, v in outs.items()}
    assert (img["noshadow"] >= img["full"] - 1e-6).all() and (img["noshadow"] > img["full"]).any()
    assert (img["nospec"] <= img["full"] + 1e-6).all() and (img["nospec"] < img["full"]).any()


def test_env_transport_options(run_cli, files):
    """Issue 50's options change what they say: under builtin:sky (a sun), per-vertex
    transport, no bright sources and the Schlick lobe each render differently from the
    defaults; the Schlick lobe is the darker (its G shadows more); the provenance records
    them."""
    base = ["relight", "builtin:right:fist", "builtin:sky", "--camera", files / "cam.json",
            "--tex-res", "64", "--aa", "1", "--no-sss", "-q"]
    outs = {}
    for name, extra in (("default", []), ("vertices", ["--env-space", "vertices"]),
                        ("nosources", ["--env-sources", "none"]),
                        ("schlick", ["--ggx-shadowing", "schlick"]),
                        ("diffuse", ["--no-specular"])):
        outs[name] = files / f"{name}.exr"
        r = run_cli(*base, "-o", outs[name], *extra)
        assert r.exit_code == 0, r.output
    img = {k: read_exr(str(v)).layer("") for k, v in outs.items()}
    mask = read_exr(str(outs["default"])).channels["A"] > 0.99
    assert mask.sum() > 20
    for name in ("vertices", "nosources", "schlick"):
        assert np.abs(img[name] - img["default"])[mask].max() > 1e-3, name
    spec = {k: img[k] - img["diffuse"] for k in ("default", "schlick")}
    assert spec["schlick"][mask].sum() < spec["default"][mask].sum()
    settings = read_exr(str(outs["schlick"])).provenance()["settings"]
    assert settings.get("shadowing", settings.get("ggx_shadowing")) == "schlick", settings


def test_default_camera_and_size(run_cli, files):
    out = files / "d.exr"
    r = run_cli("relight", "builtin:left", "builtin:uniform", "--size", "16x12", "-o", out,
                *FAST, "-q")
    assert r.exit_code == 0, r.output
    image = read_exr(str(out))
    assert (image.width, image.height) == (16, 12)


def test_subprocess(files):
    out = files / "s.exr"
    r = run_relight("relight", "builtin:right", "builtin:studio", "--model", "physical",
                    "--camera", files / "cam.json", "-o", out, *FAST)
    assert r.returncode == 0, r.stderr
    assert out.exists() and "wrote" in r.stderr and r.stdout == ""


@pytest.mark.parametrize("args, code, message", [
    (["builtin:right", "-o", "o.exr"], 2, "give an env map ENV and/or --lights"),
    (["builtin:right", "builtin:sky", "--model", "neural", "-o", "o.exr"], 2, "not available"),
    (["builtin:right", "builtin:sky", "-o", "o.png"], 2, "name it .exr"),
    (["builtin:right", "builtin:sky", "--aov", "albedo", "-o", "o.exr"], 2, "unknown: albedo"),
    (["builtin:right", "builtin:sky", "--frame", "3", "-o", "o.exr"], 2, "out of range"),
    (["builtin:right", "builtin:sky", "--probe", "p.json", "-o", "o.exr"], 2,
     "only apply to Gaussians"),
    (["builtin:right", "builtin:sky", "--direct-light", "--shading-clip", "2", "-o", "o.exr"], 2,
     "--direct-light, --shading-clip only apply to Gaussians"),     # once ignored silently
    (["builtin:right", "builtin:sky", "--light-weights", "equal", "-o", "o.exr"], 2,
     "--light-weights only apply to Gaussians"),
    (["builtin:right", "builtin:sky", "--shadow-strength", "0.5", "-o", "o.exr"], 2,
     "--shadow-strength only apply to Gaussians"),                   # issue 52 cause 10
    (["builtin:right", "builtin:sky", "--roughness", "0", "-o", "o.exr"], 2, "--roughness"),
    (["builtin:right", "builtin:sky", "--env-sources", "x", "-o", "o.exr"], 2, "--env-sources"),
    (["builtin:right", "builtin:sky", "--env-sources", "-1", "-o", "o.exr"], 2, "--env-sources"),
    (["builtin:right", "builtin:sky", "--env-space", "pixels", "-o", "o.exr"], 2, "--env-space"),
    (["builtin:right", "builtin:sky", "--ggx-shadowing", "beckmann", "-o", "o.exr"], 2,
     "--ggx-shadowing"),
    (["builtin:right", "builtin:sky", "--model", "teacher", "--checkpoint", "t.pt",
      "--ggx-shadowing", "smith", "-o", "o.exr"], 2, "--ggx-shadowing only apply to --model"),
    (["builtin:right", "builtin:sky", "--tex-res", "2", "-o", "o.exr"], 2, "--tex-res"),
    (["builtin:right", "builtin:sky", "--env-res", "1x4", "-o", "o.exr"], 2, "--env-res"),
    (["builtin:right", "builtin:sky", "--env-res", "16x32", "-o", "o.exr"], 2,
     "did you mean 32x16"),                               # sizes are WxH (issue 16)
    (["builtin:right", "builtin:sky", "--tex-res", "16x8", "-o", "o.exr"], 2, "not square"),
    (["builtin:right", "builtin:sky", "--preview", "p.jpg", "-o", "o.exr"], 2, "name it .png"),
    (["builtin:nobody", "builtin:sky", "-o", "o.exr"], 2, "unknown built-in hand"),
    (["avatar.ply", "builtin:sky", "--model", "physical", "-o", "o.ply"], 2,
     "--model only apply to"),            # issue 53: ENV itself now lights Gaussians
    (["builtin:right", "missing.exr", "-o", "o.exr"], 1, "no such file"),
    (["missing.npz", "builtin:sky", "-o", "o.exr"], 1, "no such file"),
    (["builtin:right", "builtin:sky", "--camera", "bad.json", "-o", "o.exr"], 1, "invalid JSON"),
    (["builtin:right", "builtin:sky", "--lights", "bad.json", "-o", "o.exr"], 1, "invalid JSON"),
    (["junk.npz", "builtin:sky", "-o", "o.exr"], 1, "junk.npz"),
])
def test_bad_input(run_cli, files, monkeypatch, args, code, message):
    monkeypatch.chdir(files)
    (files / "bad.json").write_text("{not json")
    (files / "junk.npz").write_bytes(b"PK\x03\x04 not really a zip")
    r = run_cli("relight", *args)
    assert r.exit_code == code, r.output
    assert message in r.output, r.output
    assert len(r.output.strip().splitlines()) == 1 and "Traceback" not in r.output
    assert not (files / "o.exr").exists() and not (files / "o.png").exists()


def test_image_maps(run_cli, files):
    from relight_cli.formats.exr import write_exr
    from relight_cli.formats.image import write_png
    write_png(str(files / "grey.png"), np.full((8, 8, 3), 0.5))
    write_png(str(files / "white.png"), np.full((8, 8, 3), 1.0))
    write_exr(str(files / "rough.exr"), {"Y": np.full((8, 8), 0.3, np.float32)})
    write_exr(str(files / "hot.exr"), {"R": np.full((8, 8), 2.0, np.float32),
                                       "G": np.ones((8, 8), np.float32),
                                       "B": np.ones((8, 8), np.float32)})
    base = ["relight", "builtin:right", "builtin:uniform", "--camera", files / "cam.json",
            "--no-specular", "--no-sss", *FAST, "-q"]
    for name in ("grey", "white"):
        r = run_cli(*base, "--albedo", files / f"{name}.png", "--roughness", files / "rough.exr",
                    "-o", files / f"{name}.exr")
        assert r.exit_code == 0, r.output
    grey = read_exr(str(files / "grey.exr")).layer("")
    white = read_exr(str(files / "white.exr")).layer("")
    lit = white > 1e-4
    # Diffuse only: radiance is exactly proportional to the albedo (8-bit 128/255 vs 1).
    np.testing.assert_allclose(grey[lit] / white[lit], 128 / 255, rtol=1e-5)
    r = run_cli(*base, "--albedo", files / "hot.exr", "-o", files / "hot_out.exr")
    assert r.exit_code == 1 and "albedo map values" in r.output and "hot.exr" in r.output
    assert not (files / "hot_out.exr").exists()


def test_preview_exposure(run_cli, files, monkeypatch):
    """--preview-exposure S: the hand's --preview tone-mapped with that one scale (issue 53:
    two renders compared side by side each exposed on their own look alike); without
    --preview a usage error, nothing written."""
    import relight_cli.preview as P
    used = []
    real = P.write_preview
    monkeypatch.setattr(P, "write_preview", lambda path, rgb, exposure=None, **kw: (
        used.append(exposure), real(path, rgb, exposure=exposure, **kw))[1])
    r = run_cli("relight", "builtin:right", "builtin:sky", "--camera", files / "cam.json",
                "-o", files / "e.exr", "--preview", files / "e.png", "--preview-exposure",
                "0.5", *FAST, "-q")
    assert r.exit_code == 0, r.output
    assert used == [0.5]
    r = run_cli("relight", "builtin:right", "builtin:sky", "--camera", files / "cam.json",
                "-o", files / "f.exr", "--preview-exposure", "0.5", *FAST)
    assert r.exit_code == 2 and "--preview-exposure" in r.output
    assert not (files / "f.exr").exists()
