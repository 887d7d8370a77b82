"""``relight fit-geometry``: help, posing, fitting, report, preview, bad input."""

from __future__ import annotations

import json

import numpy as np
from cli_errors import _one_error
from conftest import run_relight, shared_path

from relight_cli.formats.hand_npz import read_hand
from relight_cli.hand import poses as P
from relight_cli.hand.model import PARENTS, builtin_hand
from relight_cli.hand.skinning import posed_joints


def _keypoints(n=3, seed=0):
    rest = builtin_hand(pose=None).rest_joints
    poses = P.random_poses(n, seed=seed)
    trans = np.random.default_rng(seed).normal(0, 0.05, (n, 3))
    return posed_joints(poses, trans, rest, PARENTS)


def test_help(run_cli):
    r = run_cli("fit-geometry", "--help")
    assert r.exit_code == 0
    for opt in ("--template", "--pose", "--keypoints", "--scans", "--interpolate", "--report",
                "--preview", "--two-hands"):
        assert opt in r.output


def test_named_pose_with_preview(run_cli, tmp_path):
    out, png = tmp_path / "hand.npz", tmp_path / "hand.png"
    r = run_cli("fit-geometry", "--pose", "fist", "-o", out, "--preview", png,
                "--preview-size", "96x80", "-q")
    assert r.exit_code == 0, r.output
    hand = read_hand(str(out))
    np.testing.assert_allclose(hand.poses[0], P.named_pose("fist"))
    assert len(hand.coarse.vertices) == len(builtin_hand().coarse.vertices)
    from relight_cli.formats.image import read_image
    from relight_cli.preview import picture_box
    img, _ = read_image(str(png))
    x0, y0, k = picture_box(img.shape, 80, 96)          # the 96x80 render under its caption
    img = img[y0:y0 + 80 * k:k, x0:x0 + 96 * k:k]
    assert img.shape[:2] == (80, 96)
    # The hand covers part of the frame and is lit: not a uniform image.
    assert img.std() > 0.05 and (img.max(-1) > 0.3).mean() > 0.05


def test_random_poses_are_seeded_and_two_hands(run_cli, tmp_path):
    a, b = tmp_path / "a.npz", tmp_path / "b.npz"
    for path in (a, b):
        r = run_cli("fit-geometry", "--pose", "random", "--n-frames", "4", "--seed", "9",
                    "--two-hands", "-o", path, "-q")
        assert r.exit_code == 0, r.output
    ha, hb = read_hand(str(a)), read_hand(str(b))
    np.testing.assert_array_equal(ha.poses, hb.poses)
    assert ha.n_frames == 4 and [h.name for h in ha.hands] == ["right", "left"]
    assert ha.hands[1].mirror


def test_pose_json_and_npz_template(run_cli, tmp_path):
    poses = P.random_poses(2, seed=4)
    spec = tmp_path / "poses.json"
    spec.write_text(json.dumps({"poses": poses.tolist(), "translations": [[0, 0, 0], [0, 0.1, 0]]}))
    first = tmp_path / "first.npz"
    assert run_cli("fit-geometry", "--pose", spec, "-o", first, "-q").exit_code == 0
    h = read_hand(str(first))
    np.testing.assert_allclose(h.poses, poses)
    np.testing.assert_allclose(h.translations[1], [0, 0.1, 0])
    names = tmp_path / "names.json"
    names.write_text(json.dumps({"names": ["open", "ok"]}))
    second = tmp_path / "second.npz"
    r = run_cli("fit-geometry", "--template", first, "--pose", names, "-o", second, "-q")
    assert r.exit_code == 0, r.output
    np.testing.assert_allclose(read_hand(str(second)).poses[1], P.named_pose("ok"), atol=1e-12)


def test_gltf_template(run_cli, tmp_path):
    glb = shared_path("hands", "webxr-generic-hand-left.glb")
    out = tmp_path / "g.npz"
    r = run_cli("fit-geometry", "--template", glb, "--pose", "fist", "-o", out, "-q")
    assert r.exit_code == 0, r.output
    h = read_hand(str(out))
    assert h.side == "left" and h.inverse_bind_matrices is not None
    # The fist of a left glTF hand curls: fingertips closer to the wrist.
    j = posed_joints(h.poses[0], h.translations[0], h.rest_joints, h.parents)
    rest = h.rest_joints
    assert np.linalg.norm(j[14] - j[0]) < 0.75 * np.linalg.norm(rest[14] - rest[0])


def test_fit_keypoints_json_interpolate_report(run_cli, tmp_path):
    kp = _keypoints(3, seed=1)
    conf = np.ones((3, 25, 1))
    conf[1, 20:25] = 0                              # pinky missing in the middle keyframe
    data = np.concatenate([kp, conf], -1)
    # Frame 6 measures no joint at all: a missing frame, filled like the others.
    data = np.concatenate([data[:2], np.zeros((1, 25, 4)), data[2:]])
    spec = tmp_path / "kp.json"
    spec.write_text(json.dumps({"format": "relight/keypoints", "version": 1,
                                "frames": [0, 4, 6, 8], "keypoints": data.tolist()}))
    out, report = tmp_path / "fit.npz", tmp_path / "fit.json"
    r = run_cli("fit-geometry", "--keypoints", spec, "--interpolate", "--iterations", "90",
                "-o", out, "--report", report, "-q")
    assert r.exit_code == 0, r.output
    h = read_hand(str(out))
    assert h.n_frames == 9                          # frames 0..8, 1-3 and 5-7 by slerp
    rep = json.loads(report.read_text())
    assert rep["output_frames"] == list(range(9))
    assert [row["frame"] for row in rep["per_frame"]] == [0, 4, 8]
    assert rep["frames_without_joints"] == [6]
    assert rep["per_frame"][1]["observed_joints"] == 20
    assert rep["mpjpe_mm"] < 5.0
    # Keyframes reproduce the fitted joints; in-betweens are slerps of them.
    j0 = posed_joints(h.poses[0], h.translations[0], h.rest_joints, PARENTS)
    assert np.linalg.norm(j0 - kp[0], axis=1).mean() < 0.005
    mid = P.slerp(h.poses[0], h.poses[4], 0.5)
    np.testing.assert_allclose(h.poses[2], mid, atol=1e-9)
    np.testing.assert_allclose(h.poses[6], P.slerp(h.poses[4], h.poses[8], 0.5), atol=1e-9)


def test_fit_npy_with_scan_subprocess(tmp_path):
    """The installed console script, fitting .npy keypoints plus a PLY scan."""
    import trimesh

    kp = _keypoints(1, seed=2)
    npy = tmp_path / "kp.npy"
    np.save(npy, kp)
    rest = builtin_hand(pose=None)
    from relight_cli.hand.skinning import lbs
    pose = P.random_poses(1, seed=2)[0]
    t = np.random.default_rng(2).normal(0, 0.05, (1, 3))[0]
    v = lbs(rest.coarse.vertices, rest.coarse.weights, rest.rest_joints, PARENTS, pose, t)
    trimesh.Trimesh(v, rest.coarse.faces, process=False).export(tmp_path / "scan_000.ply")
    out, report = tmp_path / "fit.npz", tmp_path / "r.json"
    r = run_relight("fit-geometry", "--keypoints", npy, "--scans", str(tmp_path / "scan_*.ply"),
                    "--iterations", "60", "-o", out, "--report", report)
    assert r.returncode == 0, r.stderr
    assert r.stdout == ""
    rep = json.loads(report.read_text())
    assert rep["per_frame"][0]["scan_mm"] < 1.0 and rep["mpjpe_mm"] < 3.0
    prov = json.loads(str(np.load(out)["provenance"]))
    assert "keypoints" in prov["inputs"] and "scan0" in prov["inputs"]


def test_bad_keypoints(run_cli, tmp_path):
    out = tmp_path / "o.npz"
    kp = _keypoints(2)
    nan = kp.copy()
    nan[1, 3, 0] = np.nan
    np.save(tmp_path / "nan.npy", nan)
    _one_error(run_cli("fit-geometry", "--keypoints", tmp_path / "nan.npy", "-o", out), 1,
               "NaN")
    np.save(tmp_path / "j21.npy", kp[:, :21])
    _one_error(run_cli("fit-geometry", "--keypoints", tmp_path / "j21.npy", "-o", out), 1,
               "21 joints")
    (tmp_path / "bad.json").write_text("{not json")
    _one_error(run_cli("fit-geometry", "--keypoints", tmp_path / "bad.json", "-o", out), 1,
               "invalid JSON")
    (tmp_path / "v2.json").write_text(json.dumps({"format": "relight/keypoints", "version": 2,
                                                  "keypoints": kp.tolist()}))
    _one_error(run_cli("fit-geometry", "--keypoints", tmp_path / "v2.json", "-o", out), 1,
               "version 2")
    conf = np.concatenate([kp, np.full((2, 25, 1), 1.5)], -1)
    np.save(tmp_path / "conf.npy", conf)
    _one_error(run_cli("fit-geometry", "--keypoints", tmp_path / "conf.npy", "-o", out), 1,
               "confidences")
    _one_error(run_cli("fit-geometry", "--keypoints", tmp_path / "none.npy", "-o", out), 1,
               "no such file")
    assert not out.exists()


def test_bad_scans_templates_and_usage(run_cli, tmp_path):
    out = tmp_path / "o.npz"
    np.save(tmp_path / "kp.npy", _keypoints(1))
    _one_error(run_cli("fit-geometry", "--scans", str(tmp_path / "nothing_*.ply"), "-o", out), 2,
               "matches no files")
    (tmp_path / "empty.ply").write_text("")
    _one_error(run_cli("fit-geometry", "--keypoints", tmp_path / "kp.npy", "--scans",
                       tmp_path / "empty.ply", "-o", out), 1)
    _one_error(run_cli("fit-geometry", "--pose", "wave", "-o", out), 2, "--pose must be")
    _one_error(run_cli("fit-geometry", "--pose", "fist", "--keypoints", tmp_path / "kp.npy",
                       "-o", out), 2)
    _one_error(run_cli("fit-geometry", "--pose", "fist", "--n-frames", "3", "-o", out), 2)
    _one_error(run_cli("fit-geometry", "--template", "builtin:middle", "-o", out), 2)
    (tmp_path / "t.obj").write_text("v 0 0 0\n")
    _one_error(run_cli("fit-geometry", "--template", tmp_path / "t.obj", "-o", out), 1,
               "unknown template type")
    (tmp_path / "broken.npz").write_bytes(b"PK\x03\x04broken")
    _one_error(run_cli("fit-geometry", "--template", tmp_path / "broken.npz", "-o", out), 1)
    _one_error(run_cli("fit-geometry", "-o", tmp_path / "nodir" / "o.npz"), 2,
               "output folder does not exist")
    (tmp_path / "bad_pose.json").write_text(json.dumps({"poses": [[0, 0, 0]] * 24}))
    _one_error(run_cli("fit-geometry", "--pose", tmp_path / "bad_pose.json", "-o", out), 1,
               "shape")
    assert not out.exists()
    keep = tmp_path / "keep.npz"
    keep.write_bytes(b"keep")
    _one_error(run_cli("fit-geometry", "--no-clobber", "-o", keep), 2)
    assert keep.read_bytes() == b"keep"
