"""`relight dgsm-build`, the relight/dgsm EXR and relight/lights JSON formats, bad input."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from relight_cli.cli import cli
from relight_cli.formats.dgsm_exr import read_dgsm, write_dgsm
from relight_cli.formats.gaussians_ply import Gaussians, rgb_to_sh_dc, write_gaussians
from relight_cli.formats.lights_json import Lights, read_lights, write_lights
from relight_cli.gaussians import dgsm as D
from relight_cli.gaussians import transmittance as TR


def _gaussians(means, scale, alpha=0.9, flat=False):
    n = len(means)
    s = np.tile([scale, scale, scale * (0.05 if flat else 1.0)], (n, 1))
    return Gaussians(means, s, np.tile([1.0, 0, 0, 0], (n, 1)), np.full(n, alpha),
                     rgb_to_sh_dc(np.full((n, 3), 0.6))[:, None, :], 0)


@pytest.fixture()
def scene(tmp_path):
    rng = np.random.default_rng(0)
    occ = _gaussians(rng.normal(size=(200, 3)) * 0.15 + [0, 1.0, 0], 0.04)
    gx, gz = np.meshgrid(np.linspace(-1.5, 1.5, 30), np.linspace(-1.5, 1.5, 30))
    floor = _gaussians(np.stack([gx.ravel(), np.zeros(gx.size), gz.ravel()], 1), 0.05, flat=True)
    # rotate the floor discs so their thin axis is +Y: quaternion for +90° about X
    floor.rotations[:] = [np.cos(np.pi / 4), np.sin(np.pi / 4), 0, 0]
    paths = {"occ": tmp_path / "occ.ply", "floor": tmp_path / "floor.ply",
             "lights": tmp_path / "lights.json"}
    write_gaussians(str(paths["occ"]), occ)
    write_gaussians(str(paths["floor"]), floor)
    write_lights(str(paths["lights"]), Lights([[0.3, 3.0, 0.2], [-1.0, 2.5, 0.0]],
                                              [[1, 1, 1], [1, 0.9, 0.8]], [10.0, 4.0]))
    return {k: str(v) for k, v in paths.items()} | {"dir": tmp_path}


def _run(args):
    return CliRunner().invoke(cli, args, catch_exceptions=False)


def test_help():
    r = _run(["dgsm-build", "--help"])
    assert r.exit_code == 0 and "--receivers" in r.output and "auto:K" in r.output


def test_build_in_process_and_read_back(scene):
    out = str(scene["dir"] / "shadows.exr")
    r = _run(["dgsm-build", scene["occ"], "--receivers", scene["floor"], "--lights",
              scene["lights"], "-o", out, "--size", "32", "--bins", "16", "-q"])
    assert r.exit_code == 0, r.output
    m = read_dgsm(out)
    assert m.transmittance.shape == (2, 16, 32, 32)
    assert m.layout == "octahedral" and m.mapping == "avg" and m.kappa == 1.0
    # version 2 stores the lights' intensities and colours (per-light shadow weighting)
    np.testing.assert_array_equal(m.intensities, [10.0, 4.0])
    np.testing.assert_array_equal(m.colors, [[1, 1, 1], [1, 0.9, 0.8]])
    assert len(m.roi) == 2 and m.roi[0]["receivers"] > 0
    from relight_cli.formats.exr import read_exr
    img = read_exr(out)
    assert "light1.t015" in img.channels and img.attributes["relight.format"] == "relight/dgsm"
    prov = img.provenance()
    assert prov["settings"]["bins"] == 16 and "occluders" in prov["inputs"]
    assert prov["settings"]["mapping"] == "avg" and prov["version"] == 2
    # the table agrees with the exact transmittance at receivers (resolution-limited)
    from relight_cli.formats.gaussians_ply import read_gaussians
    floor = read_gaussians(scene["floor"])
    mix = TR.from_gaussians(read_gaussians(scene["occ"]))
    exact = TR.transmittance_between(mix, m.lights[0], floor.means)
    looked = D.sample_transmittance(m, floor.means, light_index=0)
    assert exact.min() < 0.2                         # a real shadow
    assert np.abs(looked - exact).mean() < 0.05      # 32² × 16 table: mean error a few %


def test_cube_atlas_and_half_and_lights_out(scene):
    out = str(scene["dir"] / "cube.exr")
    lout = str(scene["dir"] / "lights-out.json")
    r = _run(["dgsm-build", scene["occ"], "--receivers", scene["floor"], "--lights",
              scene["lights"], "-o", out, "--size", "24", "--bins", "8", "--atlas", "cube",
              "--mapping", "mass", "--kappa", "0.5", "--half", "--lights-out", lout, "-q"])
    assert r.exit_code == 0, r.output
    m = read_dgsm(out)
    assert m.layout == "cube" and m.height == 6 * m.width and m.mapping == "mass"
    back = read_lights(lout)
    np.testing.assert_array_equal(back.positions, read_lights(scene["lights"]).positions)


def test_installed_console_script(scene):
    exe = Path(sys.executable).with_name("relight")
    exe = str(exe) if exe.exists() else shutil.which("relight")
    assert exe, "console script 'relight' not installed"
    out = str(scene["dir"] / "sub.exr")
    p = subprocess.run([exe, "dgsm-build", scene["occ"], "--receivers", scene["floor"],
                        "--lights", scene["lights"], "-o", out, "--size", "16", "--bins", "8"],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    assert os.path.exists(out) and p.stdout == ""
    assert "built in" in p.stderr


def test_size_is_width_by_height(scene):
    """--size WxH, width first as everywhere (issue 16): 8x4 is 8 texels wide, 4 tall."""
    out = str(scene["dir"] / "wide.exr")
    r = _run(["dgsm-build", scene["occ"], "--receivers", scene["floor"], "--lights",
              scene["lights"], "-o", out, "--size", "8x4", "--bins", "4", "-q"])
    assert r.exit_code == 0, r.output
    assert read_dgsm(out).transmittance.shape[-2:] == (4, 8)   # [L, K, H, W]
    _fails(["dgsm-build", scene["occ"], "--receivers", scene["floor"], "--lights",
            scene["lights"], "-o", out, "--size", "8x4x2"], 2, "WxH")


def test_lights_from_stdin(scene):
    out = scene["dir"] / "piped.exr"
    text = Path(scene["lights"]).read_text()
    r = CliRunner().invoke(cli, ["dgsm-build", scene["occ"], "--receivers", scene["floor"],
                                 "--lights", "-", "-o", str(out), "--size", "8", "--bins", "4",
                                 "-q"], input=text)
    assert r.exit_code == 0, r.output
    from relight_cli.formats.exr import read_exr
    assert read_exr(str(out)).provenance()["inputs"]["lights"]["path"] == "-"


def _fails(args, code, *words):
    r = CliRunner().invoke(cli, args)
    assert r.exit_code == code, r.output
    text = r.output.lower()
    assert "traceback" not in text
    for w in words:
        assert w.lower() in text, (w, r.output)


def test_bad_ply_missing_field_and_nan(scene):
    out = str(scene["dir"] / "x.exr")
    from plyfile import PlyData, PlyElement
    data = PlyData.read(scene["occ"])
    v = data["vertex"].data
    names = [n for n in v.dtype.names if n != "opacity"]
    broken = np.empty(len(v), dtype=[(n, v.dtype[n]) for n in names])
    for n in names:
        broken[n] = v[n]
    bad = str(scene["dir"] / "missing.ply")
    PlyData([PlyElement.describe(broken, "vertex")]).write(bad)
    _fails(["dgsm-build", bad, "--receivers", scene["floor"], "--lights", scene["lights"],
            "-o", out], 1, "opacity", "missing.ply")
    v2 = v.copy()
    v2["x"][3] = np.nan
    nan = str(scene["dir"] / "nan.ply")
    PlyData([PlyElement.describe(v2, "vertex")]).write(nan)
    _fails(["dgsm-build", nan, "--receivers", scene["floor"], "--lights", scene["lights"],
            "-o", out], 1, "nan.ply")
    assert not os.path.exists(out)


def test_bad_lights_json(scene):
    out = str(scene["dir"] / "x.exr")
    bad = scene["dir"] / "v9.json"
    obj = json.loads(Path(scene["lights"]).read_text())
    obj["version"] = 9
    bad.write_text(json.dumps(obj))
    _fails(["dgsm-build", scene["occ"], "--receivers", scene["floor"], "--lights", str(bad),
            "-o", out], 1, "version 9", "v9.json")
    obj["version"] = 1
    obj["lights"][0]["position"] = [0, "up", 1]
    bad.write_text(json.dumps(obj))
    _fails(["dgsm-build", scene["occ"], "--receivers", scene["floor"], "--lights", str(bad),
            "-o", out], 1, "position")
    other = scene["dir"] / "other.json"
    other.write_text(json.dumps({"format": "relight/sh-probe", "version": 1}))
    _fails(["dgsm-build", scene["occ"], "--receivers", scene["floor"], "--lights", str(other),
            "-o", out], 1, "not a relight/lights file")
    assert not os.path.exists(out)


def test_lights_intensity_list_is_one_line(scene):
    """``"intensity": [1]`` is not a number (formats/lights_json.md): one line naming the
    file and the field, exit 1, nothing written."""
    out = str(scene["dir"] / "x.exr")
    bad = scene["dir"] / "listed.json"
    obj = json.loads(Path(scene["lights"]).read_text())
    obj["lights"][1]["intensity"] = [1]
    bad.write_text(json.dumps(obj))
    r = CliRunner().invoke(cli, ["dgsm-build", scene["occ"], "--receivers", scene["floor"],
                                 "--lights", str(bad), "-o", out])
    lines = [line for line in r.output.splitlines() if line.strip()]
    assert r.exit_code == 1 and len(lines) == 1, r.output
    assert lines[0].startswith("relight dgsm-build: error:"), r.output
    assert "lights[1].intensity" in lines[0] and "listed.json" in lines[0], r.output
    assert not os.path.exists(out)


def test_zero_receivers_in_roi_writes_all_ones_with_warning(scene):
    far = _gaussians(np.array([[40.0, 0, 0], [41.0, 0, 0]]), 0.05)
    path = str(scene["dir"] / "far.ply")
    write_gaussians(path, far)
    out = str(scene["dir"] / "ones.exr")
    lights = scene["dir"] / "one.json"
    write_lights(str(lights), Lights([[40.5, 3.0, 0.0]]))
    r = CliRunner().invoke(cli, ["dgsm-build", scene["occ"], "--receivers", path, "--lights",
                                 str(lights), "-o", out, "--size", "8", "--bins", "4"])
    assert r.exit_code == 0, r.output
    assert "warning" in r.output and "no receivers" in r.output
    m = read_dgsm(out)
    assert np.all(m.transmittance == 1.0)


def test_light_inside_occluder(scene):
    out = str(scene["dir"] / "x.exr")
    from relight_cli.formats.gaussians_ply import read_gaussians
    occ = read_gaussians(scene["occ"])
    lights = scene["dir"] / "inside.json"
    write_lights(str(lights), Lights([occ.means[5] + 0.001]))
    _fails(["dgsm-build", scene["occ"], "--receivers", scene["floor"], "--lights", str(lights),
            "-o", out], 1, "inside occluder gaussian", "--allow-light-inside")
    assert not os.path.exists(out)
    r = CliRunner().invoke(cli, ["dgsm-build", scene["occ"], "--receivers", scene["floor"],
                                 "--lights", str(lights), "-o", out, "--size", "8", "--bins", "4",
                                 "--allow-light-inside"])
    assert r.exit_code == 0 and "warning" in r.output
    assert np.isfinite(read_dgsm(out).transmittance).all()


def test_usage_errors(scene):
    out = str(scene["dir"] / "x.exr")
    base = ["dgsm-build", scene["occ"], "--lights", scene["lights"], "-o", out]
    _fails(base, 2, "--receivers")                                     # no receivers, no t_max
    _fails(base + ["--receivers", scene["floor"], "--size", "0"], 2, "--size")
    _fails(base + ["--receivers", scene["floor"], "--kappa", "-1"], 2, "--kappa")
    _fails(base[:3] + ["auto:x", "-o", out, "--receivers", scene["floor"]], 2, "auto")
    _fails(["dgsm-build", scene["occ"], "--lights", "auto:2", "-o", out], 2, "--receivers")
    _fails(["dgsm-build", str(scene["dir"] / "nope.ply"), "--receivers", scene["floor"],
            "--lights", scene["lights"], "-o", out], 1, "no such file")


def test_auto_lights_works(scene):
    out = str(scene["dir"] / "auto.exr")
    lout = str(scene["dir"] / "auto-lights.json")
    r = CliRunner().invoke(cli, ["dgsm-build", scene["occ"], "--receivers", scene["floor"],
                                 "--lights", "auto:1", "-o", out, "--size", "8", "--bins", "4",
                                 "--lights-out", lout])
    assert r.exit_code == 0, r.output
    est = read_lights(lout)
    assert est.extra["variant"] == "paper" and len(est.positions) == 1
    # the estimated intensity travels into the shadow map (per-light weighting)
    np.testing.assert_allclose(read_dgsm(out).intensities, est.intensities)


def test_dgsm_exr_rejects_damage(tmp_path):
    m = D.DGSM(np.ones((1, 2, 4, 4), np.float32), np.array([[0.0, 2, 0]]), np.array([3.0]),
               roi=[{"bins": [0, 1]}])
    good = str(tmp_path / "g.exr")
    from relight_cli.provenance import provenance
    from relight_cli.formats.dgsm_exr import VERSION
    write_dgsm(good, m, provenance("relight/dgsm", VERSION))
    assert read_dgsm(good).transmittance.shape == (1, 2, 4, 4)
    from relight_cli.errors import DataError
    from relight_cli.formats.exr import write_exr
    # newer version
    newer = str(tmp_path / "n.exr")
    write_exr(newer, {"light0.t000": np.ones((4, 4))},
              provenance=provenance("relight/dgsm", VERSION + 1))
    with pytest.raises(DataError, match=f"version {VERSION + 1}"):
        read_dgsm(newer)
    # missing channel
    img = {"light0.t000": np.ones((4, 4))}
    attrs = {"relight.dgsm.layout": "octahedral", "relight.dgsm.lights": 1,
             "relight.dgsm.bins": 2, "relight.dgsm.light_positions": "[[0, 2, 0]]",
             "relight.dgsm.t_max": "[3.0]", "relight.dgsm.mapping": "eq5",
             "relight.dgsm.kappa": 1.0, "relight.dgsm.roi": "[]"}
    miss = str(tmp_path / "m.exr")
    write_exr(miss, img, attributes=attrs, provenance=provenance("relight/dgsm", 1))
    with pytest.raises(DataError, match="light0.t001"):
        read_dgsm(miss)
    # out-of-range values
    img2 = {"light0.t000": np.full((4, 4), 2.0), "light0.t001": np.ones((4, 4))}
    rng_ = str(tmp_path / "r.exr")
    write_exr(rng_, img2, attributes=attrs, provenance=provenance("relight/dgsm", 1))
    with pytest.raises(DataError, match="outside"):
        read_dgsm(rng_)


def test_builtin_and_mesh_inputs_with_outputs(tmp_path):
    import trimesh
    lights = tmp_path / "l.json"
    write_lights(str(lights), Lights([[0.2, 1.2, 0.3]]))
    out = str(tmp_path / "s.exr")
    occ_out = str(tmp_path / "sphere.ply")
    rec_out = str(tmp_path / "room.ply")
    r = _run(["dgsm-build", "builtin:sphere", "--translate", "0,0.4,0", "--receivers",
              "builtin:room", "--lights", str(lights), "-o", out, "--size", "32", "--bins", "16",
              "--footprint", "centre", "--occluders-out", occ_out, "--receivers-out", rec_out, "-q"])
    assert r.exit_code == 0, r.output
    from relight_cli.formats.gaussians_ply import read_gaussians
    sphere = read_gaussians(occ_out)
    assert abs(sphere.means[:, 1].mean() - 0.4) < 1e-3
    room = read_gaussians(rec_out)
    m = read_dgsm(out)
    T = D.sample_transmittance(m, room.means, light_index=0)
    # the floor point straight under the sphere along the light ray is in shadow
    L = m.lights[0]
    under = L + (np.array([0, 0.4, 0]) - L) * (L[1] / (L[1] - 0.4))
    nearest = np.argmin(np.linalg.norm(room.means - under, axis=1))
    assert T[nearest] < 0.1 and np.median(T) > 0.99
    # a mesh file as occluders
    mesh = trimesh.creation.box(extents=[0.2, 0.05, 0.2])
    mesh.apply_translation([0, 0.5, 0])
    obj = str(tmp_path / "box.obj")
    mesh.export(obj)
    r = _run(["dgsm-build", obj, "--receivers", rec_out, "--lights", str(lights), "-o", out,
              "--size", "16", "--bins", "8", "-q"])
    assert r.exit_code == 0, r.output
    _fails(["dgsm-build", "builtin:nothing", "--receivers", rec_out, "--lights", str(lights),
            "-o", out], 2, "unknown built-in")  # a usage error, as for builtin env maps
    bad = tmp_path / "bad.obj"
    bad.write_text("this is not a mesh\n")
    _fails(["dgsm-build", str(bad), "--receivers", rec_out, "--lights", str(lights), "-o", out],
           1, "bad.obj")


def _v1_file(path, mapping="eq5"):
    """A DGSM file as version 1 wrote it: no light intensities/colours, old mapping names."""
    from relight_cli.formats.exr import write_exr
    from relight_cli.provenance import provenance
    attrs = {"relight.dgsm.layout": "octahedral", "relight.dgsm.lights": 2,
             "relight.dgsm.bins": 2, "relight.dgsm.light_positions": "[[0, 2, 0], [1, 2, 0]]",
             "relight.dgsm.t_max": "[3.0, 3.0]", "relight.dgsm.mapping": mapping,
             "relight.dgsm.kappa": 1.0, "relight.dgsm.roi": "[]"}
    img = {f"light{i}.t00{k}": np.full((4, 4), 0.5 if i else 1.0, np.float32)
           for i in range(2) for k in range(2)}
    write_exr(str(path), img, attributes=attrs, provenance=provenance("relight/dgsm", 1))
    return str(path)


def test_dgsm_version1_upgrade(tmp_path):
    """Version 1 files stay readable: 'eq5' is today's 'peak'; no intensities → None."""
    m = read_dgsm(_v1_file(tmp_path / "v1.exr"))
    assert m.mapping == "peak" and m.intensities is None and m.colors is None
    assert m.transmittance.shape == (2, 2, 4, 4)
    # version 1's own simple/mass/diag were other definitions: labelled, not confused
    assert read_dgsm(_v1_file(tmp_path / "v1m.exr", "mass")).mapping == "v1-mass"
    from relight_cli.errors import DataError
    with pytest.raises(DataError, match="mapping"):
        read_dgsm(_v1_file(tmp_path / "v1x.exr", "avg"))   # version 1 never wrote 'avg'


def test_dgsm_version2_requires_light_properties(tmp_path):
    from relight_cli.errors import DataError
    from relight_cli.formats.dgsm_exr import VERSION
    from relight_cli.formats.exr import read_exr, write_exr
    from relight_cli.provenance import provenance
    m = D.DGSM(np.ones((1, 2, 4, 4), np.float32), np.array([[0.0, 2, 0]]), np.array([3.0]),
               roi=[{"bins": [0, 1]}], intensities=np.array([3.0]), colors=np.array([[1, 0.5, 0]]))
    good = str(tmp_path / "g.exr")
    write_dgsm(good, m, provenance("relight/dgsm", VERSION))
    back = read_dgsm(good)
    np.testing.assert_array_equal(back.intensities, [3.0])
    np.testing.assert_array_equal(back.colors, [[1, 0.5, 0]])
    img = read_exr(good)
    for key, value, what in (("light_intensities", None, "light_intensities"),
                             ("light_intensities", "[1, 2]", "light count"),
                             ("light_colors", "[[1, -1, 0]]", "≥ 0")):
        attrs = {k: v for k, v in img.attributes.items()
                 if k.startswith("relight.dgsm.") and k != "relight.dgsm." + key}
        if value is not None:
            attrs["relight.dgsm." + key] = value
        bad = str(tmp_path / "b.exr")
        write_exr(bad, dict(img.channels), attributes=attrs,
                  provenance=provenance("relight/dgsm", VERSION))
        with pytest.raises(DataError, match=what):
            read_dgsm(bad)


def test_shadow_protocol_from_the_command_line(tmp_path):
    """Paper Sec. 4.2 end to end: a DGSM matte of a Gaussian sphere and the embree pseudo-GT
    matte of the same sphere as a mesh, scored in the avatar-centric ROI."""
    import json

    from relight_cli.formats.camera import Camera, write_cameras
    lights = tmp_path / "l.json"
    write_lights(str(lights), Lights([[0.3, 1.5, 0.2]], intensities=[4.0]))
    write_cameras(str(tmp_path / "cam.json"),
                  [Camera.look_at([0.0, 1.6, 0.9], [0.0, 0.0, -0.1], width=96, height=72,
                                  fov_y_deg=60)])
    sphere = "builtin:sphere:translate=0,0.35,0"
    shadows = str(tmp_path / "s.exr")
    r = _run(["dgsm-build", sphere, "--receivers", "builtin:room", "--lights", str(lights),
              "-o", shadows, "--size", "128", "--bins", "32", "--footprint", "centre", "-q"])
    assert r.exit_code == 0, r.output
    mattes = {}
    for mode in ("dgsm", "mesh"):
        mattes[mode] = str(tmp_path / f"{mode}.exr")
        r = _run(["relight", sphere, "--shadow-matte", mode, "--dgsm", shadows, "--receivers",
                  "builtin:room", "--camera", str(tmp_path / "cam.json"), "--footprint", "centre",
                  "-o", mattes[mode], "-q"])
        assert r.exit_code == 0, r.output
    from relight_cli.formats.exr import read_exr
    gt = read_exr(mattes["mesh"]).channels["R"]
    pred = read_exr(mattes["dgsm"]).channels["R"]
    assert gt.max() > 0.99 and (gt > 0.5).sum() > 30          # a hard shadow on the floor
    assert pred.max() > 0.5
    out = str(tmp_path / "m.json")
    r = _run(["metrics", "shadow", mattes["dgsm"], mattes["mesh"], "--roi-avatar", sphere,
              "--camera", str(tmp_path / "cam.json"), "--roi-radius", "0.6", "-o", out])
    assert r.exit_code == 0, r.output
    rec = json.loads(open(out).read())
    x, y, w, h = rec["settings"]["roi"]
    assert 0 < w < 96 and 0 < h <= 72                          # computed, smaller than the image
    assert rec["metrics"]["sm_iou"] > 0.5 and rec["metrics"]["sae"] < 0.5
    # usage errors: a matte needs the DGSM (its lights) and a camera; the GT needs a mesh
    r = _run(["relight", sphere, "--shadow-matte", "dgsm", "--receivers", "builtin:room",
              "--camera", str(tmp_path / "cam.json"), "-o", str(tmp_path / "x.exr")])
    assert r.exit_code == 2 and "--dgsm" in r.output
    from relight_cli.formats.gaussians_ply import write_gaussians
    from relight_cli.gaussians.from_mesh import load_gaussians
    write_gaussians(str(tmp_path / "ball.ply"), load_gaussians("builtin:sphere"))
    r = _run(["relight", str(tmp_path / "ball.ply"), "--shadow-matte", "mesh", "--dgsm", shadows,
              "--receivers", "builtin:room", "--camera", str(tmp_path / "cam.json"),
              "-o", str(tmp_path / "x.exr")])
    assert r.exit_code == 1 and "mesh" in r.output
    r = _run(["metrics", "shadow", mattes["dgsm"], mattes["mesh"], "--roi-avatar", sphere])
    assert r.exit_code == 2 and "--camera" in r.output


def test_hand_npz_occluder_frame_and_export(scene, tmp_path):
    """A posed hand.npz is an occluder (frame=K picks the pose) and --occluders-out
    exports it as a Gaussian PLY that relight reads: the hand half meets the Gaussian half."""
    from relight_cli.formats.gaussians_ply import read_gaussians
    hand = tmp_path / "hand.npz"
    assert _run(["fit-geometry", "--pose", "random", "--n-frames", "2", "-o", str(hand)]).exit_code == 0
    out, ply = tmp_path / "sh.exr", tmp_path / "hand.ply"
    r = _run(["dgsm-build", f"{hand}:frame=1;translate=0,0.3,0", "--receivers", scene["floor"],
              "--lights", scene["lights"], "--size", "64", "-o", str(out),
              "--occluders-out", str(ply), "-q"])
    assert r.exit_code == 0, r.output
    g = read_gaussians(str(ply))
    assert len(g) > 1000 and g.means[:, 1].min() > 0.2
    assert read_dgsm(str(out)) is not None
    _fails(["dgsm-build", f"{hand}:frame=2", "--receivers", scene["floor"], "--lights",
            scene["lights"], "-o", str(tmp_path / "x.exr")], 1, "out of range", "hand.npz")
    _fails(["dgsm-build", f"{scene['occ']}:frame=0", "--receivers", scene["floor"], "--lights",
            scene["lights"], "-o", str(tmp_path / "x.exr")], 2, "hand .npz")
    _fails(["dgsm-build", f"{hand}:frame=x", "--receivers", scene["floor"], "--lights",
            scene["lights"], "-o", str(tmp_path / "x.exr")], 2, "frame must be an integer")
    assert not (tmp_path / "x.exr").exists()


def test_colour_space_of_receivers_and_occluders(scene):
    """--colour-space: a foreign receivers PLY (no relight header) is sRGB and decoded on
    read, so --receivers-out writes it linear (and says so); --colour-space linear keeps
    the stored colours; the setting is in the provenance; a bad value is a usage error."""
    from conftest import as_foreign_ply
    from relight_cli.formats.exr import read_exr
    from relight_cli.formats.gaussians_ply import read_gaussians, srgb_eotf
    as_foreign_ply(scene["floor"])
    got = {}
    for space in ("auto", "linear"):
        out = scene["dir"] / f"shadows-{space}.exr"
        recv = scene["dir"] / f"recv-{space}.ply"
        occ = scene["dir"] / f"occ-{space}.ply"
        r = _run(["dgsm-build", scene["occ"], "--receivers", scene["floor"], "--lights",
                  scene["lights"], "-o", str(out), "--size", "16", "--bins", "8",
                  "--colour-space", space, "--receivers-out", str(recv),
                  "--occluders-out", str(occ), "-q"])
        assert r.exit_code == 0, r.output
        assert read_exr(str(out)).provenance()["settings"]["colour_space"] == space
        got[space] = read_gaussians(str(recv))
        assert got[space].source_colour_space == "linear"
        assert got[space].provenance["settings"]["colour_space"] == space
        # the occluders were written by relight: linear whatever the guess
        np.testing.assert_allclose(read_gaussians(str(occ)).colors(), 0.6, atol=1e-6)
    np.testing.assert_allclose(got["linear"].colors(), 0.6, atol=1e-6)
    np.testing.assert_allclose(got["auto"].colors(), srgb_eotf(0.6), atol=1e-6)
    _fails(["dgsm-build", scene["occ"], "--receivers", scene["floor"], "--lights",
            scene["lights"], "-o", str(scene["dir"] / "x.exr"), "--colour-space", "rgb"],
           2, "colour-space")


# ------------------------------------------------------------------ preview shadow (issue 53, 8)


def _uniform_probe(path, radiance=0.2):
    from relight_cli.formats.sh_probe_json import ShProbe, write_probe
    c = np.zeros((1, 3))
    c[0] = radiance * np.sqrt(4 * np.pi)              # uniform radiance: E_probe = π·radiance
    write_probe(str(path), ShProbe(c, 0))
    return str(path)


@pytest.mark.parametrize("strength", ["auto", 1.0, 0.4])
def test_preview_shadow_is_relights_shadow(scene, strength):
    """dgsm-build --preview draws the receivers as relight relight shadows them: for the
    same scene, strength and probe the shadowed/lit ratio of every receiver is the
    render's (one function, relight_cli.gaussians.receiver_shadow); at auto it is lighter
    than the full shadow the preview used to show."""
    from relight_cli.formats.gaussians_ply import read_gaussians
    from relight_cli.formats.lights_json import read_lights
    from relight_cli.formats.sh_probe_json import read_probe
    from relight_cli.jobs.dgsm_build import DgsmOptions, build
    from relight_cli.jobs.relight_gaussians import GaussianOptions, relight
    probe = read_probe(_uniform_probe(scene["dir"] / "p.json"))
    occ, floor = read_gaussians(scene["occ"]), read_gaussians(scene["floor"])
    options = DgsmOptions(size=(32, 32), bins=16, preview=True, preview_strength=strength,
                          preview_probe=probe)
    built = build([occ], read_lights(scene["lights"]), options, floor)
    rendered = relight([occ], probe, GaussianOptions(shadow_strength=strength),
                       built.shadow_map, floor)
    lit = floor.colors()
    preview_ratio = built.preview_receivers.colors() / lit
    render_ratio = rendered.receivers.colors() / lit
    np.testing.assert_allclose(preview_ratio, render_ratio, rtol=1e-12, atol=0)
    assert preview_ratio.min() < 0.97                     # something is really shadowed
    if strength == "auto":
        full = build([occ], read_lights(scene["lights"]),
                     DgsmOptions(size=(32, 32), bins=16, preview=True), floor)   # default: 1
        darkest = np.argmin(full.preview_receivers.colors()[:, 1])
        assert preview_ratio[darkest, 1] > full.preview_receivers.colors()[darkest, 1] / \
            lit[darkest, 1] + 0.05


def test_preview_strength_on_the_command_line(scene):
    """--preview-probe: the label says auto and its median; without one: strength 1, said;
    the options need --preview, and auto needs a probe (usage errors, nothing written)."""
    probe = _uniform_probe(scene["dir"] / "p.json")
    out, png = str(scene["dir"] / "s.exr"), str(scene["dir"] / "s.png")
    base = ["dgsm-build", scene["occ"], "--receivers", scene["floor"], "--lights",
            scene["lights"], "-o", out, "--size", "16", "--bins", "8", "-q"]
    for extra in (["--preview-probe", probe], ["--preview-shadow-strength", "0.5"]):
        _fails(base + extra, 2, extra[0], "needs --preview")
    _fails(base + ["--preview", png, "--preview-shadow-strength", "auto"], 2,
           "--preview-probe")
    _fails(base + ["--preview", png, "--preview-shadow-strength", "1.5"], 2,
           "--preview-shadow-strength")
    _fails(base + ["--preview", png, "--preview-probe", str(scene["dir"] / "nope.json")], 1,
           "no such file")
    assert not os.path.exists(out) and not os.path.exists(png)
    r = _run(base + ["--preview", png, "--preview-probe", probe])
    assert r.exit_code == 0, r.output
    from PIL import Image
    with Image.open(png) as im:
        assert im.size[0] > 300
    r = _run(base + ["--preview", png, "--preview-probe", probe,
                     "--preview-shadow-strength", "0.3"])
    assert r.exit_code == 0, r.output


def test_preview_labels_its_strength(monkeypatch):
    """The scene tile's label names the strength it shows (what relight would deliver)."""
    from relight_cli import preview as P
    labels = []
    real_tile = P.tile
    monkeypatch.setattr(P, "tile", lambda values, label, *a, **k:
                        labels.append(label) or real_tile(values, label, *a, **k))
    rng = np.random.default_rng(1)
    occ = _gaussians(rng.normal(size=(40, 3)) * 0.1 + [0, 0.8, 0], 0.04)
    gx, gz = np.meshgrid(np.linspace(-1, 1, 12), np.linspace(-1, 1, 12))
    floor = _gaussians(np.stack([gx.ravel(), np.zeros(gx.size), gz.ravel()], 1), 0.08,
                       flat=True)
    floor.rotations[:] = [np.cos(np.pi / 4), np.sin(np.pi / 4), 0, 0]
    m = D.build_dgsm(TR.from_gaussians(occ), [[0.2, 2.5, 0.1]], floor.means, size=(16, 16),
                     bins=8, intensities=[5.0], colors=[[1, 1, 1]])
    c = np.full((1, 3), 0.2 * np.sqrt(4 * np.pi))
    P.dgsm_sheet(m, occ, floor, strength="auto", probe_coefficients=c)
    P.dgsm_sheet(m, occ, floor)
    assert labels[0].startswith("relight's shadow at strength auto (median 0.")
    assert "relight's shadow at strength 1" in labels
