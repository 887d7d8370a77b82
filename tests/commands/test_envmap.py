"""`relight envmap` end to end: CliRunner and the installed console script, bad input."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from conftest import SHARED_DATA, run_relight, shared_path
from relight_cli.formats.envmap import read_envmap
from relight_cli.formats.exr import read_exr


def _assert_clean_failure(result, code, out_dir, *needles):
    """One line on stderr, the exit code, no traceback, nothing written."""
    stderr = result.stderr if hasattr(result, "stderr") else result.output
    lines = [l for l in stderr.strip().splitlines() if l.strip()]
    assert result.exit_code if hasattr(result, "exit_code") else result.returncode
    code_got = result.exit_code if hasattr(result, "exit_code") else result.returncode
    assert code_got == code, stderr
    assert len(lines) == 1, stderr
    assert lines[0].startswith("relight envmap: error:"), stderr
    assert "Traceback" not in stderr
    for needle in needles:
        assert needle in lines[0]
    assert not [p for p in os.listdir(out_dir) if p.startswith(("out", ".out"))], os.listdir(out_dir)


def test_convert_builtin_to_cube_and_back(run_cli, tmp_path):
    cube = tmp_path / "sky_cube.exr"
    r = run_cli("envmap", "builtin:sky", "--to", "cube", "--size", "16", "-o", cube, "--quiet")
    assert r.exit_code == 0, r.output
    env = read_envmap(str(cube))
    assert env.layout == "cube" and env.radiance.shape == (96, 16, 3)
    prov = read_exr(str(cube)).provenance()
    assert prov["format"] == "relight/envmap" and prov["version"] == 1
    assert prov["inputs"]["input"]["path"] == "builtin:sky"
    assert "envmap builtin:sky" in prov["command"]
    lat = tmp_path / "sky_lat.exr"
    r = run_cli("envmap", cube, "--to", "latlong", "--size", "32x16", "-o", lat, "--quiet")
    assert r.exit_code == 0, r.output
    assert read_envmap(str(lat)).radiance.shape == (16, 32, 3)


def test_info_json_on_stdout(run_cli):
    r = run_cli("envmap", "builtin:point", "--info", "--quiet")
    assert r.exit_code == 0
    info = json.loads(r.stdout)
    for key in ("width", "height", "layout", "min", "max", "mean", "power", "dominant_direction"):
        assert key in info
    assert info["layout"] == "latlong"
    np.testing.assert_allclose(info["power"], 10.0, rtol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(info["dominant_direction"]), 1.0, rtol=1e-9)


def test_identical_inputs_give_identical_outputs(run_cli, tmp_path, monkeypatch):
    # Same command line (the provenance records it), run twice.
    monkeypatch.chdir(tmp_path)
    outputs = []
    for _ in range(2):
        assert run_cli("envmap", "builtin:studio", "--size", "32x16", "-o", "a.exr", "-q").exit_code == 0
        outputs.append((tmp_path / "a.exr").read_bytes())
    assert outputs[0] == outputs[1]


def test_console_script_end_to_end(tmp_path):
    out = tmp_path / "rot.exr"
    png = tmp_path / "rot.png"
    r = run_relight("envmap", "builtin:studio", "--size", "64x32", "--rotate-y", "90",
                    "-o", out, "--preview", png)
    assert r.returncode == 0, r.stderr
    assert r.stdout == ""  # logs go to stderr only
    assert out.exists() and png.read_bytes()[:4] == b"\x89PNG"
    info = run_relight("envmap", out, "--info", "-q")
    assert json.loads(info.stdout)["width"] == 64


def test_no_clobber(run_cli, tmp_path):
    out = tmp_path / "x.exr"
    out.write_bytes(b"keep")
    r = run_cli("envmap", "builtin:uniform", "-o", out, "--no-clobber")
    assert r.exit_code == 2 and out.read_bytes() == b"keep"


@pytest.mark.parametrize("args,needle", [
    (["--size", "abc"], "--size"),
    (["--to", "cube", "--size", "8x4"], "face size"),
    (["--size", "1x1"], "2x2"),
    (["--size", "16"], "WxH (width first, e.g. 32x16)"),   # one syntax per kind (issue 16)
])
def test_usage_errors_exit_2(run_cli, tmp_path, args, needle):
    r = run_cli("envmap", "builtin:sky", *args, "-o", tmp_path / "out.exr")
    _assert_clean_failure(r, 2, tmp_path, needle)


@pytest.mark.parametrize("out, needle", [
    ("out.png", "name it .exr"),           # it would write an EXR named .png
    ("-", "stdout"),                       # an EXR on stdout
])
def test_output_name_must_say_exr(run_cli, tmp_path, out, needle):
    r = run_cli("envmap", "builtin:sky", "--size", "8x4", "-o", out if out == "-" else tmp_path / out)
    _assert_clean_failure(r, 2, tmp_path, needle)


def test_info_to_stdout_with_dash(run_cli, tmp_path):
    """--info -o - (refused before issue 16) prints the statistics, writes nothing else."""
    r = run_cli("envmap", "builtin:sky", "--info", "-o", "-", "-q")
    assert r.exit_code == 0, r.output
    assert json.loads(r.stdout)["layout"] == "latlong" and r.stderr == ""


def test_unknown_builtin(run_cli, tmp_path):
    r = run_cli("envmap", "builtin:moon", "-o", tmp_path / "out.exr")
    _assert_clean_failure(r, 2, tmp_path, "builtin:sky")


def test_missing_file_and_directory(run_cli, tmp_path):
    _assert_clean_failure(run_cli("envmap", tmp_path / "nope.exr", "-o", tmp_path / "out.exr"),
                          1, tmp_path, "no such file", "nope.exr")
    _assert_clean_failure(run_cli("envmap", tmp_path, "-o", tmp_path / "out.exr"),
                          1, tmp_path, "directory")


def test_unreadable_format(run_cli, tmp_path):
    bad = tmp_path / "garbage.hdr"
    bad.write_bytes(b"this is not an image at all\n" * 10)
    _assert_clean_failure(run_cli("envmap", bad, "-o", tmp_path / "out.exr"), 1, tmp_path, "garbage.hdr")


def test_truncated_file_written_by_us(run_cli, tmp_path):
    good = tmp_path / "good.exr"
    assert run_cli("envmap", "builtin:sky", "--size", "64x32", "-o", good, "-q").exit_code == 0
    data = good.read_bytes()
    for cut in (8, len(data) // 3, len(data) - 50):
        bad = tmp_path / f"trunc{cut}.exr"
        bad.write_bytes(data[:cut])
        _assert_clean_failure(run_cli("envmap", bad, "-o", tmp_path / "out.exr"), 1, tmp_path,
                              bad.name)


def test_png_missing_its_last_byte_through_console_script(tmp_path):
    """A --preview PNG of ours with its last IEND byte cut off, read back as an env map:
    one line naming the file, exit 1, no libpng line, nothing written."""
    r = run_relight("envmap", "builtin:sky", "--to", "latlong", "--size", "16x8",
                    "--preview", tmp_path / "x.png", "-o", tmp_path / "x.exr", "-q")
    assert r.returncode == 0, r.stderr
    data = (tmp_path / "x.png").read_bytes()
    (tmp_path / "cut.png").write_bytes(data[:-1])
    r = run_relight("envmap", tmp_path / "cut.png", "-o", tmp_path / "out.exr")
    assert "libpng" not in r.stderr
    _assert_clean_failure(r, 1, tmp_path, "cut.png", "cut short")


def test_nan_inf_image_is_refused_with_count(run_cli, tmp_path):
    src = shared_path("images", "BrightRingsNanInf.exr")
    r = run_cli("envmap", src, "-o", tmp_path / "out.exr")
    _assert_clean_failure(r, 1, tmp_path, "pixel(s) hold NaN or Inf", "BrightRingsNanInf.exr")
    r = run_cli("envmap", src, "--nonfinite", "clamp", "--size", "64x32", "-o", tmp_path / "ok.exr", "-q")
    assert r.exit_code == 0
    assert np.isfinite(read_envmap(str(tmp_path / "ok.exr")).radiance).all()


def _damaged():
    folder = SHARED_DATA / "damaged-exr"
    return sorted(folder.iterdir()) if folder.is_dir() else []


@pytest.mark.skipif(not _damaged(), reason="../shared/data/damaged-exr not available")
def test_every_damaged_exr_is_a_clean_error(run_cli, tmp_path):
    """OpenEXR's fuzzed/truncated files: exit 1, one line naming the file, no output."""
    for path in _damaged():
        r = run_cli("envmap", path, "-o", tmp_path / "out.exr")
        _assert_clean_failure(r, 1, tmp_path, path.name)


@pytest.mark.skipif(not _damaged(), reason="../shared/data/damaged-exr not available")
def test_damaged_exr_through_console_script(tmp_path):
    for path in _damaged()[:3]:
        r = run_relight("envmap", path, "-o", tmp_path / "out.exr")
        assert r.returncode == 1 and "Traceback" not in r.stderr
        assert len(r.stderr.strip().splitlines()) == 1
        assert not (tmp_path / "out.exr").exists()


def _negative_map(path):
    """A 16x8 lat-long EXR from another tool (no relight header) whose pixels are 0.5 but
    three: one with R −0.5, one with G −0.02, one with G and B −0.1 (a filtered map's
    undershoot)."""
    from relight_cli.formats.exr import write_exr
    rgb = np.full((8, 16, 3), 0.5, np.float32)
    rgb[1, 2, 0] = -0.5
    rgb[4, 9, 1] = -0.02
    rgb[6, 15, 1:] = -0.1
    write_exr(str(path), {c: rgb[..., i] for i, c in enumerate("RGB")})
    return rgb


def test_negative_radiance_is_refused_naming_the_way_forward(run_cli, tmp_path):
    """Issue 53: negative radiance is one line saying how many pixels, how deep against the
    map's mean, and the option that goes on (--negative clamp); exit 1, nothing written,
    for the EXR, the --info JSON and the preview alike, and from another command too."""
    src = tmp_path / "neg.exr"
    rgb = _negative_map(src)
    mean = float(rgb.mean(dtype=np.float64))
    for extra in (["-o", tmp_path / "out.exr"], ["--info", "-o", tmp_path / "out.json"],
                  ["--preview", tmp_path / "out.png"]):
        r = run_cli("envmap", src, *extra)
        _assert_clean_failure(r, 1, tmp_path, "3 of 128 pixel(s) have negative radiance",
                              "down to -0.5 ", f"(the map's mean is {mean:.4g})", "(",
                              "neg.exr)", "--negative clamp")
    r = run_cli("sh-probe", src, "-o", tmp_path / "out.json")
    assert r.exit_code == 1 and "relight envmap IN --negative clamp" in r.output, r.output
    assert not (tmp_path / "out.json").exists()


def test_negative_clamp_sets_negative_radiance_to_zero(run_cli, tmp_path):
    """--negative clamp: every negative channel becomes exactly 0, every other value is
    kept bit for bit; the log says how many pixels and how deep; the provenance records it;
    the output reads with the default policy, and a resampled one holds no negative."""
    src = tmp_path / "neg.exr"
    rgb = _negative_map(src)
    out = tmp_path / "out.exr"
    r = run_cli("envmap", src, "--negative", "clamp", "-o", out)
    assert r.exit_code == 0, r.output
    assert "clamped 3 pixel(s) of negative radiance (down to -0.5) to 0" in r.output
    got = read_envmap(str(out)).radiance
    expected = np.where(rgb < 0, np.float32(0), rgb)
    assert got.dtype == np.float32 and np.array_equal(got, expected)
    assert read_exr(str(out)).provenance()["settings"]["negative"] == "clamp"
    cube = tmp_path / "out_cube.exr"
    r = run_cli("envmap", src, "--negative", "clamp", "--to", "cube", "--size", "4", "-o", cube,
                "-q")
    assert r.exit_code == 0, r.output
    assert read_envmap(str(cube)).radiance.min() >= 0
    # a map with no negative pixel: nothing logged, nothing recorded
    r = run_cli("envmap", "builtin:sky", "--size", "16x8", "-o", tmp_path / "sky.exr")
    assert r.exit_code == 0 and "clamped" not in r.output
    assert "negative" not in read_exr(str(tmp_path / "sky.exr")).provenance()["settings"]


def test_negative_policy_is_a_usage_choice(run_cli, tmp_path):
    r = run_cli("envmap", "builtin:sky", "--negative", "zero", "-o", tmp_path / "out.exr")
    assert r.exit_code == 2 and "--negative" in r.output
    assert not (tmp_path / "out.exr").exists()
