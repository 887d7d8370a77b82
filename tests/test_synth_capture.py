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
        "--eval-envs", "builtin:uniform", "--eval-env-res", "16x8", "-q"]


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


# ---------------------------------------------------------------- two interacting hands


def _surface_distance(a, b) -> float:
    """Exact smallest distance from a vertex of mesh ``a`` to the triangles of mesh ``b``
    (slow twin of the stage's vertex–vertex distance): for each of a's vertices near b, the
    closest point on every triangle of b that can hold it (a triangle whose corners lie
    within the nearest-vertex distance + the largest triangle diameter)."""
    import trimesh
    from scipy.spatial import cKDTree

    tree = cKDTree(b.vertices)
    d, _ = tree.query(a.vertices, k=1)
    tri = b.vertices[b.faces]
    diameter = np.linalg.norm(tri - tri[:, [1, 2, 0]], axis=2).max()
    faces_of = [[] for _ in range(len(b.vertices))]
    for f, corners in enumerate(b.faces):
        for v in corners:
            faces_of[v].append(f)
    best = np.inf
    for i in np.nonzero(d < d.min() + 0.003)[0]:
        faces = np.unique(np.concatenate([faces_of[v] for v in
                                          tree.query_ball_point(a.vertices[i], d[i] + diameter)]))
        closest = trimesh.triangles.closest_point(tri[faces], np.repeat(a.vertices[i][None],
                                                                        len(faces), 0))
        best = min(best, float(np.linalg.norm(closest - a.vertices[i], axis=1).min()))
    return best


@pytest.fixture(scope="module")
def two_motion():
    from relight_cli.hand.model import builtin_hand
    from relight_cli.hand.scene import two_hands
    return S.hand_motion(two_hands(builtin_hand("right")), 12, seed=5, keyframe_every=4)


def test_two_hands_move_close_but_apart(two_motion):
    from relight_cli.hand.scene import handedness, posed_meshes
    motion = two_motion
    assert handedness(motion) == ["right", "left"] and len(motion.hands) == 2
    # both hands move: their own finger poses (not mirrors of each other) change over time
    for inst in motion.hands:
        assert np.abs(np.diff(inst.poses[:, 1:], axis=0)).max() > 1e-3
    from relight_cli.hand.skinning import mirror_pose
    assert not np.allclose(mirror_pose(motion.hands[0].poses[:, 1:]), motion.hands[1].poses[:, 1:])
    for f in range(0, 12, 3):
        m0, m1 = posed_meshes(motion, f, "fine")
        gap = min(_surface_distance(m0, m1), _surface_distance(m1, m0))
        # never touching (the documented margin), but interacting: a few centimetres at most
        assert S.TWO_HAND_MARGIN <= gap <= S.TWO_HAND_GAP[1] + 1e-3, (f, gap)
        assert S.hand_distance(motion, f) >= S.TWO_HAND_GAP[0] - 1e-9
    # held-out poses of a pair: every frame its own key pose, still apart
    held = S.hand_motion(motion, 3, seed=9, keyframe_every=1)
    assert all(S.hand_distance(held, f) >= S.TWO_HAND_GAP[0] - 1e-9 for f in range(3))
    assert not np.allclose(held.hands[1].translations, held.hands[1].translations[0])


def test_two_hands_shadow_occlude_and_light_each_other(two_motion):
    """What makes a pair harder than two single hands: with the other hand present, some
    texels lose LEDs (cast shadows), some camera samples see the other hand instead
    (occlusion), and one bounce brings light from the other hand's skin."""
    from relight_cli.hand.scene import posed_meshes
    from relight_cli.render.appearance import hand_materials
    from relight_cli.render.gbuffer import render_gbuffer
    from relight_cli.render.shading import HandRenderer, RenderSettings

    settings = S.StageSettings(cameras=8, lights=24, frames=12, res=24, tex_res=48)
    plan = S.plan_capture(two_motion, settings, motion=two_motion)
    meshes = posed_meshes(two_motion, 6, "fine")
    materials = hand_materials(two_motion, "fine", 64)
    rs = RenderSettings(tex_res=48, aa=1, sss=False, specular=False, direct="texel", bounce=True)
    both = HandRenderer(meshes, materials, rs)
    alone = HandRenderer(meshes[:1], materials[:1], rs)
    vis_both = both.light_visibility(0, positions=plan.lights.positions)
    vis_alone = alone.light_visibility(0, positions=plan.lights.positions)
    assert not (vis_both & ~vis_alone).any()                  # the other hand only takes light
    assert (vis_alone & ~vis_both).mean() > 0.002             # … and it does: cast shadows
    occluded = 0
    for cam in plan.cameras:
        gb_both = render_gbuffer(meshes, cam, 1)
        gb_alone = render_gbuffer(meshes[:1], cam, 1)
        occluded += int(((gb_alone.hand == 0) & (gb_both.hand == 1)).sum())
    assert occluded > 0
    lights = plan.lights
    bounce_both = both._bounce(both.light(lights).direct)[0]
    bounce_alone = alone._bounce(alone.light(lights).direct)[0]
    assert (bounce_both - bounce_alone).max() > 0.01 * bounce_alone.max()


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


def test_left_hand_skin_is_the_left_hand_of_the_pair():
    """One subject: the left hand of a two-hand scene has exactly the skin of a left-hand
    capture, the right that of a right-hand one (so per-hand teachers apply to the pair)."""
    from relight_cli.hand.model import builtin_hand
    from relight_cli.hand.scene import two_hands
    from relight_cli.render.appearance import hand_materials
    pair = hand_materials(two_hands(builtin_hand("right")), "fine", 64, seed=3)
    right = hand_materials(builtin_hand("right"), "fine", 64, seed=3)[0]
    left = hand_materials(builtin_hand("left"), "fine", 64, seed=3)[0]
    np.testing.assert_array_equal(pair[0].albedo, right.albedo)
    np.testing.assert_array_equal(pair[1].albedo, left.albedo)
    np.testing.assert_array_equal(pair[1].roughness, left.roughness)
    assert np.abs(left.albedo - right.albedo).max() > 0.01          # two different hands


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


def test_nails_and_regions_are_in_the_images():
    """The stage renders the procedural skin: pixels on nails are whiter (higher G/R) than
    pixels on finger skin in a fully lit frame, so a capture without region materials
    (a flat colour) would fail here."""
    from relight_cli.hand.model import FINGER, NAIL, builtin_hand
    from relight_cli.render.appearance import hand_materials
    from relight_cli.uvraster import rasterize_uv
    hand = builtin_hand(pose="relaxed")
    settings = S.StageSettings(cameras=6, lights=32, frames=1, res=96, tex_res=128, aa=1)
    plan = S.plan_capture(hand, settings, motion=hand)
    renderer = S.FrameRenderer(plan, hand_materials(plan.motion, "fine", 256), settings)
    fine = hand.fine
    raster = rasterize_uv(fine.uv, fine.faces_uv, 256)
    labels = raster.interpolate(np.eye(5)[fine.labels], fine.faces, fill=None)
    from relight_cli.render.appearance import bilinear
    ratio = {NAIL: [], FINGER: []}
    for cam, result in renderer.frame(plan.frames[0]):
        gb = result.gbuffer
        hit = gb.hit
        lab = np.argmax(bilinear(labels, gb.uv[hit]), 1)
        rad = result.samples[hit]
        for region in ratio:
            sel = (lab == region) & (rad[:, 0] > 0.05)
            ratio[region].extend(rad[sel, 1] / rad[sel, 0])
    assert len(ratio[NAIL]) > 20
    assert np.mean(ratio[NAIL]) > np.mean(ratio[FINGER]) + 0.05


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


# ---------------------------------------------------------------- held-out env maps


def test_stage_env_render_matches_brute_force():
    """An HDR through the stage: resampled once to the working grid (power kept; the
    resampling's exactness is tests/test_envmap.py's), then the ground truth's texel
    irradiance = Σ over the grid's directions of L·h·max(n·ω, 0)·Δω, with h from
    brute-force ray–triangle tests (independent of embree and of features.py)."""
    from relight_cli import envmap as E
    from relight_cli.formats.envmap import EnvMap
    from relight_cli.raytrace import occluded_reference
    from relight_cli.render.appearance import constant_material
    from relight_cli.render.shading import HandRenderer, RenderSettings
    from render_scenes import uv_quad

    rng = np.random.default_rng(3)
    src = rng.exponential(0.5, (32, 64, 3)).astype(np.float32)
    src[5, 40] = 2000.0                                         # a small sun
    env = S.stage_envmap(EnvMap(src, "latlong", "hdr"), (8, 16))
    assert (env.height, env.width) == (8, 16)
    np.testing.assert_allclose(E.power(env), E.power(EnvMap(src, "latlong")), rtol=1e-6)
    assert S.stage_envmap(env, (8, 16)) is env                  # already on the grid: kept

    floor = uv_quad(0.2)
    blocker = uv_quad(0.08, z=0.03)                              # shades part of the floor
    blocker.vertices[:, 0] += 0.03
    white = constant_material(albedo=(1.0, 1.0, 1.0))
    renderer = HandRenderer([floor, blocker], [white, white],
                            RenderSettings(tex_res=12, aa=1, specular=False, sss=False,
                                           env_res=(8, 16), env_space="texels", direct="texel"))
    ours = renderer.light(env=env).direct[0]                    # [K, 3] floor texels
    surf = renderer.surfaces[0]
    dirs = E.latlong_directions(8, 16).reshape(-1, 3)
    dw = E.latlong_solid_angles(8, 16).reshape(-1)
    rad = env.radiance.reshape(-1, 3).astype(np.float64)
    verts = np.concatenate([floor.vertices, blocker.vertices])
    faces = np.concatenate([floor.faces, blocker.faces + len(floor.vertices)])
    cos = surf.normals @ dirs.T                                  # [K, M]
    ii, mm = np.nonzero(cos > 0)
    origins = surf.points[ii] + renderer.offsets[0] * surf.normals[ii]
    blocked = occluded_reference(verts, faces, origins, dirs[mm])
    expected = np.zeros_like(ours)
    np.add.at(expected, ii, (~blocked * cos[ii, mm] * dw[mm])[:, None] * rad[mm])
    assert blocked.any() and not blocked.all()
    np.testing.assert_allclose(ours, expected, rtol=1e-9, atol=1e-12 * expected.max())


def test_stage_env_render_is_the_sum_of_far_leds():
    """Superposition, the property every model of LED frames relies on (RelightableHands
    Eq. 2): with ``env_space="texels"`` (the stage's default since ``eval_env_space``) an
    env map of a few lit directions renders, SSS and GGX included, as the sum of far LEDs
    in those directions (r = 100 m, intensity r²·L Δω: the distant-light limit of the
    LEDs' own shading), through a camera.  The older per-vertex transport does not."""
    from relight_cli.envmap import DiscreteEnv, latlong_directions, latlong_solid_angles
    from relight_cli.hand.scene import posed_meshes
    from relight_cli.inputs import load_hand
    from relight_cli.render.appearance import hand_materials
    from relight_cli.render.shading import HandRenderer, PointLights, RenderSettings

    hand = load_hand("builtin:right")
    meshes = posed_meshes(hand, 0, "fine")
    materials = hand_materials(hand, "fine", 256, 0)
    centre = meshes[0].vertices.mean(0)
    camera = S.dome_cameras(3, centre, 1.0, 32, 30.0)[1]
    dirs = latlong_directions(8, 16).reshape(-1, 3)
    dw = latlong_solid_angles(8, 16).reshape(-1)
    far = 100.0

    def relative(space, cells, weights):
        r = HandRenderer(meshes, materials, RenderSettings(tex_res=64, aa=2, sss=True,
                                                           direct="texel", env_res=(8, 16),
                                                           env_space=space))
        rad = np.zeros((len(dirs), 3))
        rad[cells] = weights / dw[cells, None]                  # L Δω = weight
        env = r.render(camera, r.light(env=DiscreteEnv(dirs, dw, rad, 8, 16))).image
        leds = PointLights(centre + far * dirs[cells], far * far * weights)
        led = r.render(camera, r.light(leds)).image
        assert led.sum() > 0
        return float(np.sum((env - led) ** 2) / np.sum(led ** 2))

    # one at a time (a backlit grazing one, 37, has the sharpest lobe), then three at once
    singles = [20, 37, 50, 70, 90]
    weights = np.array([[1.0, 0.8, 0.6], [0.3, 0.3, 0.3], [2.0, 2.0, 1.5]])
    for c in singles:
        assert relative("texels", [c], weights[:1]) < 1e-3, c
    assert relative("texels", [20, 37, 90], weights) < 1e-3
    assert max(relative("vertices", [c], weights[:1]) for c in singles) > 1e-2


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


def test_polyhaven_eval_env(run_cli, tmp_path, shared):
    """A real 1k Poly Haven HDR as a held-out env map: stored in eval/envs/ at the working
    grid with its power, and the evaluation renders lit by it."""
    from relight_cli import envmap as E
    from relight_cli.inputs import load_envmap
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
