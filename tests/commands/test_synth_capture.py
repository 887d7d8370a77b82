"""``relight synth-capture`` (commands/synth_capture.py): help, write and resume, interruption,
the console script, bad input, renamed options, two hands, skin seeds, held-out env maps."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from conftest import run_relight
from relight_cli.formats import capture as C
from relight_cli.formats.hand_npz import read_hand
from relight_cli.render import capture as S

TINY = ["--cameras", "2", "--leds", "6", "--group", "2", "--n-frames", "3", "--size", "12",
        "--tex-res", "32", "--aa", "1", "--eval-poses", "1", "--eval-cameras", "1",
        "--eval-envs", "builtin:uniform", "--eval-env-res", "16x8", "-q"]


def test_help(run_cli):
    r = run_cli("synth-capture", "--help")
    assert r.exit_code == 0 and "--cameras" in r.output and "--group" in r.output


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
    # a seed numpy cannot take was an internal error after capture.json and hand.npz were
    # written (issue 52's sweep); --skin-seed takes what --seed takes
    (["--skin-seed", "-1"], 2, "--skin-seed"),
    (["--skin-seed", str(2**32)], 2, "--skin-seed"),
])
def test_bad_input(run_cli, tmp_path, monkeypatch, args, code, message):
    monkeypatch.chdir(tmp_path)
    r = run_cli("synth-capture", *args, "-o", "cap", "--n-frames", "2", "--size", "8")
    assert r.exit_code == code, r.output
    assert message in r.output and len(r.output.strip().splitlines()) == 1, r.output
    assert not (tmp_path / "cap").exists()


@pytest.mark.parametrize("old, value, hint", [("--lights", "6", "--leds"), ("--res", "8", "--size"),
                                              ("--frames", "3", "--n-frames")])
def test_renamed_options_are_refused_with_their_new_name(run_cli, tmp_path, old, value, hint):
    """--lights (a count here, a JSON file elsewhere) is --leds; --res R is --size N;
    --frames N (a count here, a selection everywhere else) is --n-frames N."""
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


def test_two_hand_capture(run_cli, tmp_path):
    """builtin:two: both hands in every image, per-hand coverage channels summing to the
    mask, held-out env renders of the pair, the placement recorded in capture.json."""
    from relight_cli.hand.scene import handedness
    out = tmp_path / "two"
    r = run_cli("synth-capture", "builtin:two", "-o", out, *TINY[:TINY.index("--size")],
                "--size", "24", *TINY[TINY.index("--size") + 2:])
    assert r.exit_code == 0, r.output
    cap = C.read_capture(str(out))
    hand = read_hand(str(out / "hand.npz"))
    assert handedness(hand) == ["right", "left"]
    assert handedness(read_hand(str(out / cap.evaluation["hand"]))) == ["right", "left"]
    record = cap.settings["two_hands"]
    assert record["closest_mm"] >= 1000 * S.TWO_HAND_GAP[0] - 1e-6
    assert record["eval_closest_mm"] >= 1000 * S.TWO_HAND_GAP[0] - 1e-6
    seen = np.zeros(2)
    paths = [out / C.image_path(f.index, c) for f in cap.frames for c in f.images]
    paths += [out / r["image"] for r in cap.evaluation["renders"]]
    for path in paths:
        rgb, mask, hands = C.read_image_hands(str(path), None, 2)
        assert hands.shape == (2,) + mask.shape
        np.testing.assert_allclose(hands.sum(0), mask, atol=1e-3)   # half floats
        seen += hands.sum((1, 2))
    assert (seen > 0).all()
    # one-hand readers still read every image (extra channels are ignored)
    C.read_image(str(paths[0]))
    assert C.read_image_hands(str(paths[0]), None, 1)[2] is None


# ---------------------------------------------------------------- how hard the stage is


def _capture_images(run_cli, out, *extra):
    # 2.3 mm texels (--tex-res 128): the skin profile's widest Gaussians (σ 1.4 and 2.7 mm,
    # red) span texels; narrower ones act below the texture's resolution (no blur)
    args = [a for a in TINY if a not in ("--tex-res", "32")]
    r = run_cli("synth-capture", "-o", out, *args[:args.index("--size")], "--size", "24",
                *args[args.index("--size") + 2:], "--tex-res", "128", "--eval-poses", "0", *extra)
    assert r.exit_code == 0, r.output
    cap = C.read_capture(str(out))
    return cap, {(f.index, c): C.read_image(str(out / C.image_path(f.index, c)))
                 for f in cap.frames for c in f.images}


def test_sss_and_bounce_reach_the_images(run_cli, tmp_path):
    """--no-sss and --bounce change the capture's images the way they should, so neither
    can be silently off: SSS moves light around (skin's red most) at nearly the same total,
    the bounce only adds light."""
    base_cap, base = _capture_images(run_cli, tmp_path / "base")
    flat_cap, flat = _capture_images(run_cli, tmp_path / "flat", "--no-sss")
    lit_cap, lit = _capture_images(run_cli, tmp_path / "lit", "--bounce")
    assert base_cap.settings["sss"] and not flat_cap.settings["sss"]
    assert lit_cap.settings["bounce"] and not base_cap.settings["bounce"]
    diff_sss = []
    for key, (rgb, mask) in base.items():
        inside = mask > 0.99
        d = np.abs(rgb - flat[key][0])[inside]
        diff_sss.append(d.mean(0) / np.maximum(rgb[inside].mean(0), 1e-9))
        # the bounce adds light (half floats: 1e-3 relative rounding), and somewhere visibly
        assert (lit[key][0] >= rgb - 2e-3 * np.abs(rgb) - 1e-6).all()
        np.testing.assert_array_equal(lit[key][1], mask)
    diff_sss = np.mean(diff_sss, 0)
    assert diff_sss[0] > 5e-3 and diff_sss[0] > 3 * diff_sss[2]      # red diffuses farthest
    gain = [lit[k][0][base[k][1] > 0.99].sum() / rgb[mask > 0.99].sum()
            for k, (rgb, mask) in base.items()]
    assert max(gain) > 1.002
    total = [flat[k][0][base[k][1] > 0.99].sum() / rgb[mask > 0.99].sum()
             for k, (rgb, mask) in base.items()]
    assert abs(np.mean(total) - 1) < 0.05                          # SSS conserves energy


def test_skin_seed_not_seed_decides_the_skin(run_cli, tmp_path):
    """--seed changes a capture's motion and light groups, never its subject: with the
    motion from a file, the fully lit frame is the same for two --seeds and differs for
    another --skin-seed."""
    from relight_cli.formats.hand_npz import write_hand
    from relight_cli.hand.model import builtin_hand
    hand = builtin_hand(pose="relaxed")
    path = tmp_path / "hand.npz"
    write_hand(str(path), hand)

    def full_frame(name, *extra):
        out = tmp_path / name
        r = run_cli("synth-capture", path, "-o", out, "--motion", "file", "--cameras", "1",
                    "--leds", "8", "--size", "16", "--tex-res", "32", "--aa", "1",
                    "--eval-poses", "0", "-q", *extra)
        assert r.exit_code == 0, r.output
        return C.read_image(str(out / C.image_path(0, "cam000")))[0]
    a, b, c = full_frame("a"), full_frame("b", "--seed", "4"), full_frame("c", "--skin-seed", "4")
    np.testing.assert_array_equal(a, b)
    assert np.abs(a - c).max() > 1e-3


def test_older_captures_keep_their_key_and_env_space(run_cli, tmp_path):
    """A capture.json without ``eval_env_space`` was rendered per vertex: its stage
    rebuilds as such and its key is what it was; a new capture records ``texels`` (the
    default) or what ``--eval-env-space`` says, and the two have different keys."""
    from dataclasses import asdict
    import hashlib
    old = asdict(S.StageSettings(eval_env_space="vertices"))
    del old["eval_env_space"]
    assert S.stage_settings(old).eval_env_space == "vertices"
    text = json.dumps({"settings": old, "hand": "abc"}, sort_keys=True)
    assert S.capture_key(S.StageSettings(eval_env_space="vertices"), "abc") == \
        hashlib.sha256(text.encode()).hexdigest()[:16]
    assert S.capture_key(S.StageSettings(), "abc") != S.capture_key(
        S.StageSettings(eval_env_space="vertices"), "abc")
    assert S.stage_settings({**old, "eval_env_space": "pixels"}) is None
    keys = {}
    for space in ("texels", "vertices", None):
        out = tmp_path / f"cap-{space}"
        extra = [] if space is None else ["--eval-env-space", space]
        r = run_cli("synth-capture", "-o", out, *TINY, *extra)
        assert r.exit_code == 0, r.output
        cap = C.read_capture(str(out))
        assert cap.settings["eval_env_space"] == (space or "texels")
        keys[space] = cap.key
    assert keys[None] == keys["texels"] != keys["vertices"]
    r = run_cli("synth-capture", "-o", tmp_path / "bad", *TINY, "--eval-env-space", "pixels")
    assert r.exit_code == 2 and not (tmp_path / "bad").exists()


def test_older_captures_keep_their_lobe_and_key(run_cli, tmp_path):
    """A capture.json without ``ggx_shadowing`` was made with URHand's Schlick–Smith lobe:
    its stage rebuilds so and its key is what it was; a new capture records ``smith`` (the
    default) or ``--ggx-shadowing schlick``, with different keys and images."""
    from dataclasses import asdict
    import hashlib
    old = asdict(S.StageSettings(eval_env_space="vertices", ggx_shadowing="schlick"))
    del old["eval_env_space"], old["ggx_shadowing"]
    assert S.stage_settings(old).ggx_shadowing == "schlick"
    text = json.dumps({"settings": old, "hand": "abc"}, sort_keys=True)
    assert S.capture_key(S.StageSettings(eval_env_space="vertices", ggx_shadowing="schlick"),
                         "abc") == hashlib.sha256(text.encode()).hexdigest()[:16]
    assert S.stage_settings({**old, "ggx_shadowing": "beckmann"}) is None
    caps = {}
    for lobe in ("smith", "schlick"):
        out = tmp_path / f"cap-{lobe}"
        r = run_cli("synth-capture", "-o", out, *TINY, *(["--ggx-shadowing", lobe]
                                                          if lobe == "schlick" else []))
        assert r.exit_code == 0, r.output
        caps[lobe] = C.read_capture(str(out))
        assert caps[lobe].settings["ggx_shadowing"] == lobe
    assert caps["smith"].key != caps["schlick"].key
    a = C.read_image(str(tmp_path / "cap-smith" / C.image_path(0, "cam000")))[0]
    b = C.read_image(str(tmp_path / "cap-schlick" / C.image_path(0, "cam000")))[0]
    assert np.abs(a - b).max() > 1e-4          # the lobe changed the highlights
    r = run_cli("synth-capture", "-o", tmp_path / "bad", *TINY, "--ggx-shadowing", "ue4")
    assert r.exit_code == 2 and not (tmp_path / "bad").exists()


def test_polyhaven_eval_env(run_cli, tmp_path, shared):
    """A real 1k Poly Haven HDR as a held-out env map: stored in eval/envs/ at the working
    grid with its power, and the evaluation renders lit by it."""
    from relight_cli import envmap as E
    from relight_cli.cli.inputs import load_envmap
    from relight_cli.formats.envmap import read_envmap
    hdr = shared("envmaps", "polyhaven", "lebombo_1k.hdr")
    out = tmp_path / "cap"
    args = list(TINY)
    args[args.index("--eval-envs") + 1] = str(hdr)
    r = run_cli("synth-capture", "-o", out, *args, "--eval-env-res", "32x16")
    assert r.exit_code == 0, r.output
    cap = C.read_capture(str(out))
    stored = read_envmap(str(out / cap.evaluation["envs"]["lebombo_1k"]))
    source = load_envmap(str(hdr))
    assert (stored.height, stored.width) == (16, 32)
    np.testing.assert_allclose(E.power(stored), E.power(source), rtol=1e-4)
    rgb, mask = C.read_image(str(out / cap.evaluation["renders"][0]["image"]))
    assert rgb[mask > 0.5].mean() > 0


def test_phone_scan_photos_cameras_and_keypoints(run_cli, tmp_path):
    """--phone-scan: RGBA photos whose mask covers the hand, one camera per photo, and the
    subject's joints projected into each (within the detector noise), MediaPipe's 21; a
    rerun with fewer views leaves no stale photo; a capture folder is refused."""
    from relight_cli.formats.camera import read_cameras
    from relight_cli.formats.exr import read_exr
    from relight_cli.formats.keypoints2d import MEDIAPIPE_TO_WEBXR, read_keypoints2d
    from relight_cli.hand.model import PARENTS, builtin_hand
    from relight_cli.hand.poses import named_pose
    from relight_cli.hand.skinning import posed_joints
    scan = tmp_path / "scan"
    args = ["synth-capture", "builtin:right", "--phone-scan", "builtin:sky", "--size", "48",
            "--tex-res", "16", "--aa", "1", "--no-sss", "-o", scan, "-q"]
    assert run_cli(*args, "--views", "3").exit_code == 0
    cams = read_cameras(str(scan / "cameras.json"))
    kp = read_keypoints2d(str(scan / "keypoints.json"))
    assert len(cams) == 3 and kp.skeleton == "mediapipe-21" and kp.side == "right"
    rest = builtin_hand().rest_joints
    joints = posed_joints(named_pose("relaxed", "right", rest)[None], np.zeros((1, 3)), rest,
                          PARENTS)[0]
    for cam, uv, name in zip(cams, kp.uv, kp.images):
        x = joints @ cam.R.T + cam.t
        p = x[:, :2] / x[:, 2:] @ cam.K[:2, :2].T + cam.K[:2, 2]
        err = np.linalg.norm(p - uv, axis=1)[MEDIAPIPE_TO_WEBXR]
        assert err.max() < 5.0                         # 1 px noise per axis
        image = read_exr(str(scan / name)).channels
        assert 0.02 < image["A"].mean() < 0.9 and image["R"][image["A"] == 0].max() == 0
    assert run_cli(*args, "--views", "2").exit_code == 0
    assert sorted(p.name for p in scan.glob("view_*.exr")) == ["view_00.exr", "view_01.exr"]
    (tmp_path / "cap").mkdir()
    (tmp_path / "cap" / "capture.json").write_text("{}")
    r = run_cli(*args[:-3], "-o", tmp_path / "cap")
    assert r.exit_code == 2 and "holds a capture" in r.output
