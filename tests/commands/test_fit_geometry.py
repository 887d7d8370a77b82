"""``relight fit-geometry``: help, posing, fitting, report, preview, bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest
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


# ----------------------------------------------------------------------------- two hands

def _mirror_leap(recording, missing_left=(), missing_right=()):
    """A two-hand Leap recording from a one-hand (right) one: the right hand's positions
    mirrored across x = 0 make a left hand (type "left", its own ids); the right hand is
    taken out of the frames in ``missing_right``, the left one out of ``missing_left``."""
    import copy
    out = copy.deepcopy(recording)
    for i, frame in enumerate(out["frames"]):
        hands, pointables = [], []
        for h in frame["hands"]:
            if i not in missing_right:
                hands.append(h)
                pointables += [p for p in frame["pointables"] if p["handId"] == h["id"]]
            if i in missing_left:
                continue
            left = {**h, "id": h["id"] + 1000, "type": "left"}
            hands.append(left)
            for p in frame["pointables"]:
                if p["handId"] == h["id"]:
                    q = {**p, "handId": left["id"], "id": p["id"] + 100000}
                    for key in ("carpPosition", "mcpPosition", "pipPosition", "dipPosition",
                                "tipPosition"):
                        if key in q:
                            q[key] = [-q[key][0], q[key][1], q[key][2]]
                    pointables.append(q)
        frame["hands"], frame["pointables"] = hands, pointables
    return out


@pytest.fixture(scope="module")
def two_hand_truth():
    """Known answer: one skeleton (bone scales ±5 %), a right hand in 5 frames of
    synthetic_truth (fist, claw, limits, random) and a left hand, the mirror image of
    the same skeleton in other poses, 0.25 m to the left (−x)."""
    from relight_cli.hand.fitting import synthetic_truth
    template = builtin_hand(pose=None)
    poses, trans, scales, rest, right = synthetic_truth(template, 5, seed=11)
    other = P.random_poses(5, seed=12, global_rotation=True)
    left = posed_joints(other, trans * 0.5, rest, PARENTS) * [-1.0, 1.0, 1.0] \
        + [-0.25, 0.0, 0.0]
    return right, left


def _two_hand_keypoints(path, right, left, right_frames, left_frames):
    path.write_text(json.dumps({
        "format": "relight/keypoints", "version": 1,
        "hands": [{"side": "left", "frames": list(left_frames),
                   "keypoints": left[list(left_frames)].tolist()},
                  {"side": "right", "frames": list(right_frames),
                   "keypoints": right[list(right_frames)].tolist()}]}))
    return path


def test_two_hands_known_answer_and_missing_frames(run_cli, tmp_path, two_hand_truth):
    """Issue 53: one call fits both hands of a two-hand file into one two-hand hand.npz:
    hand 0 the right hand, hand 1 the left (mirrored model), each on its own targets
    (not swapped, not a mirror image of the wrong side); a frame where one hand is
    missing is that hand's missing frame only."""
    from relight_cli.hand.scene import handedness, posed_joints_world
    right, left = two_hand_truth
    # right missing in frame 1, left missing in frame 3 (a 'hands' file: both by default)
    kp = _two_hand_keypoints(tmp_path / "two.json", right, left, [0, 2, 3, 4], [0, 1, 2, 4])
    out, report = tmp_path / "two.npz", tmp_path / "fit.json"
    r = run_cli("fit-geometry", "--keypoints", kp, "--iterations", "150", "-o", out,
                "--report", report, "-q")
    assert r.exit_code == 0, r.output
    hand, rep = read_hand(str(out)), json.loads(report.read_text())
    assert handedness(hand) == ["right", "left"] and [h.mirror for h in hand.hands] == \
        [False, True]
    # without --interpolate only the frames holding both hands are written ...
    assert rep["output_frames"] == [0, 2, 4] and hand.n_frames == 3
    by_hand = {h["hand"]: h for h in rep["hands"]}
    assert by_hand["right"]["frames_left_out"] == [3] and by_hand["left"]["frames_left_out"] == [1]
    # ... but each hand is fitted in every frame it has, and the report says which is which
    assert [(row["hand"], row["frame"]) for row in rep["per_frame"]] == \
        [("right", f) for f in (0, 2, 3, 4)] + [("left", f) for f in (0, 1, 2, 4)]
    for k, frame in enumerate(rep["output_frames"]):
        joints = posed_joints_world(hand, k)
        for index, truth in enumerate((right, left)):
            err = np.linalg.norm(joints[index] - truth[frame], axis=-1) * 1000
            # noise-free targets of one shared skeleton (measured: mean ≤ 0.3 mm)
            assert err.mean() < 1.0 and err.max() < 4.0, (frame, index, err)
            swapped = np.linalg.norm(joints[1 - index] - truth[frame], axis=-1).mean() * 1000
            assert swapped > 100, swapped                      # the hands are 0.25 m apart
        # each hand has its own side's handedness: the palm's orientation (wrist → index
        # knuckle × wrist → pinky knuckle) flips under a mirror, so it tells the sides apart
        palm = [(j[6] - j[0], j[21] - j[0]) for j in joints]
        normals = [np.cross(a, b) for a, b in palm]
        true = [np.cross(t[frame][6] - t[frame][0], t[frame][21] - t[frame][0])
                for t in (right, left)]
        for n, t in zip(normals, true):
            assert np.dot(n, t) / (np.linalg.norm(n) * np.linalg.norm(t)) > 0.99
    for h in rep["hands"]:
        assert h["mpjpe_mm"] < 1.0 and h["keypoints"]["hand"] == h["hand"]

    # --interpolate: every frame, each hand slerped over its own missing frame
    r = run_cli("fit-geometry", "--keypoints", kp, "--interpolate", "--iterations", "150",
                "-o", out, "--report", report, "-q")
    assert r.exit_code == 0, r.output
    hand, rep = read_hand(str(out)), json.loads(report.read_text())
    assert rep["output_frames"] == [0, 1, 2, 3, 4] and hand.n_frames == 5
    for frame in (0, 2, 4):                                   # both measured: both on target
        joints = posed_joints_world(hand, frame)
        for index, truth in enumerate((right, left)):
            assert np.linalg.norm(joints[index] - truth[frame], axis=-1).mean() < 1e-3
    # the measured hand of a one-hand frame is its fitted pose, not an interpolation
    assert np.linalg.norm(posed_joints_world(hand, 1)[1] - left[1], axis=-1).mean() < 1e-3
    assert np.linalg.norm(posed_joints_world(hand, 3)[0] - right[3], axis=-1).mean() < 1e-3

    # --hand picks one hand of the file (its side's template); --hand both insists
    one = tmp_path / "left.npz"
    r = run_cli("fit-geometry", "--keypoints", kp, "--hand", "left", "--iterations", "20",
                "-o", one, "-q")
    assert r.exit_code == 0, r.output
    assert read_hand(str(one)).side == "left" and len(read_hand(str(one)).hands) == 1


def test_two_hand_leap_recording_from_real_pinch(run_cli, tmp_path):
    """The real pinch with a mirrored copy as the left hand (missing in a few frames):
    `--hand both` fits both into one hand.npz that the physical renderer draws."""
    src = json.loads(shared_path("hands", "leap", "pinch.json").read_text())
    rec = tmp_path / "two.json"
    rec.write_text(json.dumps(_mirror_leap(src, missing_left={40, 41}, missing_right={120})))
    out, report = tmp_path / "two.npz", tmp_path / "fit.json"
    r = run_cli("fit-geometry", "--keypoints", rec, "--hand", "both", "--frames", "0:200:40",
                "--iterations", "60", "-o", out, "--report", report, "-q")
    assert r.exit_code == 0, r.output
    rep = json.loads(report.read_text())
    assert rep["output_frames"] == [0, 80, 160]                # 40: no left, 120: no right
    assert [(h["hand"], h["keypoints"]["frames_without_hand"]) for h in rep["hands"]] == \
        [("right", 1), ("left", 2)]
    # exact mirror images: both hands fit equally well (measured: 0.39 mm median 0.02)
    right, left = rep["hands"]
    assert right["joint_residuals_mm"]["all"]["p95"] < 3.0
    assert abs(right["mpjpe_mm"] - left["mpjpe_mm"]) < 0.2
    hand = read_hand(str(out))
    from relight_cli.hand.scene import posed_joints_world
    for k in range(hand.n_frames):
        j_right, j_left = posed_joints_world(hand, k)
        np.testing.assert_allclose(j_left, j_right * [-1.0, 1.0, 1.0], atol=2e-3)
    # the physical renderer takes it (one point light: an env map's shadows cost ~7 s)
    exr, lights = tmp_path / "two.exr", tmp_path / "lights.json"
    lights.write_text(json.dumps({"format": "relight/lights", "version": 1,
                                  "lights": [{"position": [0.0, 0.6, 0.6], "intensity": 5}]}))
    r = run_cli("relight", out, "--lights", lights, "-o", exr, "--size", "24x24", "-q")
    assert r.exit_code == 0, r.output
    from relight_cli.formats.image import read_image
    img, _ = read_image(str(exr))
    assert img.shape[:2] == (24, 24) and np.isfinite(img).all() and img.max() > 0
