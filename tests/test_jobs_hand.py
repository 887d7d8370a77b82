"""The hand jobs of issue 22 (relight_cli.jobs.bake_features / fit_geometry /
synth_capture) and the input loaders they take their inputs from (relight_cli.inputs):
each job's arrays equal what its command writes for the same inputs, a fit recovers a
known pose, and the loaders keep their one-line errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from relight_cli import inputs as I
from relight_cli.errors import DataError, UsageProblem


def _cli(run_cli, *args):
    r = run_cli(*args)
    assert r.exit_code == 0, r.output
    return r


# ---------------------------------------------------------------- bake-features


def test_bake_job_equals_the_cli(run_cli, tmp_path):
    """Two env maps, per-vertex features, GGX and Phong: the job's texel maps, per-vertex
    arrays and provenance settings are what bake-features writes."""
    from relight_cli.features import FeatureSettings
    from relight_cli.formats.features_exr import read_features, read_vertex_features
    from relight_cli.jobs import bake_features as J

    _cli(run_cli, "bake-features", "builtin:right", "builtin:sky", "builtin:studio",
         "-o", tmp_path / "f_{env}.exr", "--per-vertex", tmp_path / "f_{env}.npz",
         "--res", "24x16", "--env-res", "8x4", "--specular", "both", "--shininess", "16",
         "--roughness", "0.4", "-q")
    envs = [I.load_envmap("builtin:sky"), I.load_envmap("builtin:studio")]
    options = J.BakeOptions(FeatureSettings(shininess=(16,), specular="both", roughness=0.4),
                            env_res=(4, 8), tex_res=(16, 24))
    [frame] = list(J.bake(I.load_hand("builtin:right"), [0], envs, options))
    assert frame.frame == 0 and frame.hands == ["right"] and frame.rays_traced > 0
    for k, name in enumerate(("sky", "studio")):
        written = read_features(str(tmp_path / f"f_{name}.exr"))
        assert set(written.layers) == set(frame.maps[k]) >= {"diffuse", "phong16", "ggx",
                                                              "visibility", "mask"}
        for layer, value in frame.maps[k].items():
            np.testing.assert_array_equal(written.layers[layer], value, err_msg=layer)
        vertex = read_vertex_features(str(tmp_path / f"f_{name}.npz"))
        for key, value in frame.vertex[k].items():     # written as float32 / int32
            np.testing.assert_array_equal(vertex[key], np.asarray(value).astype(vertex[key].dtype),
                                          err_msg=key)
        record = json.loads(str(vertex["provenance"]))
        assert record["settings"] == {**frame.settings, "roughness": "0.4"}
    # the two env maps light the hand differently: the comparison above can tell them apart
    assert not np.allclose(frame.maps[0]["diffuse"], frame.maps[1]["diffuse"])


def test_bake_job_checks_env_maps_before_any_frame():
    """A map whose features would overflow float32 is refused when the job is called
    (before a frame is baked), naming the map; a viewer and a roughness map are used."""
    from relight_cli.features import FeatureSettings
    from relight_cli.jobs import bake_features as J

    bright = I.load_envmap("builtin:uniform")
    bright.radiance = np.full_like(bright.radiance, 3e36)
    options = J.BakeOptions(FeatureSettings(shininess=(), specular="ggx"), env_res=(4, 8),
                            tex_res=(8, 8))
    with pytest.raises(DataError, match="too bright") as err:
        J.bake(I.load_hand("builtin:right"), [0], [bright], options, names=["sun.exr"])
    assert "sun.exr" in str(err.value)
    # a constant roughness map equals the scalar; the viewer is the one given
    env = [I.load_envmap("builtin:studio")]
    eye = np.array([0.1, 0.3, 0.5])
    scalar = J.BakeOptions(FeatureSettings(shininess=(), specular="ggx", roughness=0.25),
                           env_res=(4, 8), tex_res=(8, 8), viewer=eye)
    mapped = J.BakeOptions(FeatureSettings(shininess=(), specular="ggx"), env_res=(4, 8),
                           tex_res=(8, 8), viewer=eye, roughness_map=np.full((4, 4), 0.25))
    hand = I.load_hand("builtin:right")
    [a], [b] = J.bake(hand, [0], env, scalar), J.bake(hand, [0], env, mapped)
    np.testing.assert_array_equal(a.viewer, eye)
    assert a.settings["view"] == [0.1, 0.3, 0.5] and b.settings["roughness"] == "map"
    np.testing.assert_allclose(a.vertex[0]["ggx"], b.vertex[0]["ggx"], rtol=1e-12)
    assert a.vertex[0]["ggx"].max() > 0


# ---------------------------------------------------------------- fit-geometry


def _known_keypoints(n: int, seed: int):
    from relight_cli.hand import poses as P
    from relight_cli.hand.model import PARENTS, builtin_hand
    from relight_cli.hand.skinning import posed_joints
    rest = builtin_hand(pose=None).rest_joints
    poses = P.random_poses(n, seed=seed)
    trans = np.random.default_rng(seed).normal(0, 0.05, (n, 3))
    return poses, trans, posed_joints(poses, trans, rest, PARENTS)


def test_fit_job_recovers_a_known_pose_as_the_cli_does(run_cli, tmp_path):
    """Keypoints of a known pose: the fitted joints land on them (and the fitted hand is
    the one fit-geometry writes for the same keypoints and seed)."""
    from relight_cli.formats.hand_npz import read_hand
    from relight_cli.formats.keypoints import Keypoints
    from relight_cli.hand.skinning import posed_joints
    from relight_cli.jobs import fit_geometry as J

    _, _, joints = _known_keypoints(1, seed=4)
    np.save(tmp_path / "kp.npy", joints)
    _cli(run_cli, "fit-geometry", "--keypoints", tmp_path / "kp.npy", "--iterations", "40",
         "-o", tmp_path / "fit.npz", "--report", tmp_path / "fit.json", "-q")
    template = I.load_template("builtin:right")
    kp = I.load_keypoints(str(tmp_path / "kp.npy"), template)
    assert isinstance(kp, Keypoints) and kp.positions.shape == (1, 25, 3)
    lines = []
    fitted = J.fit(template, kp, None, J.FitGeometryOptions(iterations=40), log=lines.append)
    hand = fitted.hand
    got = posed_joints(hand.poses, hand.translations, hand.rest_joints, hand.parents)
    assert np.abs(got - joints).max() < 0.004                      # metres: within 4 mm
    assert fitted.report["mpjpe_mm"] < 3.0
    assert lines[0].startswith("template template: right hand") and "fitting 1" in lines[-1]
    written = read_hand(str(tmp_path / "fit.npz"))
    np.testing.assert_array_equal(written.poses, hand.poses)
    np.testing.assert_array_equal(written.coarse.vertices, hand.coarse.vertices)
    report = json.loads((tmp_path / "fit.json").read_text())
    assert report["per_frame"] == fitted.report["per_frame"]
    assert report["provenance"]["settings"]["iterations"] == fitted.settings["iterations"] == 40


def test_pose_job_and_pose_loader(tmp_path):
    from relight_cli.hand import poses as P
    from relight_cli.jobs import fit_geometry as J

    template = I.load_template("builtin:left")
    poses, trans = I.load_poses("random", 3, 5, template)
    assert poses.shape == (3, 25, 3) and not np.allclose(poses[0], poses[1])
    (tmp_path / "p.json").write_text(json.dumps({"names": ["fist", "ok"]}))
    poses, trans = I.load_poses(str(tmp_path / "p.json"), 1, 0, template)
    np.testing.assert_array_equal(poses[1], P.named_pose("ok", "left", template.rest_joints))
    fitted = J.pose(template, poses, trans, two_hands=True)
    assert fitted.settings == {"frames": 2}
    assert fitted.report == {"frames": 2, "fitted": False}
    assert [h.poses.shape for h in fitted.hand.hands] == [(2, 25, 3)] * 2
    with pytest.raises(UsageProblem, match="--pose must be"):
        I.load_poses("wave", 1, 0, template)
    (tmp_path / "bad.json").write_text(json.dumps({"poses": [[0, 0, 0]]}))
    with pytest.raises(DataError, match="shape"):
        I.load_poses(str(tmp_path / "bad.json"), 1, 0, template)


def test_keypoint_and_template_loaders(tmp_path):
    """Leap recordings cut to a frame range and checked against the template's side;
    the frame-range and template specs' errors."""
    from conftest import shared_path

    assert I.frame_range("0:300:10") == slice(0, 300, 10)
    assert I.frame_range("5:") == slice(5, None, None)
    for bad in ("1", "a:b", "-1:4", "0:4:0"):
        with pytest.raises(UsageProblem, match="--frame-range"):
            I.frame_range(bad)
    with pytest.raises(UsageProblem, match="unknown built-in template"):
        I.load_template("builtin:two")
    with pytest.raises(UsageProblem, match="--hand must be"):
        I.leap_hand("both")
    assert I.leap_hand("7") == 7
    leap = shared_path("hands", "leap", "pinch.json")
    if not leap.exists():
        pytest.skip("no shared Leap recording here")
    kp = I.load_keypoints(str(leap), I.load_template("builtin:right"),
                          frames=I.frame_range("0:40:10"))
    np.testing.assert_array_equal(kp.frames, [0, 10, 20, 30])
    assert kp.source is not None and kp.positions.shape == (4, 25, 3)
    with pytest.raises(DataError, match="left hand"):
        I.load_keypoints(str(leap), I.load_template("builtin:left"))
    with pytest.raises(DataError, match="no keypoint frames"):
        I.load_keypoints(str(leap), I.load_template("builtin:right"),
                         frames=I.frame_range("100000:"))


def test_scan_loaders(tmp_path):
    import trimesh

    from relight_cli.hand.model import builtin_hand
    rest = builtin_hand(pose=None)
    for i in range(2):
        trimesh.Trimesh(rest.coarse.vertices + i, rest.coarse.faces,
                        process=False).export(tmp_path / f"scan_{i}.ply")
    paths = I.scan_paths(str(tmp_path / "scan_*.ply"))
    assert [p.rsplit("/", 1)[1] for p in paths] == ["scan_0.ply", "scan_1.ply"]
    a, b = I.load_scans(paths, seed=1)
    assert a.shape == (5000, 3) and b.mean(0) == pytest.approx(a.mean(0) + 1, abs=0.01)
    np.testing.assert_array_equal(I.load_scans(paths, seed=1)[1], b)     # seeded
    with pytest.raises(UsageProblem, match="matches no files"):
        I.scan_paths(str(tmp_path / "none_*.ply"))
    (tmp_path / "empty.ply").write_text("")
    with pytest.raises(DataError):
        I.load_scans([str(tmp_path / "empty.ply")])


# ---------------------------------------------------------------- synth-capture


def test_light_stage_job_equals_the_cli(run_cli, tmp_path):
    """The job's plan (key, frames, lit LEDs, recorded settings) and its renders are what
    synth-capture writes (images are half floats)."""
    from relight_cli.formats import capture as C
    from relight_cli.jobs import synth_capture as J

    out = tmp_path / "cap"
    _cli(run_cli, "synth-capture", "-o", out, "--cameras", "2", "--leds", "6", "--group", "2",
         "--frames", "2", "--full-every", "2", "--size", "10", "--tex-res", "32", "--aa", "1",
         "--eval-poses", "1", "--eval-cameras", "1", "--eval-envs", "builtin:sky",
         "--eval-env-res", "16x8", "--seed", "2", "-q")
    settings = J.StageSettings(cameras=2, lights=6, group=2, frames=2, full_every=2, res=10,
                               tex_res=32, aa=1, seed=2, eval_env_res=(8, 16))
    stage = J.light_stage(I.load_hand("builtin:right"), [I.load_envmap("builtin:sky")],
                          settings, eval_poses=1)
    cap = C.read_capture(str(out))
    assert stage.key == cap.key and json.loads(json.dumps(stage.record)) == cap.settings
    assert [f.lights_on for f in stage.plan.frames] == [f.lights_on for f in cap.frames]
    assert stage.plan.frames[1].lit == "group"
    frame = stage.plan.frames[1]
    renders = list(stage.frame(frame, stage.plan.cameras[1:]))
    assert [r.camera.name for r in renders] == ["cam001"] and renders[0].hand_masks is None
    rgb, mask = C.read_image(str(out / C.image_path(1, "cam001")))
    np.testing.assert_array_equal(rgb, renders[0].image.astype(np.float16).astype(np.float32))
    np.testing.assert_array_equal(mask, renders[0].mask.astype(np.float16).astype(np.float32))
    assert renders[0].mask.mean() > 0.01
    [held] = stage.held_out(0, 0, stage.plan.cameras[:1])
    rgb, _ = C.read_image(str(out / cap.evaluation["renders"][0]["image"]))
    np.testing.assert_array_equal(rgb, held.image.astype(np.float16).astype(np.float32))
    assert not np.allclose(held.image, renders[0].image)


def test_make_capture_writes_the_clis_folder(run_cli, tmp_path):
    """``jobs.synth_capture.make_capture`` (what the studies call) writes the folder
    ``synth-capture`` writes: the same files, index (but the provenance's command line,
    empty from Python) and pixels; a second call resumes and renders nothing."""
    from relight_cli.formats import capture as C
    from relight_cli.jobs import synth_capture as J

    args = dict(cameras=2, lights=6, group=2, frames=3, res=10, tex_res=32, aa=1, seed=4,
                eval_poses=1, eval_cameras=1, eval_envs=["builtin:sky"], eval_env_res=(8, 16))
    cli_out, lib_out = tmp_path / "cli", tmp_path / "lib"
    _cli(run_cli, "synth-capture", "builtin:two", "-o", cli_out, "--cameras", "2", "--leds",
         "6", "--group", "2", "--frames", "3", "--size", "10", "--tex-res", "32", "--aa", "1",
         "--seed", "4", "--eval-poses", "1", "--eval-cameras", "1", "--eval-envs",
         "builtin:sky", "--eval-env-res", "16x8", "-q")
    capture, rendered, skipped = J.make_capture(str(lib_out), "builtin:two", **args)
    assert (rendered, skipped) == (3 * 2 + 1, 0)
    files = sorted(p.relative_to(cli_out) for p in cli_out.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(lib_out) for p in lib_out.rglob("*") if p.is_file())

    def index(folder):
        obj = json.loads((folder / C.INDEX).read_text())
        return obj, obj["provenance"].pop("command")
    (lib, lib_command), (cli, cli_command) = index(lib_out), index(cli_out)
    assert lib == cli and lib_command == ""      # (the CLI run before it has ended)
    assert cli_command.startswith("relight synth-capture builtin:two -o ")
    for rel in files:
        if rel.suffix == ".exr" and rel.parts[:2] != ("eval", "envs"):
            for a, b in zip(C.read_image(str(cli_out / rel)), C.read_image(str(lib_out / rel))):
                np.testing.assert_array_equal(a, b)
    assert J.make_capture(str(lib_out), "builtin:two", **args)[1:] == (0, 3 * 2 + 1)
