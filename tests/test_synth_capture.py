"""`relight synth-capture` and the relight/capture format: plan, images, resume, bad input."""

from __future__ import annotations

import json
import math
import os

import numpy as np
import pytest

from conftest import run_relight
from relight_cli.errors import DataError
from relight_cli.formats import capture as C
from relight_cli.formats.hand_npz import read_hand
from relight_cli.render import capture as S

TINY = ["--cameras", "2", "--leds", "6", "--group", "2", "--frames", "3", "--size", "12",
        "--tex-res", "32", "--aa", "1", "--eval-poses", "1", "--eval-cameras", "1",
        "--eval-envs", "builtin:uniform", "-q"]


def test_help(run_cli):
    r = run_cli("synth-capture", "--help")
    assert r.exit_code == 0 and "--cameras" in r.output and "--group" in r.output


# ---------------------------------------------------------------- engine


def test_fibonacci_dome_and_light_groups():
    d = S.fibonacci_sphere(400)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1, atol=1e-12)
    assert np.abs(d.mean(0)).max() < 0.01                  # evenly spread: centroid ≈ 0
    cams = S.dome_cameras(12, [0, 0.1, 0], 1.0, 16, 20)
    for cam in cams:
        np.testing.assert_allclose(np.linalg.norm(cam.center - [0, 0.1, 0]), 1.0, atol=1e-9)
        # The optical axis passes through the centre.
        p = cam.R @ np.array([0, 0.1, 0]) + cam.t
        assert abs(p[0]) < 1e-9 and abs(p[1]) < 1e-9 and p[2] > 0
    lights, names = S.dome_lights(100, [0, 0, 0], 1.2)
    group = S.light_group(lights.positions, 5, np.random.default_rng(0))
    assert len(group) == 5
    # A group is one light and its 4 nearest neighbours.
    assert any(sorted(np.argsort(np.linalg.norm(lights.positions - lights.positions[m], axis=1),
                                 kind="stable")[:5].tolist()) == group for m in group)


def test_fully_lit_stage_irradiance():
    """All LEDs on: irradiance on any unoccluded surface is ≈ π (see dome_lights)."""
    lights, _ = S.dome_lights(400, [0, 0, 0], 1.2)
    rng = np.random.default_rng(1)
    n = rng.normal(size=(50, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    l = lights.positions / np.linalg.norm(lights.positions, axis=1, keepdims=True)
    e = (np.clip(n @ l.T, 0, None) / 1.2 ** 2) @ lights.intensity[:, 0]
    # 400 lights sample the cosine lobe: quadrature error ~1%.
    np.testing.assert_allclose(e, math.pi, rtol=0.03)


def test_plan_is_deterministic_and_multiplexed():
    from relight_cli.hand.model import builtin_hand
    hand = builtin_hand()
    settings = S.StageSettings(cameras=3, lights=20, group=5, frames=7, full_every=3, res=8)
    a, b = S.plan_capture(hand, settings), S.plan_capture(hand, settings)
    assert a.key == b.key
    np.testing.assert_array_equal(a.motion.poses, b.motion.poses)
    assert [f.lit for f in a.frames] == ["full", "group", "group"] * 2 + ["full"]
    for f in a.frames:
        assert len(f.lights_on) == (20 if f.lit == "full" else 5)
    assert [f.lights_on for f in a.frames] == [f.lights_on for f in b.frames]
    other = S.plan_capture(hand, S.StageSettings(cameras=3, lights=20, frames=7, seed=1, res=8))
    assert other.key != a.key and not np.allclose(other.motion.poses, a.motion.poses)
    # Slerp motion: consecutive frames are close, key poses differ.
    step = np.abs(np.diff(a.motion.poses, axis=0)).max()
    assert 0 < step < 0.5


# ---------------------------------------------------------------- command


def test_capture_write_and_resume(run_cli, tmp_path):
    out = tmp_path / "cap"
    r = run_cli("synth-capture", "-o", out, *TINY)
    assert r.exit_code == 0, r.output
    cap = C.read_capture(str(out))
    assert cap.complete and len(cap.cameras) == 2 and len(cap.light_names) == 6
    assert [f.lit for f in cap.frames] == ["full", "group", "group"]
    assert [len(f.lights_on) for f in cap.frames] == [6, 2, 2]
    hand = read_hand(str(out / "hand.npz"))
    assert hand.n_frames == 3
    images = {}
    for f in cap.frames:
        assert sorted(f.images) == ["cam000", "cam001"]
        for name in f.images:
            path = out / C.image_path(f.index, name)
            rgb, mask = C.read_image(str(path), cap.camera(name))
            assert rgb.shape == (12, 12, 3) and mask.max() > 0
            images[path] = os.path.getmtime(path)
    # Fully lit frames are brighter than grouped ones (6 vs 2 lights).
    full = C.read_image(str(out / C.image_path(0, "cam000")))[0].sum()
    grouped = C.read_image(str(out / C.image_path(1, "cam000")))[0].sum()
    assert full > grouped
    render = cap.evaluation["renders"][0]
    assert (out / render["image"]).exists() and (out / cap.evaluation["envs"]["uniform"]).exists()

    # Resume: delete one image, damage another; only those two are rendered again.
    removed = out / C.image_path(1, "cam001")
    damaged = out / C.image_path(2, "cam000")
    removed.unlink()
    damaged.write_bytes(damaged.read_bytes()[:100])
    r = run_cli("synth-capture", "-o", out, *[a for a in TINY if a != "-q"])
    assert r.exit_code == 0, r.output
    assert "2 image(s) rendered" in r.output
    for path, mtime in images.items():
        if path not in (removed, damaged):
            assert os.path.getmtime(path) == mtime
    C.read_image(str(removed)), C.read_image(str(damaged))


def test_interrupted_capture_keeps_finished_frames(run_cli, tmp_path, monkeypatch):
    out = tmp_path / "cap"
    calls = {"n": 0}
    original = S.FrameRenderer.frame

    def failing(self, frame, cameras=None):
        calls["n"] += 1
        if calls["n"] == 2:
            raise MemoryError
        yield from original(self, frame, cameras)

    monkeypatch.setattr(S.FrameRenderer, "frame", failing)
    r = run_cli("synth-capture", "-o", out, *TINY)
    assert r.exit_code == 1 and "out of memory" in r.output
    assert (out / C.image_path(0, "cam000")).exists()            # frame 0 landed
    assert not (out / C.image_path(1, "cam000")).exists()
    assert not C.read_capture(str(out)).complete
    monkeypatch.setattr(S.FrameRenderer, "frame", original)
    r = run_cli("synth-capture", "-o", out, *[a for a in TINY if a != "-q"])
    assert r.exit_code == 0 and "2 already there" in r.output
    assert C.read_capture(str(out)).complete


def test_subprocess(tmp_path):
    r = run_relight("synth-capture", "-o", tmp_path / "cap", *TINY[:-1], "--eval-poses", "0")
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "cap" / "capture.json").exists() and r.stdout == ""
    assert C.read_capture(str(tmp_path / "cap")).evaluation is None


@pytest.mark.parametrize("args, code, message", [
    (["--group", "9", "--leds", "6"], 2, "exceeds --leds"),
    (["--cameras", "0"], 2, "--cameras must be"),
    (["--eval-cameras", "5", "--cameras", "2"], 2, "exceeds --cameras"),
    (["--motion", "file"], 2, "needs a HAND.npz"),
    (["--eval-envs", "builtin:sky,builtin:sky"], 2, "same name"),
    (["missing.npz"], 1, "no such file"),
    (["--eval-envs", "nothere.exr"], 1, "no such file"),
    (["builtin:martian"], 2, "unknown built-in hand"),
])
def test_bad_input(run_cli, tmp_path, monkeypatch, args, code, message):
    monkeypatch.chdir(tmp_path)
    r = run_cli("synth-capture", *args, "-o", "cap", "--frames", "2", "--size", "8")
    assert r.exit_code == code, r.output
    assert message in r.output and len(r.output.strip().splitlines()) == 1, r.output
    assert not (tmp_path / "cap").exists()


@pytest.mark.parametrize("old, value, hint", [("--lights", "6", "--leds"), ("--res", "8", "--size")])
def test_renamed_options_are_refused_with_their_new_name(run_cli, tmp_path, old, value, hint):
    """--lights (a count here, a JSON file elsewhere) is --leds; --res R is --size N."""
    r = run_cli("synth-capture", "-o", tmp_path / "cap", old, value)
    assert r.exit_code == 2 and len(r.output.strip().splitlines()) == 1, r.output
    assert f"{old} was renamed {hint}" in r.output
    assert not (tmp_path / "cap").exists()


def test_size_is_square(run_cli, tmp_path):
    """The stage's cameras are square: --size N or NxN, a non-square WxH is refused."""
    r = run_cli("synth-capture", "-o", tmp_path / "cap", "--size", "16x8")
    assert r.exit_code == 2 and "not square" in r.output, r.output
    assert not (tmp_path / "cap").exists()
    r = run_cli("synth-capture", "-o", tmp_path / "cap", *TINY[:-1], "--size", "12x12",
                "--eval-poses", "0", "-q")
    assert r.exit_code == 0, r.output
    assert C.read_capture(str(tmp_path / "cap")).cameras[0].width == 12


def test_no_clobber_refuses_an_existing_capture(run_cli, tmp_path):
    out = tmp_path / "cap"
    out.mkdir()
    r = run_cli("synth-capture", "-o", out, *TINY, "--no-clobber")
    assert r.exit_code == 2 and "--no-clobber" in r.output, r.output
    assert os.listdir(out) == []


def test_bad_output_folders(run_cli, tmp_path):
    (tmp_path / "file").write_text("x")
    r = run_cli("synth-capture", "-o", tmp_path / "file")
    assert r.exit_code == 2 and "not a folder" in r.output
    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "other.txt").write_text("x")
    r = run_cli("synth-capture", "-o", tmp_path / "busy")
    assert r.exit_code == 2 and "holds no capture.json" in r.output
    out = tmp_path / "cap"
    assert run_cli("synth-capture", "-o", out, *TINY).exit_code == 0
    before = sorted(p.name for p in out.rglob("*"))
    r = run_cli("synth-capture", "-o", out, *TINY, "--seed", "3")
    assert r.exit_code == 2 and "different capture" in r.output
    assert sorted(p.name for p in out.rglob("*")) == before


# ---------------------------------------------------------------- format


def _minimal():
    return {"format": "relight/capture", "version": 1, "hand": "hand.npz",
            "cameras": [{"name": "a", "K": [[10, 0, 4], [0, 10, 4], [0, 0, 1]],
                         "R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "t": [0, 0, 1],
                         "width": 8, "height": 8}],
            "lights": [{"position": [0, 1, 0], "intensity": [1, 1, 1]}],
            "frames": [{"index": 0, "time": 0.0, "pose": 0, "lit": "full", "lights_on": [0],
                        "images": ["a"]}]}


def test_format_round_trip_and_rejections(tmp_path):
    path = tmp_path / "capture.json"
    path.write_text(json.dumps(_minimal()))
    cap = C.read_capture(str(path))
    C.write_capture(str(tmp_path / "again.json"), cap)
    assert C.to_json(C.read_capture(str(tmp_path / "again.json"))) == C.to_json(cap)
    for change, message in (
            ({"version": 2}, "version 2 is newer"),
            ({"format": "relight/other"}, "not a relight/capture file"),
            ({"frames": [{"index": 0, "pose": 0, "lights_on": [3]}]}, "lights_on"),
            ({"frames": [{"index": 0, "pose": 0, "images": ["zz"]}]}, "unknown camera"),
            ({"frames": [{"index": 0, "pose": 0, "lit": "half"}]}, "'full' or 'group'"),
            ({"lights": [{"position": [0, "x", 0]}]}, "position"),
            ({"cameras": []}, "'cameras' is empty")):
        obj = dict(_minimal(), **change)
        path.write_text(json.dumps(obj))
        with pytest.raises(DataError) as info:
            C.read_capture(str(path))
        assert message in str(info.value) and str(path) in str(info.value)
