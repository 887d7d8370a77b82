"""Gaussian clips (issue 49): ``relight relight`` over frames (commands/_clip.py,
relight_cli/jobs/gaussian_clip.py) and ``dgsm-build --frames`` (commands/_dgsm_frames.py):
moving avatars as '{frame}' PLY patterns, sequence indexes and hand motions; shadow maps
built per frame in-process or read per frame; probes refitted at the avatar; one frame
alone equal to the same frame of the clip; the video; bad input."""

from __future__ import annotations

import json
import math
import os

import numpy as np
import pytest

from conftest import run_relight
from relight_cli.formats.camera import Camera, write_cameras
from relight_cli.formats.gaussians_ply import Gaussians, rgb_to_sh_dc, write_gaussians

N_FRAMES = 4


def ball(centre, n=150, radius=0.08, seed=0, colour=(0.8, 0.5, 0.3)):
    """A ball of small round Gaussians."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return Gaussians(d * radius + np.asarray(centre, float), np.full((n, 3), 0.02),
                     np.tile([1.0, 0, 0, 0], (n, 1)), np.full(n, 0.95),
                     rgb_to_sh_dc(np.tile(colour, (n, 1)))[:, None, :], 0)


def floor(n=24, size=1.2):
    """A flat floor of Gaussians at y = 0."""
    u = np.linspace(-size / 2, size / 2, n)
    x, z = np.meshgrid(u, u)
    m = n * n
    scales = np.full((m, 3), size / n * 0.7)
    scales[:, 1] = 0.002
    return Gaussians(np.column_stack([x.ravel(), np.zeros(m), z.ravel()]), scales,
                     np.tile([1.0, 0, 0, 0], (m, 1)), np.full(m, 0.95),
                     rgb_to_sh_dc(np.full((m, 3), 0.6))[:, None, :], 0)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A ball moving along x over a floor (frames 0-3 as seq/ball_{frame:03d}.ply), its
    sequence index, a lamp above, a camera."""
    root = tmp_path_factory.mktemp("clip")
    (root / "seq").mkdir()
    for k in range(N_FRAMES):
        write_gaussians(str(root / "seq" / f"ball_{k:03d}.ply"),
                        ball([-0.3 + 0.2 * k, 0.25, 0.0]))
    write_gaussians(str(root / "floor.ply"), floor())
    (root / "lights.json").write_text(json.dumps({
        "format": "relight/lights", "version": 1,
        "lights": [{"position": [0.1, 1.5, 0.2], "color": [1, 1, 1], "intensity": 4.0}]}))
    write_cameras(str(root / "cam.json"),
                  [Camera.look_at([0.0, 0.9, 1.3], [0.0, 0.1, 0.0], width=48, height=36)])
    (root / "seq.json").write_text(json.dumps({
        "format": "relight/gaussian-sequence", "version": 1,
        "frames": "seq/ball_{frame:03d}.ply", "count": N_FRAMES, "fps": 12,
        "colour_space": "linear", "same_topology": True}))
    return root


CLIP = ["--receivers", "floor.ply", "--lights", "lights.json", "--probe", "scene",
        "--direct-light", "--camera", "cam.json"]


def _pixels(path):
    from relight_cli.formats.exr import read_exr
    return read_exr(str(path))


def _invoke(cwd, *args):
    from click.testing import CliRunner

    from relight_cli.cli import cli
    old = os.getcwd()
    os.chdir(cwd)
    try:
        return CliRunner().invoke(cli, [str(a) for a in args])
    finally:
        os.chdir(old)


def test_clip_frames_equal_single_frame_runs_and_shadow_follows(scene, tmp_path):
    """One process renders every frame (the shadow map rebuilt per frame in-process, the
    probe refitted at the ball): each frame equals the same frame rendered alone, and the
    ball's shadow on the floor moves with it."""
    out = tmp_path / "clip"
    out.mkdir()
    r = _invoke(scene, "relight", "seq/ball_{frame:03d}.ply", "--frames", "all", *CLIP,
                "-o", out / "f_{frame}.exr", "--video", out / "clip.webp")
    assert r.exit_code == 0, r.output
    assert sorted(os.listdir(out)) == ["clip.webp"] + [f"f_{k}.exr" for k in range(N_FRAMES)]
    for k in (0, 2):
        r = _invoke(scene, "relight", "seq/ball_{frame:03d}.ply", "--frame", k, *CLIP,
                    "-o", tmp_path / f"one_{k}.exr")
        assert r.exit_code == 0, r.output
        np.testing.assert_array_equal(_pixels(tmp_path / f"one_{k}.exr").layer(""),
                                      _pixels(out / f"f_{k}.exr").layer(""))
    # the shadow: floor pixels darker than the same run without shadows, and where
    darkest = []
    for k in range(N_FRAMES):
        shadowed = _pixels(out / f"f_{k}.exr").layer("")
        r = _invoke(scene, "relight", "seq/ball_{frame:03d}.ply", "--frame", k,
                    "--receivers", "floor.ply", "--probe", "scene", "--camera", "cam.json",
                    "-o", tmp_path / f"lit_{k}.exr")
        assert r.exit_code == 0, r.output
        unshadowed = _pixels(tmp_path / f"lit_{k}.exr").layer("")
        drop = (unshadowed - shadowed).sum(axis=2)
        assert drop.max() > 0.05, k
        darkest.append(np.unravel_index(np.argmax(drop), drop.shape)[1])
    assert np.all(np.diff(darkest) > 0), darkest          # moving +x: to the right
    from PIL import Image
    with Image.open(out / "clip.webp") as im:
        assert im.n_frames == N_FRAMES and im.size == (48, 36)
        im.seek(1)
        im.load()
        assert im.info["duration"] == 42                   # 24 fps (a pattern declares none)


def test_dgsm_build_frames_are_what_the_clip_builds(scene, tmp_path):
    """Composable: dgsm-build --frames (--radial roi, as the in-process build) writes one
    DGSM per frame and relight --dgsm PATTERN reads them back; every frame's pixels equal
    the in-process clip's."""
    r = _invoke(scene, "dgsm-build", "seq.json", "--frames", "1:4:2", "--receivers", "floor.ply",
                "--lights", "lights.json", "--radial", "roi", "-o", tmp_path / "s_{frame:02d}.exr",
                "--occluders-out", tmp_path / "o_{frame:02d}.ply")
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["o_01.ply", "o_03.ply", "s_01.exr",
                                                         "s_03.exr"]
    common = ["--receivers", "floor.ply", "--probe", "scene", "--direct-light", "--camera",
              "cam.json", "--frames", "1:4:2"]
    r = _invoke(scene, "relight", "seq.json", *common, "--dgsm", tmp_path / "s_{frame:02d}.exr",
                "-o", tmp_path / "read_{frame}.exr")
    assert r.exit_code == 0, r.output
    r = _invoke(scene, "relight", "seq.json", *common, "--lights", "lights.json",
                "-o", tmp_path / "built_{frame}.exr")
    assert r.exit_code == 0, r.output
    for k in (1, 3):
        a, b = _pixels(tmp_path / f"read_{k}.exr"), _pixels(tmp_path / f"built_{k}.exr")
        np.testing.assert_array_equal(a.layer(""), b.layer(""))
        assert a.provenance()["settings"]["frame"] == k
        assert a.provenance()["inputs"]["dgsm"]["path"].endswith(f"s_{k:02d}.exr")
        assert b.provenance()["inputs"]["input"]["path"].endswith(f"ball_{k:03d}.ply")


def test_placement_applies_to_the_whole_sequence(scene, tmp_path):
    """fit/on-floor are resolved once (on the recording's first frame): the motion is kept,
    not re-centred per frame; a frame made alone is placed as in the clip."""
    from relight_cli.gaussians.placement import robust_bounds
    from relight_cli.gaussians.sequence import GaussianSource
    os.chdir(scene)
    s = GaussianSource("seq/ball_{frame:03d}.ply:fit=0.5;on-floor")
    assert s.frames == list(range(N_FRAMES)) and s.moves
    centres = [np.mean(robust_bounds(s.frame(k)), axis=0) for k in range(N_FRAMES)]
    assert centres[0][0] == pytest.approx(0.0, abs=1e-9)           # fitted on frame 0
    steps = np.diff([c[0] for c in centres])
    assert steps[0] > 0.3 and steps == pytest.approx(np.full(N_FRAMES - 1, steps[0]), rel=1e-6)
    assert robust_bounds(s.frame(0))[0][1] == pytest.approx(0.0, abs=1e-9)
    alone = GaussianSource("seq/ball_{frame:03d}.ply:fit=0.5;on-floor").frame(2)
    np.testing.assert_array_equal(alone.means, s.frame(2).means)


def test_hand_motion_as_gaussians(scene, tmp_path):
    """A hand.npz with frames is a moving avatar: two frames differ, --frame K equals the
    clip's frame K, and the PLY output (no camera) holds the posed hand."""
    hand = tmp_path / "hand.npz"
    r = _invoke(scene, "fit-geometry", "--pose", "random", "--n-frames", "2", "--seed", "3",
                "-o", hand)
    assert r.exit_code == 0, r.output
    r = _invoke(scene, "relight", f"{hand}:translate=0,0.2,0", "--frames", "all",
                "--probe", "scene", "--receivers", "floor.ply", "-o", tmp_path / "h_{frame}.ply")
    assert r.exit_code == 0, r.output
    from relight_cli.formats.gaussians_ply import read_gaussians
    a, b = read_gaussians(str(tmp_path / "h_0.ply")), read_gaussians(str(tmp_path / "h_1.ply"))
    assert len(a) == len(b) and not np.allclose(a.means, b.means)
    r = _invoke(scene, "relight", f"{hand}:translate=0,0.2,0", "--frame", "1", "--probe",
                "scene", "--receivers", "floor.ply", "-o", tmp_path / "one.ply")
    assert r.exit_code == 0, r.output
    np.testing.assert_array_equal(read_gaussians(str(tmp_path / "one.ply")).sh, b.sh)


def test_clip_subprocess(scene, tmp_path):
    """The console script renders a clip and its animated PNG."""
    r = run_relight("relight", "seq/ball_{frame:03d}.ply", "--frames", "0:2", *CLIP,
                    "-o", str(tmp_path / "f_{frame}.exr"), "--video", str(tmp_path / "c.png"),
                    cwd=scene)
    assert r.returncode == 0, r.stderr
    from PIL import Image
    with Image.open(tmp_path / "c.png") as im:
        assert im.n_frames == 2
    assert r.stderr.strip().splitlines()[-1] == f"wrote {tmp_path / 'c.png'}"


@pytest.mark.parametrize("case,args,code,words", [
    ("frames-without-motion", ["floor.ply", "--frames", "all", "--probe", "scene",
                               "--receivers", "floor.ply", "-o", "x_{frame}.ply"], 2, "moves"),
    ("no-frame-field", ["seq/ball_{frame:03d}.ply", "--frames", "all", *CLIP, "-o", "x.exr"],
     2, "{frame}"),
    ("video-without-frames", ["seq/ball_{frame:03d}.ply", *CLIP, "-o", "x.exr",
                              "--video", "c.webp"], 2, "--video"),
    ("video-extension", ["seq/ball_{frame:03d}.ply", "--frames", "all", *CLIP,
                         "-o", "x_{frame}.exr", "--video", "c.mp4"], 2, "--video"),
    ("lights-and-dgsm", ["seq/ball_{frame:03d}.ply", "--frames", "all", *CLIP,
                         "--dgsm", "s_{frame}.exr", "-o", "x_{frame}.exr"], 2, "--lights"),
    ("probe-scene-without-receivers", ["seq/ball_{frame:03d}.ply", "--probe", "scene",
                                       "-o", "x.ply"], 2, "--receivers"),
    ("probe-degree-without-scene", ["seq/ball_{frame:03d}.ply", "--probe", "p.json",
                                    "--probe-degree", "3", "-o", "x.ply"], 2, "--probe-degree"),
    ("shadow-size-without-lights", ["seq/ball_{frame:03d}.ply", "--probe", "scene",
                                    "--receivers", "floor.ply", "--shadow-size", "64",
                                    "-o", "x.ply"], 2, "--shadow-size"),
    ("shadow-size-bad", ["seq/ball_{frame:03d}.ply", *CLIP, "--shadow-size", "1x0",
                         "-o", "x.exr"], 2, "--shadow-size"),
    ("frame-out-of-range", ["seq/ball_{frame:03d}.ply", "--frame", "9", *CLIP, "-o", "x.exr"],
     2, "frame 9"),
    ("frames-select-none", ["seq/ball_{frame:03d}.ply", "--frames", "7:9", *CLIP,
                            "-o", "x_{frame}.exr"], 2, "selects no frame"),
    ("frame-and-frames", ["seq/ball_{frame:03d}.ply", "--frame", "1", "--frames", "all",
                          *CLIP, "-o", "x_{frame}.exr"], 2, "give one of them"),
    ("pattern-field-in-folder", ["seq_{frame}/b.ply", "--frames", "all", *CLIP,
                                 "-o", "x_{frame}.exr"], 2, "file name"),
    ("pattern-bad-field", ["seq/ball_{frame[0]}.ply", *CLIP, "-o", "x.exr"], 2, "{frame"),
    ("no-file-matches", ["seq/none_{frame:03d}.ply", *CLIP, "-o", "x.exr"], 1, "no file"),
    ("missing-frame", ["gap/ball_{frame:03d}.ply", *CLIP, "-o", "x.exr"], 1, "frame 1"),
    ("missing-dgsm-frame", ["seq/ball_{frame:03d}.ply", "--frames", "all", "--receivers",
                            "floor.ply", "--dgsm", "nodgsm_{frame}.exr", "--probe", "scene",
                            "--camera", "cam.json", "-o", "x_{frame}.exr"], 1, "nodgsm_0.exr"),
    ("bad-index", ["bad.json", *CLIP, "-o", "x.exr"], 1, "'count'"),
    ("index-topology", ["topo.json", "--frames", "all", *CLIP, "-o", "x_{frame}.exr"], 1,
     "same topology"),
])
def test_clip_bad_input(scene, tmp_path, case, args, code, words):
    """One line naming the problem, exit 1/2, nothing written, the inputs untouched."""
    import shutil
    work = tmp_path / "w"
    shutil.copytree(scene, work)
    (work / "gap").mkdir()
    for k in (0, 2):
        shutil.copy(work / "seq" / f"ball_{k:03d}.ply", work / "gap" / f"ball_{k:03d}.ply")
    (work / "bad.json").write_text(json.dumps({"format": "relight/gaussian-sequence",
                                               "version": 1, "frames": "seq/ball_{frame:03d}.ply",
                                               "count": 0}))
    (work / "topo").mkdir()
    write_gaussians(str(work / "topo" / "b_0.ply"), ball([0, 0.3, 0], n=100))
    write_gaussians(str(work / "topo" / "b_1.ply"), ball([0, 0.3, 0], n=90))
    (work / "topo.json").write_text(json.dumps({"format": "relight/gaussian-sequence",
                                                "version": 1, "frames": "topo/b_{frame}.ply",
                                                "count": 2, "same_topology": True}))
    before = {p: p.stat().st_mtime_ns for p in work.rglob("*")}
    r = _invoke(work, "relight", *args)
    lines = [line for line in r.output.splitlines() if line.strip()]
    assert r.exit_code == code, r.output
    assert len(lines) == 1 and lines[0].startswith("relight relight: error: "), r.output
    assert words in lines[0], lines[0]
    assert {p: p.stat().st_mtime_ns for p in work.rglob("*")} == before


def test_dgsm_build_frames_bad_input(scene, tmp_path):
    """dgsm-build --frames: -o must hold {frame}; one line, exit 2, nothing written."""
    r = _invoke(scene, "dgsm-build", "seq.json", "--frames", "all", "--receivers", "floor.ply",
                "--lights", "lights.json", "-o", tmp_path / "s.exr")
    assert r.exit_code == 2 and "{frame}" in r.output and list(tmp_path.iterdir()) == []
    r = _invoke(scene, "dgsm-build", "floor.ply", "--frames", "all", "--t-max", "2",
                "--lights", "lights.json", "-o", tmp_path / "s_{frame}.exr")
    assert r.exit_code == 2 and "moves" in r.output and list(tmp_path.iterdir()) == []


def test_self_shadow_cli(scene, tmp_path):
    """--self-shadow (ours): an object shadowed by itself, built in-process (--lights) or
    by dgsm-build --self-shadow, the two equal; a map built without it is refused naming
    it; the option needs shadow maps."""
    import sys
    sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "gaussians"))
    from test_self_shadow import shelf
    g, _ = shelf()
    write_gaussians(str(tmp_path / "shelf.ply"), g)
    common = ["relight", tmp_path / "shelf.ply", "--receivers", "floor.ply", "--probe", "scene",
              "--shadow-strength", "1"]
    r = _invoke(scene, *common, "--lights", "lights.json", "--self-shadow",
                "-o", tmp_path / "self.ply")
    assert r.exit_code == 0, r.output
    r = _invoke(scene, *common, "--lights", "lights.json", "-o", tmp_path / "plain.ply")
    assert r.exit_code == 0, r.output
    from relight_cli.formats.gaussians_ply import read_gaussians
    a, b = read_gaussians(str(tmp_path / "self.ply")), read_gaussians(str(tmp_path / "plain.ply"))
    under = (g.means[:, 1] < 0.03) & (g.means[:, 0] < -0.01) & (np.abs(g.means[:, 2]) < 0.04)
    assert under.sum() > 50
    from relight_cli.formats.gaussians_ply import SH_C0
    ca, cb = 0.5 + SH_C0 * a.sh[:, 0, 0], 0.5 + SH_C0 * b.sh[:, 0, 0]
    assert cb[under].min() > 0 and np.median(ca[under] / cb[under]) < 0.5   # the shelf's shadow
    top = g.means[:, 1] > 0.03          # lit: never shadowed by itself (the 128² atlas's
    assert np.median(ca[top] / cb[top]) > 0.9    # texels blur the oblique lamp's edge a bit)
    r = _invoke(scene, "dgsm-build", tmp_path / "shelf.ply", "--receivers", "floor.ply",
                "--lights", "lights.json", "--radial", "roi", "--self-shadow",
                "-o", tmp_path / "s.exr")
    assert r.exit_code == 0, r.output
    r = _invoke(scene, *common, "--dgsm", tmp_path / "s.exr", "--self-shadow",
                "-o", tmp_path / "read.ply")
    assert r.exit_code == 0, r.output
    np.testing.assert_array_equal(read_gaussians(str(tmp_path / "read.ply")).sh, a.sh)
    r = _invoke(scene, "dgsm-build", tmp_path / "shelf.ply", "--receivers", "floor.ply",
                "--lights", "lights.json", "-o", tmp_path / "plain.exr")
    assert r.exit_code == 0, r.output
    r = _invoke(scene, *common, "--dgsm", tmp_path / "plain.exr", "--self-shadow",
                "-o", tmp_path / "x.ply")
    assert r.exit_code == 1 and "self-shadowing" in r.output
    assert r.output.strip().endswith(f"({tmp_path / 'plain.exr'})") and not (tmp_path / "x.ply").exists()
    r = _invoke(scene, "relight", tmp_path / "shelf.ply", "--probe", "scene", "--receivers",
                "floor.ply", "--self-shadow", "-o", tmp_path / "x.ply")
    assert r.exit_code == 2 and "--self-shadow" in r.output


def test_a_path_moves_a_static_object_and_its_shadow(scene, tmp_path):
    """path=FILE.json (a relight/path): a static ball walks along x over three frames; its
    frames are the path's, its shadow follows; bad paths are one line naming the file;
    path= outside a clip command is a usage error."""
    walk = tmp_path / "walk.json"
    walk.write_text(json.dumps({"format": "relight/path", "version": 1, "fps": 12,
                                "translations": [[-0.2, 0, 0], [0.0, 0, 0], [0.2, 0, 0]]}))
    r = _invoke(scene, "relight", f"seq/ball_000.ply:path={walk}", "--frames", "all", *CLIP,
                "-o", tmp_path / "w_{frame}.exr")
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in tmp_path.glob("w_*.exr")) == ["w_0.exr", "w_1.exr", "w_2.exr"]
    from relight_cli.gaussians.sequence import GaussianSource
    s = GaussianSource(f"{scene / 'seq' / 'ball_000.ply'}:translate=0,0.1,0;path={walk}")
    assert s.frames == [0, 1, 2] and s.fps == 12.0
    np.testing.assert_allclose(s.frame(2).means - s.frame(0).means, np.tile([0.4, 0, 0], (150, 1)),
                               atol=1e-12)
    np.testing.assert_allclose(s.frame(1).means.mean(axis=0)[1], 0.35, atol=0.02)
    r = _invoke(scene, "relight", f"seq/ball_000.ply:path={walk}", "--frames", "all",
                "--receivers", "floor.ply", "--probe", "scene", "--camera", "cam.json",
                "-o", tmp_path / "lit_{frame}.exr")
    assert r.exit_code == 0, r.output
    darkest = []
    for k in range(3):
        drop = (_pixels(tmp_path / f"lit_{k}.exr").layer("")
                - _pixels(tmp_path / f"w_{k}.exr").layer("")).sum(axis=2)
        darkest.append(np.unravel_index(np.argmax(drop), drop.shape)[1])
    assert darkest[0] < darkest[1] < darkest[2], darkest
    for body, words in (({"format": "relight/path", "version": 1, "translations": []},
                         "'translations'"),
                        ({"format": "relight/path", "version": 1,
                          "translations": [[0, 0]]}, "[x, y, z]"),
                        ({"format": "relight/path", "version": 1,
                          "translations": [[0, 0, 1e7]]}, "within"),
                        ({"format": "relight/path", "version": 1, "fps": -1,
                          "translations": [[0, 0, 0]]}, "'fps'")):
        bad = tmp_path / "bad.json"
        bad.write_text(json.dumps(body))
        r = _invoke(scene, "relight", f"seq/ball_000.ply:path={bad}", "--frames", "all", *CLIP,
                    "-o", tmp_path / "b_{frame}.exr")
        assert r.exit_code == 1 and words in r.output and f"({bad})" in r.output, r.output
    r = _invoke(scene, "relight", "seq/ball_{frame:03d}.ply:path=" + str(walk), "--frames",
                "all", *CLIP, "-o", tmp_path / "b_{frame}.exr")        # 4 frames, 3 steps
    assert r.exit_code == 1 and "3 translation(s)" in r.output
    r = _invoke(scene, "metrics", "shadow", tmp_path / "w_0.exr", tmp_path / "w_1.exr",
                "--roi-avatar", f"seq/ball_000.ply:path={walk}", "--camera", "cam.json",
                "-o", tmp_path / "m.json")                  # one frame: no path there
    assert r.exit_code == 2 and "path=FILE.json" in r.output, r.output
    assert not list(tmp_path.glob("b_*")) and not (tmp_path / "m.json").exists()


def test_two_moving_avatars_shadow_each_other(scene, tmp_path):
    """Several avatars at once: a ball moving along x (a '{frame}' pattern) passes over a
    second ball walking below it (a path); per frame the in-process maps are built per
    object (groups), so the lower ball is darkened only where the upper one is above it."""
    walk = tmp_path / "walk.json"
    walk.write_text(json.dumps({"format": "relight/path", "version": 1,
                                "translations": [[0.1, -0.15, 0.0]] * N_FRAMES}))
    r = _invoke(scene, "relight", "seq/ball_{frame:03d}.ply", "--object",
                f"seq/ball_000.ply:path={walk}", "--frames", "all", "--receivers", "floor.ply",
                "--lights", "lights.json", "--probe", "scene", "--shadow-strength", "1",
                "-o", tmp_path / "o_{frame}.ply")
    assert r.exit_code == 0, r.output
    from relight_cli.formats.gaussians_ply import SH_C0, read_gaussians
    lower = []
    for k in range(N_FRAMES):
        g = read_gaussians(str(tmp_path / f"o_{k}.ply"))
        assert len(g) == 300                       # both objects, IN first
        lower.append(float((0.5 + SH_C0 * g.sh[150:, 0]).mean()))
    # the upper ball is at x = -0.3 + 0.2 k: over the lower one (x = -0.2) at k = 0, 1
    assert min(lower[:2]) < 0.8 * max(lower[2:]), lower


def test_avatar_export_quirks_are_repaired(scene, tmp_path):
    """What avatar exports get wrong: non-unit quaternions (normalised on read), zero and
    1e-12 m scales (a point, a sheet of no thickness): the clip renders finite pixels and
    the read rotations are unit."""
    import plyfile

    from relight_cli.formats.gaussians_ply import read_gaussians
    (tmp_path / "seq").mkdir()
    for k in range(2):
        g = ball([0.1 * k, 0.25, 0.0])
        g.scales[0] = 0.0
        g.scales[1] = [0.05, 1e-12, 0.05]
        write_gaussians(str(tmp_path / f"t_{k}.ply"), g)
        v = plyfile.PlyData.read(str(tmp_path / f"t_{k}.ply"), mmap=False)["vertex"].data.copy()
        for c in ("rot_0", "rot_1", "rot_2", "rot_3"):
            v[c] = v[c] * 3.7
        plyfile.PlyData([plyfile.PlyElement.describe(v, "vertex")]).write(
            str(tmp_path / "seq" / f"b_{k}.ply"))
    back = read_gaussians(str(tmp_path / "seq" / "b_1.ply"))
    np.testing.assert_allclose(np.linalg.norm(back.rotations, axis=1), 1.0, atol=1e-6)
    r = _invoke(scene, "relight", str(tmp_path / "seq" / "b_{frame}.ply"), "--frames", "all",
                *CLIP, "--self-shadow", "-o", tmp_path / "o_{frame}.exr")
    assert r.exit_code == 0, r.output
    for k in range(2):
        assert np.isfinite(_pixels(tmp_path / f"o_{k}.exr").layer("")).all()


def test_preview_exposure_is_one_scale_for_every_picture(scene, tmp_path, monkeypatch):
    """--preview-exposure (issue 53: previews each exposed on their own hide the change
    they show): every preview of a sequence, and its video, tone-mapped with the one
    scale given (the tone mapping itself is tests/render's); without --preview it is a
    usage error."""
    import relight_cli.preview as P
    from relight_cli.tonemap import tonemap
    used, video = [], []
    real = P.write_preview
    monkeypatch.setattr(P, "write_preview", lambda path, rgb, exposure=None, **kw: (
        used.append(exposure), real(path, rgb, exposure=exposure, **kw))[1])
    monkeypatch.setattr("relight_cli.tonemap.tonemap", lambda rgb, exposure=None, **kw: (
        video.append(exposure), tonemap(rgb, exposure, **kw))[1])
    r = _invoke(scene, "relight", "seq/ball_{frame:03d}.ply", "--frames", "0:3", *CLIP,
                "-o", tmp_path / "f_{frame}.exr", "--preview", tmp_path / "p_{frame}.png",
                "--video", tmp_path / "v.webp", "--preview-exposure", "2")
    assert r.exit_code == 0, r.output
    assert used == [2.0] * 3 and video == [2.0] * 6, (used, video)   # previews + video
    r = _invoke(scene, "relight", "seq/ball_{frame:03d}.ply", "--frame", "0", *CLIP,
                "-o", tmp_path / "x.exr", "--preview-exposure", "2")
    assert r.exit_code == 2 and "--preview-exposure" in r.output
