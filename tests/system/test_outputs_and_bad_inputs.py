"""Every subcommand against one table of bad output targets and bad inputs (issue 15).

Each failing case must give: the documented exit code, exactly one line on
stderr, no traceback, no "internal error", inputs unchanged and nothing new on
disk (temporary files included).  Cases that succeed (a symlink, a character
device) must leave the node as it was and write through it.  Also: SIGTERM and
SIGKILL leave no temporary files once the next run is over, and identical
inputs give identical bytes whatever the presentation flags.

Inputs are tiny (8×4 env maps, 8×8 textures, a few dozen Gaussians) so that the
whole module runs in well under a minute of CPU; cases that need a real process
(devices, FIFOs, another user, a full file system, signals) use the installed
console script, the rest run in-process through click's CliRunner.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import signal
import stat
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from conftest import relight_executable
from relight_cli.cli import cli
from sweep import (COMMANDS, DUPLICATES, FIRST_INPUT, _assert_one_error,  # noqa: F401
                   _full_filesystem_available, _inproc, _quote, _run_inproc_fail, _snapshot,
                   data)

TEMP_MARK = ".relight-tmp-"


# ----------------------------------------------------------------------------- inputs


def _temps_of(pid: int) -> list[str]:
    """Temporary files process ``pid`` left in the system temp folder (in-place writes
    stage there); other sessions' files are not ours to judge."""
    return sorted(n for n in os.listdir(tempfile.gettempdir()) if f"{TEMP_MARK}{pid}-" in n)


def _subprocess(args, timeout=120, **kw):
    """Run the console script; the result has .pid too."""
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    proc = subprocess.Popen([relight_executable(), *map(str, args)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env, **kw)
    stdout, stderr = proc.communicate(timeout=timeout)
    result = subprocess.CompletedProcess(proc.args, proc.returncode, stdout, stderr)
    result.pid = proc.pid
    return result


# ----------------------------------------------------------------------------- bad outputs


# kind -> (how to make the output path in a work folder, expected exit code).
BAD_OUTPUTS = ["input", "directory", "missing-folder", "empty-name", "proc", "name-too-long",
               "symlink-loop"]


# fit-geometry as run here reads no file; its "output is an input" case is
# test_fit_geometry_refuses_to_write_over_its_keypoints.
@pytest.mark.parametrize("name,kind", [(n, k) for n in sorted(COMMANDS) for k in BAD_OUTPUTS
                                       if not (k == "input" and FIRST_INPUT[n] is None)])
def test_bad_output_target(data, tmp_path, name, kind):
    build, ext = COMMANDS[name]
    if kind == "input":   # an input of another kind may be refused by its extension first
        same_kind = FIRST_INPUT[name].endswith(ext)
        out, code = data / FIRST_INPUT[name], 2
        word = "also an input" if same_kind else ("also an input", "name it")
    elif kind == "directory":
        (tmp_path / ("d" + ext)).mkdir()
        out, code, word = tmp_path / ("d" + ext), 2, "directory"
    elif kind == "missing-folder":
        out, code, word = tmp_path / "nope" / ("x" + ext), 2, "does not exist"
    elif kind == "empty-name":
        out, code, word = "", 2, ""   # "empty output file name", or the command's own refusal
    elif kind == "proc":
        out, code, word = "/proc/relight-x" + ext, 1, "/proc"
    elif kind == "symlink-loop":
        (tmp_path / ("a" + ext)).symlink_to("b" + ext)
        (tmp_path / ("b" + ext)).symlink_to("a" + ext)
        out, code, word = tmp_path / ("a" + ext), 1, "symbolic links"
    else:
        out, code, word = tmp_path / ("a" * 300 + ext), 1, "too long"
    before = _snapshot(data, tmp_path)
    _run_inproc_fail(build(data, out), code, word)
    assert _snapshot(data, tmp_path) == before


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_symlink_output_is_written_through(data, tmp_path, name):
    build, ext = COMMANDS[name]
    real = tmp_path / ("real" + ext)
    real.write_text("old")
    link = tmp_path / ("link" + ext)
    link.symlink_to(real.name)
    r = _inproc(*build(data, link))
    assert r.exit_code == 0, r.output
    assert link.is_symlink() and os.readlink(link) == real.name
    assert real.read_bytes() != b"old" and real.stat().st_size > 0
    assert sorted(os.listdir(tmp_path)) == sorted([real.name, link.name])


needs_root = pytest.mark.skipif(os.geteuid() != 0, reason="mknod needs root")


@needs_root
@pytest.mark.parametrize("name", ["envmap", "fit-geometry", "metrics-image", "dgsm-build"])
def test_character_device_is_written_in_place(data, tmp_path, name):
    """A device node given as output keeps being that node (as root, `-o /dev/null`
    once replaced /dev/null with a regular file)."""
    build, _ = COMMANDS[name]
    node = tmp_path / "null"
    os.mknod(node, 0o666 | stat.S_IFCHR, os.makedev(1, 3))   # the same device as /dev/null
    p = _subprocess([*build(data, node), "-q"])
    assert p.returncode == 0, p.stderr
    assert stat.S_ISCHR(os.lstat(node).st_mode) and os.listdir(tmp_path) == ["null"]
    assert _temps_of(p.pid) == []


@needs_root
def test_block_device_and_socket_are_refused(data, tmp_path):
    import socket
    block = tmp_path / "disk"
    os.mknod(block, 0o600 | stat.S_IFBLK, os.makedev(7, 0))   # a loop device node
    sock_path = tmp_path / "sock"
    server = socket.socket(socket.AF_UNIX)
    server.bind(str(sock_path))
    try:
        before = _snapshot(tmp_path)
        for target, word in ((block, "block device"), (sock_path, "socket")):
            _run_inproc_fail(COMMANDS["envmap"][0](data, target), 2, word)
        assert _snapshot(tmp_path) == before
    finally:
        server.close()


@needs_root
def test_full_device_is_a_write_error(data, tmp_path):
    node = tmp_path / "full"
    os.mknod(node, 0o666 | stat.S_IFCHR, os.makedev(1, 7))   # /dev/full: ENOSPC on write
    p = _subprocess(COMMANDS["envmap"][0](data, node) + ["-q"])
    _assert_one_error(p.returncode, p.stderr, 1, "no space left")
    assert stat.S_ISCHR(os.lstat(node).st_mode)


@pytest.mark.parametrize("name", ["envmap", "sh-probe", "metrics-image"])
def test_fifo_without_reader_is_refused_and_kept(data, tmp_path, name):
    build, _ = COMMANDS[name]
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    p = _subprocess(build(data, fifo) + ["-q"])   # -q: the log lines came before the write
    _assert_one_error(p.returncode, p.stderr, 1, "FIFO has no reader")
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode) and os.listdir(tmp_path) == ["pipe"]
    assert _temps_of(p.pid) == []


def test_fifo_with_reader_gets_the_bytes(data, tmp_path):
    fifo, plain = tmp_path / "pipe", tmp_path / "plain.json"
    os.mkfifo(fifo)
    reader = subprocess.Popen(["cat", str(fifo)], stdout=subprocess.PIPE)
    p = _subprocess(COMMANDS["sh-probe"][0](data, fifo) + ["-q"])
    streamed = reader.communicate(timeout=60)[0]
    assert p.returncode == 0, p.stderr
    assert _inproc(*COMMANDS["sh-probe"][0](data, plain)).exit_code == 0
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode)
    streamed, written = json.loads(streamed), json.loads(plain.read_text())
    for record in (streamed, written):   # the command lines differ in the output's name
        record["provenance"].pop("command")
    assert streamed == written


# Two outputs of one command on one file: refused before any work.
@pytest.mark.parametrize("case", sorted(DUPLICATES))
def test_two_outputs_on_one_file_are_refused(data, tmp_path, case):
    before = _snapshot(data, tmp_path)
    _run_inproc_fail(DUPLICATES[case](data, tmp_path), 2, "two outputs")
    assert _snapshot(data, tmp_path) == before


def test_hard_link_to_an_input_is_refused(data, tmp_path):
    alias = tmp_path / "alias.exr"
    os.link(data / "sky.exr", alias)
    before = _snapshot(data, tmp_path)
    _run_inproc_fail(["envmap", data / "sky.exr", "-o", alias], 2, "also an input")
    assert _snapshot(data, tmp_path) == before


def _without_root_override():
    """preexec_fn: drop CAP_DAC_OVERRIDE and CAP_DAC_READ_SEARCH from the bounding set,
    so the exec'd relight (still uid 0, so it can run the interpreter under /root)
    obeys file permissions like any user."""
    import ctypes
    libc = ctypes.CDLL(None, use_errno=True)
    for cap in (1, 2):  # CAP_DAC_OVERRIDE, CAP_DAC_READ_SEARCH
        if libc.prctl(24, cap, 0, 0, 0) != 0:  # PR_CAPBSET_DROP
            raise OSError(ctypes.get_errno(), "prctl(PR_CAPBSET_DROP)")


@pytest.mark.skipif(os.geteuid() != 0 or not sys.platform.startswith("linux"),
                    reason="needs Linux root to run relight without its permission override")
@pytest.mark.parametrize("name", ["envmap", "sh-probe", "fit-geometry", "metrics-image"])
def test_read_only_folder(data, name):
    """A folder the user may not write in: one error line, exit 1, before any work.
    Root ignores permissions, so relight runs without root's override; the folder
    belongs to `nobody`, mode r-x for everyone else."""
    folder = Path(tempfile.mkdtemp(prefix="relight-ro-", dir="/tmp"))
    try:
        os.chown(folder, 65534, -1)
        os.chmod(folder, 0o555)
        build, ext = COMMANDS[name]
        try:
            p = subprocess.run([relight_executable(), *map(str, build(data, folder / ("x" + ext)))],
                               capture_output=True, text=True, timeout=120,
                               env=dict(os.environ, PYTHONWARNINGS="ignore"),
                               preexec_fn=_without_root_override)
        except (OSError, subprocess.SubprocessError) as exc:
            pytest.skip(f"cannot drop root's permission override here: {exc}")
        _assert_one_error(p.returncode, p.stderr, 1, "permission denied")
        assert os.listdir(folder) == []
    finally:
        os.chmod(folder, 0o755)
        shutil.rmtree(folder, ignore_errors=True)


@pytest.mark.parametrize("name", ["envmap", "sh-probe", "fit-geometry", "bake-features"])
def test_full_file_system_never_leaves_an_empty_output(data, tmp_path, name):
    """On a full disk: one error line, exit 1, and no 0-byte (or partial) output."""
    reason = _full_filesystem_available()
    if reason:
        pytest.skip(reason)
    build, ext = COMMANDS[name]
    mount = tmp_path / "full"
    mount.mkdir()
    out = mount / ("x" + ext)
    cmd = " ".join(map(_quote, [relight_executable(), *build(data, out), "-q"]))
    # fd 3 carries the folder listing back on stdout; the command's output goes to stderr
    script = (f"exec 3>&1 1>&2; mount -t tmpfs -o size=8k tmpfs {mount} || exit 99; "
              f"head -c 16384 /dev/zero > {mount}/fill 2>/dev/null; "
              f"{cmd}; rc=$?; ls -a {mount} >&3; exit $rc")
    p = subprocess.run(["unshare", "-rm", "bash", "-c", script],
                       capture_output=True, text=True, timeout=120,
                       env=dict(os.environ, PYTHONWARNINGS="ignore"))
    listing = sorted(p.stdout.split())
    _assert_one_error(p.returncode, p.stderr, 1)
    assert listing == [".", "..", "fill"], listing


# ----------------------------------------------------------------------------- bad inputs


def _exr(path, channels, attributes):
    from relight_cli.formats.exr import write_exr
    write_exr(str(path), channels, attributes=attributes)


def _hand_variant(src, dst, change):
    with np.load(src, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    change(arrays)
    with open(dst, "wb") as f:
        np.savez(f, **arrays)


def _make_bad_inputs(data, folder, ext):
    """name -> path of one bad input file each (tiny); generic ones named *ext."""
    bad = {}
    bad["missing"] = folder / f"missing{ext}"
    (folder / f"folder{ext}").mkdir()
    bad["directory"] = folder / f"folder{ext}"
    (folder / f"empty{ext}").write_bytes(b"")
    bad["empty"] = folder / f"empty{ext}"
    (folder / f"garbage{ext}").write_bytes(b"\x00\x01not a file of any kind" * 10)
    bad["garbage"] = folder / f"garbage{ext}"
    ones = {c: np.ones((4, 8), np.float32) for c in "RGB"}
    _exr(folder / "v99.exr", ones, {"relight.format": "relight/envmap", "relight.version": 99})
    bad["env-version-99"] = folder / "v99.exr"
    _exr(folder / "huge.exr", {c: np.full((4, 8), 3e38, np.float32) for c in "RGB"}, {})
    bad["env-3e38"] = folder / "huge.exr"
    hand = data / "hand.npz"

    def zero_area(a):
        for p in ("coarse_", "fine_"):
            a[p + "faces"] = np.repeat(a[p + "faces"][:, :1], 3, axis=1)

    def collapsed(a):
        for p in ("coarse_", "fine_"):
            a[p + "vertices"] = np.zeros_like(a[p + "vertices"])

    def huge(a):
        for p in ("coarse_", "fine_"):
            a[p + "vertices"] = a[p + "vertices"] * 1e300
        a["rest_joints"] = a["rest_joints"] * 1e300

    def middle(a):
        a["side"] = np.array("middle")

    for key, change in (("hand-zero-area", zero_area), ("hand-collapsed", collapsed),
                        ("hand-1e300", huge), ("hand-side-middle", middle)):
        _hand_variant(hand, folder / f"{key}.npz", change)
        bad[key] = folder / f"{key}.npz"
    deep = "[" * 100_000 + "]" * 100_000
    for key, text in (("json-deep", deep), ("json-long-int", '{"version": ' + "9" * 5000 + "}"),
                      ("json-nan", '{"format": "relight/lights", "version": 1, "lights": '
                                   '[{"position": [NaN, 1, 0]}]}')):
        (folder / f"{key}.json").write_text(text)
        bad[key] = folder / f"{key}.json"
    cam = {"K": [[8, 0, 4], [0, 8, 4], [0, 0, 1]], "R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]],
           "t": [0, 0, 1], "width": True, "height": 8}
    (folder / "cam-bool.json").write_text(json.dumps(cam))
    bad["camera-bool-width"] = folder / "cam-bool.json"
    return bad


# (command argv given the data folder, the bad file and the output) per input slot
SLOTS = {
    "envmap:IN": lambda d, b, o: ["envmap", b, "-o", o],
    "sh-probe:IN": lambda d, b, o: ["sh-probe", b, "-o", o],
    "bake-features:ENV": lambda d, b, o: ["bake-features", d / "hand.npz", b, "--res", "8",
                                          "--env-res", "8x4", "-o", o],
    "bake-features:HAND": lambda d, b, o: ["bake-features", b, d / "sky.exr", "--res", "8",
                                           "--env-res", "8x4", "-o", o],
    "relight-hand:ENV": lambda d, b, o: ["relight", d / "hand.npz", b, "-o", o],
    "relight-hand:HAND": lambda d, b, o: ["relight", b, d / "sky.exr", "-o", o],
    "relight-hand:--camera": lambda d, b, o: ["relight", d / "hand.npz", d / "sky.exr",
                                              "--camera", b, "-o", o],
    "fit-geometry:--template": lambda d, b, o: ["fit-geometry", "--template", b, "-o", o],
    "dgsm-build:--lights": lambda d, b, o: ["dgsm-build", d / "ball.ply", "--receivers",
                                            d / "room.ply", "--lights", b, "-o", o],
    "relight-gaussians:--probe": lambda d, b, o: ["relight", d / "ball.ply", "--probe", b,
                                                  "-o", o],
    "metrics-compare:NEW": lambda d, b, o: ["metrics", "compare", b, d / "m.json"],
    "camera:--from": lambda d, b, o: ["camera", "--from", b, "-o", o],
}
# which bad inputs each slot gets (the generic ones go everywhere)
GENERIC = ["missing", "directory", "empty", "garbage"]
SPECIFIC = {
    "envmap:IN": ["env-version-99"], "sh-probe:IN": ["env-version-99"],
    "bake-features:ENV": ["env-version-99", "env-3e38"], "relight-hand:ENV": ["env-version-99"],
    "bake-features:HAND": ["hand-zero-area", "hand-collapsed", "hand-1e300", "hand-side-middle"],
    "relight-hand:HAND": ["hand-zero-area", "hand-collapsed", "hand-1e300", "hand-side-middle"],
    "fit-geometry:--template": ["hand-collapsed", "hand-side-middle"],
    "relight-hand:--camera": ["camera-bool-width", "json-deep", "json-long-int"],
    "dgsm-build:--lights": ["json-deep", "json-long-int", "json-nan"],
    "relight-gaussians:--probe": ["json-deep", "json-long-int"],
    "metrics-compare:NEW": ["json-deep", "json-long-int"],
    "camera:--from": ["camera-bool-width", "json-deep", "json-long-int", "json-nan"],
}
SLOT_EXT = {"bake-features:HAND": ".npz", "relight-hand:HAND": ".npz",
            "fit-geometry:--template": ".npz", "relight-hand:--camera": ".json",
            "dgsm-build:--lights": ".json", "relight-gaussians:--probe": ".json",
            "metrics-compare:NEW": ".json", "camera:--from": ".json"}
OUT_EXT = {"envmap": ".exr", "sh-probe": ".json", "bake-features": ".exr", "relight-hand": ".exr",
           "fit-geometry": ".npz", "dgsm-build": ".exr", "relight-gaussians": ".ply",
           "metrics-compare": ".json", "camera": ".json"}
CASES = [(slot, kind) for slot in sorted(SLOTS) for kind in GENERIC + SPECIFIC.get(slot, [])]


@pytest.mark.parametrize("slot,kind", CASES)
def test_bad_input(data, tmp_path, slot, kind):
    """Bad data is exit 1 (a missing file too), one line naming the file."""
    folder = tmp_path / "bad"
    folder.mkdir()
    bad = _make_bad_inputs(data, folder, SLOT_EXT.get(slot, ".exr"))[kind]
    out = tmp_path / ("out" + OUT_EXT[slot.split(":")[0]])
    before = _snapshot(data, tmp_path)
    r = _run_inproc_fail(SLOTS[slot](data, bad, out), 1)
    assert str(bad) in r.stderr or os.path.basename(str(bad)) in r.stderr, r.stderr
    assert _snapshot(data, tmp_path) == before


# Impossible option values: usage errors (exit 2) before any work.
BAD_OPTIONS = {
    "envmap --rotate-y nan": lambda d, o: ["envmap", d / "sky.exr", "--rotate-y", "nan", "-o", o],
    "envmap --rotate-y inf": lambda d, o: ["envmap", d / "sky.exr", "--rotate-y", "inf", "-o", o],
    "fit-geometry --seed -1": lambda d, o: ["fit-geometry", "--pose", "random", "--seed", "-1",
                                            "-o", o],
    "fit-geometry --smooth nan": lambda d, o: ["fit-geometry", "--smooth", "nan", "-o", o],
    "relight --shadow-strength nan": lambda d, o: ["relight", d / "ball.ply", "--probe",
                                                   d / "probe.json", "--shadow-strength", "nan",
                                                   "-o", o],
    "relight --background -1,0,0": lambda d, o: ["relight", d / "hand.npz", d / "sky.exr",
                                                 "--background", "-1,0,0", "-o", o],
    "relight --aov ''": lambda d, o: ["relight", d / "hand.npz", d / "sky.exr", "--aov", "",
                                      "-o", o],
    "relight --sss-scale 1e9": lambda d, o: ["relight", d / "hand.npz", d / "sky.exr",
                                             "--sss-scale", "1e9", "-o", o],
    "sh-probe --degree 17": lambda d, o: ["sh-probe", d / "sky.exr", "--degree", "17", "-o", o],
    "sh-probe --ridge inf": lambda d, o: ["sh-probe", d / "sky.exr", "--ridge", "inf", "-o", o],
    "dgsm-build --kappa nan": lambda d, o: ["dgsm-build", d / "ball.ply", "--t-max", "1",
                                            "--lights", d / "lights.json", "--kappa", "nan",
                                            "-o", o],
    "dgsm-build builtin:nope": lambda d, o: ["dgsm-build", "builtin:nope", "--t-max", "1",
                                             "--lights", d / "lights.json", "-o", o],
    "bake-features -o '{env.__class__}'": lambda d, o: [
        "bake-features", d / "hand.npz", d / "sky.exr", "-o", str(o.parent / "{env.__class__}.exr")],
    "metrics shadow --threshold nan": lambda d, o: ["metrics", "shadow", d / "img.exr",
                                                   d / "img2.exr", "--threshold", "nan", "-o", o],
    "metrics compare --rtol bogus=0.1": lambda d, o: ["metrics", "compare", d / "m.json",
                                                      d / "m.json", "--rtol", "bogus=0.1"],
    "camera --fov 0": lambda d, o: ["camera", "--eye", "0,0,1", "--fov", "0", "-o", o],
    "camera --eye inf,0,0": lambda d, o: ["camera", "--eye", "inf,0,0", "-o", o],
    "camera --orbit 0": lambda d, o: ["camera", "--orbit", "0", "--radius", "1", "-o", o],
    "envmap --preview x.jpg": lambda d, o: ["envmap", d / "sky.exr", "-o", o, "--preview",
                                            o.parent / "x.jpg"],
    "bake-features --preview x.exr": lambda d, o: ["bake-features", d / "hand.npz", d / "sky.exr",
                                                   "-o", o, "--preview", o.parent / "x.exr"],
    "sh-probe --preview x.json": lambda d, o: ["sh-probe", d / "sky.exr", "-o", o, "--preview",
                                               o.parent / "x.json"],
    "dgsm-build --preview x.tif": lambda d, o: ["dgsm-build", d / "ball.ply", "--t-max", "1",
                                                "--lights", d / "lights.json", "-o", o,
                                                "--preview", o.parent / "x.tif"],
    "dgsm-build --preview-camera alone": lambda d, o: [
        "dgsm-build", d / "ball.ply", "--t-max", "1", "--lights", d / "lights.json", "-o", o,
        "--preview-camera", d / "lights.json"],
    "synth-capture --preview x.exr": lambda d, o: ["synth-capture", "-o", o.parent / "cap",
                                                   "--preview", o.parent / "x.exr"],
}


@pytest.mark.parametrize("case", sorted(BAD_OPTIONS))
def test_impossible_option_is_a_usage_error(data, tmp_path, case):
    out = tmp_path / ("out.ply" if "shadow-strength" in case else "out.exr")
    if case.startswith(("sh-probe", "metrics", "camera")):
        out = tmp_path / "out.json"
    if case.startswith("fit-geometry"):
        out = tmp_path / "out.npz"
    before = _snapshot(data, tmp_path)
    _run_inproc_fail(BAD_OPTIONS[case](data, out), 2)
    assert _snapshot(data, tmp_path) == before


def test_metrics_compare_fails_on_nan_and_inf(data, tmp_path):
    record = json.loads((data / "m.json").read_text())
    for value in ("NaN", "Infinity"):
        text = json.dumps(record).replace('"psnr": ', f'"psnr": {value}, "was": ', 1)
        bad = tmp_path / f"{value}.json"
        bad.write_text(text)
        for new, base in ((bad, data / "m.json"), (data / "m.json", bad)):
            r = CliRunner().invoke(cli, ["metrics", "compare", str(new), str(base), "-q"])
            assert r.exit_code == 3, (value, r.output)


def test_library_warnings_do_not_reach_stderr(data, tmp_path, monkeypatch):
    """Warnings of numpy, torch or pygltflib before an error would break 'one line'."""
    import warnings

    from relight_cli.errors import DataError
    from relight_cli.formats import envmap as formats_envmap

    def noisy(path, **_):
        warnings.warn("a library's complaint", UserWarning)
        np.float64(1) / np.float64(0)          # numpy's RuntimeWarning
        raise DataError("damaged", path)
    monkeypatch.setattr(formats_envmap, "read_envmap", noisy)
    _run_inproc_fail(["envmap", data / "sky.exr", "-o", tmp_path / "x.exr"], 1, "damaged")
    for before, after in ((["--debug"], []), ([], ["--debug"])):   # --debug lets them through
        with pytest.warns((UserWarning, RuntimeWarning)) as shown:
            CliRunner().invoke(cli, before + ["envmap", str(data / "sky.exr"), "-o",
                                              str(tmp_path / "x.exr")] + after)
        assert any("complaint" in str(w.message) for w in shown)


def test_fit_geometry_refuses_to_write_over_its_keypoints(data, tmp_path):
    from relight_cli.hand.model import builtin_hand
    kp = tmp_path / "kp.npy"
    np.save(kp, builtin_hand("right", pose=None).rest_joints[None])
    before = _snapshot(tmp_path)
    _run_inproc_fail(["fit-geometry", "--keypoints", kp, "-o", kp], 2,
                     ("also an input", "name it .npz"))
    assert _snapshot(tmp_path) == before


def test_synth_capture_refuses_an_env_map_from_a_newer_relight(data, tmp_path):
    bad = tmp_path / "v99.exr"
    _exr(bad, {c: np.ones((4, 8), np.float32) for c in "RGB"},
         {"relight.format": "relight/envmap", "relight.version": 99})
    _run_inproc_fail(["synth-capture", data / "hand.npz", "-o", tmp_path / "cap", "--cameras",
                      "1", "--eval-cameras", "1", "--eval-envs", bad], 1, "version 99")
    assert sorted(os.listdir(tmp_path)) == ["v99.exr"]


def test_metrics_lighting_refuses_a_relit_avatar_of_another_size(data, tmp_path):
    _run_inproc_fail(["metrics", "lighting", "--scene", data / "room.ply", "--avatar",
                      data / "ball.ply", "--relit", data / "room.ply", "-o", tmp_path / "l.json"],
                     1, "Gaussians")


# ----------------------------------------------------------------------------- interruptions


def _wait_for_temp(folder: Path, proc, timeout=60.0) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end and proc.poll() is None:
        if any(TEMP_MARK in n for n in os.listdir(folder)):
            return True
        time.sleep(0.005)
    return False


# signal -> (exit code, last stderr line) of a run that cleans up; SIGKILL cannot.
_STOPPED = {signal.SIGINT: (130, "interrupted"),
            signal.SIGTERM: (128 + signal.SIGTERM, "terminated by signal SIGTERM"),
            signal.SIGHUP: (128 + signal.SIGHUP, "terminated by signal SIGHUP")}


@pytest.mark.parametrize("how", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGKILL])
def test_killed_run_leaves_no_temp_files_after_the_next_run(data, tmp_path, how):
    """fit-geometry stages hand.npz, then renders the preview: stop it in between.
    Ctrl-C, SIGTERM and SIGHUP clean up at once; SIGKILL's leftovers go with the next run."""
    args = ["fit-geometry", "--pose", "fist", "-o", tmp_path / "h.npz", "--preview",
            tmp_path / "h.png", "--preview-size", "160x160", "-q"]
    proc = subprocess.Popen([relight_executable(), *map(str, args)], stderr=subprocess.PIPE,
                            text=True)
    if not _wait_for_temp(tmp_path, proc):
        proc.wait()
        pytest.skip("the run finished before a temporary file could be seen")
    proc.send_signal(how)
    if how == signal.SIGTERM:   # `timeout` signals the process, then its group: twice
        time.sleep(0.05)
        with contextlib.suppress(ProcessLookupError):
            proc.send_signal(how)
    stderr = proc.communicate(timeout=60)[1]
    if how in _STOPPED:
        code, last_line = _STOPPED[how]
        assert proc.returncode == code, stderr
        assert stderr.strip().splitlines()[-1].endswith(last_line), stderr
        assert "Traceback" not in stderr
        assert os.listdir(tmp_path) == []   # cleaned up at once, nothing half-written
    else:
        assert all(TEMP_MARK in n for n in os.listdir(tmp_path))  # only temp files, no output
    p = _subprocess(args)
    assert p.returncode == 0, p.stderr
    assert sorted(os.listdir(tmp_path)) == ["h.npz", "h.png"]


def test_stale_temp_files_of_live_processes_are_kept(tmp_path):
    from relight_cli.fileio import remove_stale_temps
    dead = tmp_path / f".x.exr{TEMP_MARK}999999999-abcdefgh.exr"
    alive = tmp_path / f".x.exr{TEMP_MARK}{os.getppid()}-abcdefgh.exr"
    other = tmp_path / f".y.exr{TEMP_MARK}999999999-abcdefgh.exr"
    for p in (dead, alive, other):
        p.write_text("x")
    assert remove_stale_temps(str(tmp_path), "x.exr") == [str(dead)]
    assert sorted(os.listdir(tmp_path)) == sorted([alive.name, other.name])


# ----------------------------------------------------------------------------- byte identity


IDENTITY = {
    "envmap": lambda d, t: (["envmap", d / "sky.exr", "--size", "16x8", "-o", t / "e.exr",
                             "--preview", t / "e.png"], ["e.exr", "e.png"]),
    "sh-probe": lambda d, t: (["sh-probe", d / "sky.exr", "--degree", "2", "-o", t / "p.json",
                               "--preview", t / "p.png"], ["p.json", "p.png"]),
    "envmap-cube": lambda d, t: (["envmap", d / "sky.exr", "--to", "cube", "--size", "4",
                                  "-o", t / "c.exr", "--preview", t / "c.png"], ["c.exr", "c.png"]),
    "fit-geometry": lambda d, t: (["fit-geometry", "--pose", "random", "--n-frames", "2", "--seed",
                                   "3", "-o", t / "h.npz"], ["h.npz"]),
    "bake-features": lambda d, t: (["bake-features", d / "hand.npz", d / "sky.exr", "--res", "8",
                                    "--env-res", "8x4", "-o", t / "f.exr", "--per-vertex",
                                    t / "f.npz", "--preview", t / "f.png"],
                                   ["f.exr", "f.npz", "f.png"]),
    "relight-hand": lambda d, t: (["relight", d / "hand.npz", d / "sky.exr", "--size", "8x8",
                                   "--tex-res", "8", "--aa", "1", "--env-res", "8x4",
                                   "-o", t / "r.exr"], ["r.exr"]),
    "relight-gaussians": lambda d, t: (["relight", d / "ball.ply", "--probe", d / "probe.json",
                                        "-o", t / "g.ply"], ["g.ply"]),
    "dgsm-build": lambda d, t: (["dgsm-build", d / "ball.ply", "--receivers", d / "room.ply",
                                 "--lights", d / "lights.json", "--size", "4", "--bins", "2",
                                 "-o", t / "s.exr", "--preview", t / "s.png"], ["s.exr", "s.png"]),
    "metrics-image": lambda d, t: (["metrics", "image", d / "img.exr", d / "img2.exr",
                                    "-o", t / "m.json"], ["m.json"]),
    "metrics-lighting": lambda d, t: (["metrics", "lighting", "--scene", d / "room.ply",
                                       "--avatar", d / "ball.ply", "--max-points", "16",
                                       "--neighbours", "4", "-o", t / "l.json"], ["l.json"]),
    "train-teacher": lambda d, t: (["train-teacher", d / "cap", "--config", d / "small.json",
                                    "--iters", "2", "-o", t / "t.pt", "--metrics-out",
                                    t / "v.json"], ["t.pt", "v.json"]),
    "relight-teacher": lambda d, t: (["relight", d / "hand.npz", d / "sky.exr", "--model",
                                      "teacher", "--checkpoint", d / "teacher.pt", "--size",
                                      "8x8", "--env-res", "8x4", "-o", t / "r.exr"], ["r.exr"]),
    "relight-capture": lambda d, t: (["relight", d / "cap", "--model", "teacher",
                                      "--checkpoint", d / "teacher.pt", "--eval-samples", "1",
                                      "-o", t / "s.json"], ["s.json"]),
    "camera": lambda d, t: (["camera", "--orbit", "3", "--radius", "0.7", "--elevation", "20",
                             "-o", t / "c.json"], ["c.json"]),
    "synth-capture": lambda d, t: (["synth-capture", d / "hand.npz", "-o", t / "cap",
                                    "--cameras", "1", "--leds", "2", "--group", "1",
                                    "--n-frames", "1", "--size", "8", "--tex-res", "8", "--aa", "1",
                                    "--eval-poses", "0", "--eval-cameras", "1", "--preview",
                                    t / "cap.png"],
                                   ["cap/capture.json", "cap/hand.npz", "cap.png",
                                    "cap/images/000000/cam000.exr"]),
}


NO_CLOBBER: set[str] = set()  # commands without --no-clobber (none since issue 16)


def _identity_run(data, folder, name, second):
    if folder.exists():
        shutil.rmtree(folder)
    folder.mkdir(parents=True)
    args, files = IDENTITY[name](data, folder)
    extra = ["-q"] + ([] if name in NO_CLOBBER else ["--no-clobber"]) if second else []
    r = CliRunner().invoke(cli, (["--debug"] if second else []) + [str(a) for a in args] + extra)
    assert r.exit_code == 0, r.output
    if name == "synth-capture":
        files = files[:3] + sorted(str(p.relative_to(folder))
                                   for p in (folder / "cap" / "images").rglob("*.exr"))
    return {f: (folder / f).read_bytes() for f in files}


@pytest.fixture(scope="module")
def first_runs(data, tmp_path_factory):
    """Every command's outputs once, then a pause longer than zip's 2-second clock."""
    root = tmp_path_factory.mktemp("identity")
    runs = {name: _identity_run(data, root / name, name, False) for name in IDENTITY}
    time.sleep(2.1)
    return root, runs


@pytest.mark.parametrize("name", sorted(IDENTITY))
def test_identical_inputs_give_identical_bytes(data, first_runs, name):
    """A second run of the same command line (same output names) with presentation
    flags (-q, --debug, --no-clobber), seconds later (timestamps and timings would
    show), writes the same bytes."""
    root, runs = first_runs
    second = _identity_run(data, root / name, name, True)
    assert runs[name].keys() == second.keys()
    for f in second:
        assert runs[name][f] == second[f], f"{f} differs between identical runs"


# ----------------------------------------------------------------------------- issue 16:
# one syntax per kind (presentation flags in either place, extensions), and streams


def _mattes(folder: Path) -> tuple[Path, Path]:
    """Two 16×8 shadow mattes in [0, 1] (metrics shadow's inputs)."""
    a, b = folder / "matte_a.exr", folder / "matte_b.exr"
    ramp = np.tile(np.linspace(0, 1, 16, dtype=np.float32), (8, 1))
    _exr(a, {"Y": ramp}, {})
    _exr(b, {"Y": ramp ** 2}, {})
    return a, b


# Every command (and metrics subcommand) once more, for the presentation flags.
EVERY_COMMAND = {
    **{name: (lambda build, ext: lambda d, t: build(d, t / ("out" + ext)))(*COMMANDS[name])
       for name in COMMANDS},
    "synth-capture": lambda d, t: ["synth-capture", d / "hand.npz", "-o", t / "cap",
                                   "--cameras", "1", "--leds", "2", "--group", "1", "--n-frames",
                                   "1", "--size", "8", "--tex-res", "8", "--aa", "1",
                                   "--eval-poses", "0", "--eval-cameras", "1"],
    "metrics-compare": lambda d, t: ["metrics", "compare", d / "m.json", d / "m.json",
                                     "-o", t / "c.json"],
    "metrics-shadow": lambda d, t: ["metrics", "shadow", *_mattes(t.parent), "-o", t / "s.json"],
    "distill": lambda d, t: ["distill", d / "teacher.pt", d / "cap", "--envs", "builtin:sky",
                             "--envs", "builtin:uniform", "--eval-envs", "builtin:studio",
                             "--config", d / "student.json", "-o", t / "s.pt"],
}


@pytest.fixture(scope="module")
def student_config(data):
    path = data / "student.json"
    path.write_text(json.dumps({"tex_res": 8, "decoder": [2, 2, 2, 2, 2, 2, 2],
                                "pose_channels": [2, 2], "dram_code": 4, "val_samples": 1,
                                "env_res": [2, 4], "iters": 1}))
    return path


@pytest.mark.parametrize("name", sorted(EVERY_COMMAND))
def test_quiet_before_or_after_the_subcommand(data, student_config, tmp_path, name):
    """`relight -q CMD ...` and `relight CMD ... -q` are the same: nothing on stderr."""
    outputs = []
    for where in ("before", "after"):
        folder = tmp_path / where
        folder.mkdir()
        args = [str(a) for a in EVERY_COMMAND[name](data, folder)]
        r = CliRunner().invoke(cli, ["-q", *args] if where == "before" else [*args, "-q"])
        assert r.exit_code == 0, r.output
        assert r.stderr == "", (where, r.stderr)
        outputs.append(sorted(p.name for p in folder.iterdir()))
    assert outputs[0] == outputs[1]


@pytest.mark.parametrize("name", sorted(EVERY_COMMAND))
def test_debug_before_or_after_the_subcommand(data, tmp_path, name):
    """--debug in either place shows the traceback of a refusal, then its one line."""
    missing = tmp_path / "nope"
    for where in ("before", "after"):
        args = [str(a) for a in EVERY_COMMAND[name](data, missing)]
        r = CliRunner().invoke(cli, ["--debug", *args] if where == "before" else [*args, "--debug"])
        assert r.exit_code == 2, (where, r.output)
        assert "Traceback" in r.stderr and "does not exist" in r.stderr.splitlines()[-1], r.stderr
        plain = CliRunner().invoke(cli, args)
        assert "Traceback" not in plain.stderr and len(plain.stderr.splitlines()) == 1


# An output named with another kind's extension: a usage error naming the right one, before
# any work.  (name -> argv given data, a wrong output name; the extension it wants)
WRONG_EXTENSION = {
    "envmap -o sky.png": (lambda d, t: ["envmap", d / "sky.exr", "-o", t / "sky.png"], ".exr"),
    "envmap --preview .exr": (lambda d, t: ["envmap", d / "sky.exr", "-o", t / "a.exr",
                                            "--preview", t / "b.exr"], ".png"),
    "envmap --info -o .txt": (lambda d, t: ["envmap", d / "sky.exr", "--info", "-o",
                                            t / "i.txt"], ".exr"),
    "sh-probe -o .exr": (lambda d, t: ["sh-probe", d / "sky.exr", "-o", t / "p.exr"], ".json"),
    "fit-geometry -o .json": (lambda d, t: ["fit-geometry", "-o", t / "h.json"], ".npz"),
    "fit-geometry --report .npz": (lambda d, t: ["fit-geometry", "-o", t / "h.npz", "--report",
                                                 t / "r.npz"], ".json"),
    "fit-geometry --preview .jpg": (lambda d, t: ["fit-geometry", "-o", t / "h.npz",
                                                  "--preview", t / "h.jpg"], ".png"),
    "bake-features -o .png": (lambda d, t: ["bake-features", d / "hand.npz", d / "sky.exr",
                                            "-o", t / "f.png"], ".exr"),
    "bake-features --per-vertex .exr": (lambda d, t: ["bake-features", d / "hand.npz",
                                                      d / "sky.exr", "-o", t / "f.exr",
                                                      "--per-vertex", t / "v.exr"], ".npz"),
    "relight hand -o .png": (lambda d, t: ["relight", d / "hand.npz", d / "sky.exr", "-o",
                                           t / "r.png"], ".exr"),
    "relight hand --preview .exr": (lambda d, t: ["relight", d / "hand.npz", d / "sky.exr",
                                                  "-o", t / "r.exr", "--preview", t / "p.exr"],
                                    ".png"),
    "relight gaussians -o .exr": (lambda d, t: ["relight", d / "ball.ply", "--probe",
                                                d / "probe.json", "-o", t / "g.exr"], ".ply"),
    "dgsm-build -o .png": (lambda d, t: ["dgsm-build", d / "ball.ply", "--receivers",
                                         d / "room.ply", "--lights", d / "lights.json",
                                         "-o", t / "s.png"], ".exr"),
    "dgsm-build --lights-out .txt": (lambda d, t: ["dgsm-build", d / "ball.ply", "--receivers",
                                                   d / "room.ply", "--lights",
                                                   d / "lights.json", "-o", t / "s.exr",
                                                   "--lights-out", t / "l.txt"], ".json"),
    "dgsm-build --occluders-out .exr": (lambda d, t: ["dgsm-build", d / "ball.ply",
                                                      "--receivers", d / "room.ply", "--lights",
                                                      d / "lights.json", "-o", t / "s.exr",
                                                      "--occluders-out", t / "o.exr"], ".ply"),
    "metrics image -o .txt": (lambda d, t: ["metrics", "image", d / "img.exr", d / "img2.exr",
                                            "-o", t / "m.txt"], ".json"),
    "metrics image --jsonl .json": (lambda d, t: ["metrics", "image", d / "img.exr",
                                                  d / "img2.exr", "-o", t / "m.json",
                                                  "--jsonl", t / "rows.json"], ".jsonl"),
    "metrics compare -o .exr": (lambda d, t: ["metrics", "compare", d / "m.json", d / "m.json",
                                              "-o", t / "c.exr"], ".json"),
    "train-teacher -o .json": (lambda d, t: ["train-teacher", d / "cap", "-o", t / "t.json"],
                               ".pt"),
    "camera -o .txt": (lambda d, t: ["camera", "--eye", "0,0,1", "-o", t / "c.txt"], ".json"),
    "train-teacher --metrics-out .txt": (lambda d, t: ["train-teacher", d / "cap", "-o",
                                                       t / "t.pt", "--metrics-out", t / "v.txt"],
                                         ".json"),
}


@pytest.mark.parametrize("case", sorted(WRONG_EXTENSION))
def test_output_extension_must_say_what_is_written(data, tmp_path, case):
    build, wanted = WRONG_EXTENSION[case]
    before = _snapshot(data, tmp_path)
    _run_inproc_fail(build(data, tmp_path), 2, f"name it {wanted}")
    assert _snapshot(data, tmp_path) == before


def test_extensions_are_checked_in_any_case(data, tmp_path):
    r = _inproc("envmap", data / "sky.exr", "-o", tmp_path / "SKY.EXR", "-q")
    assert r.exit_code == 0 and (tmp_path / "SKY.EXR").exists()


# Binary outputs cannot go to stdout.
BINARY_TO_STDOUT = {
    "envmap": lambda d: ["envmap", d / "sky.exr", "-o", "-"],
    "envmap --preview -": lambda d: ["envmap", d / "sky.exr", "--info", "--preview", "-"],
    "fit-geometry": lambda d: ["fit-geometry", "-o", "-"],
    "bake-features": lambda d: ["bake-features", d / "hand.npz", d / "sky.exr", "-o", "-"],
    "relight-gaussians": lambda d: ["relight", d / "ball.ply", "--probe", d / "probe.json",
                                    "-o", "-"],
    "dgsm-build": lambda d: ["dgsm-build", d / "ball.ply", "--receivers", d / "room.ply",
                             "--lights", d / "lights.json", "-o", "-"],
    "train-teacher": lambda d: ["train-teacher", d / "cap", "-o", "-"],
    "synth-capture": lambda d: ["synth-capture", "-o", "-"],
}


@pytest.mark.parametrize("case", sorted(BINARY_TO_STDOUT))
def test_binary_outputs_cannot_go_to_stdout(data, case):
    r = _run_inproc_fail(BINARY_TO_STDOUT[case](data), 2)
    assert r.stdout == ""


# JSON outputs go to stdout with -o -: (argv, the format stdout holds)
JSON_TO_STDOUT = {
    "envmap --info": (lambda d: ["envmap", d / "sky.exr", "--info", "-o", "-"], None),
    "sh-probe": (lambda d: ["sh-probe", d / "sky.exr", "--degree", "1", "-o", "-"],
                 "relight/sh-probe"),
    "metrics image": (lambda d: ["metrics", "image", d / "img.exr", d / "img2.exr", "-o", "-"],
                      "relight/metrics"),
    "metrics compare": (lambda d: ["metrics", "compare", d / "m.json", d / "m.json", "-o", "-"],
                        "relight/metrics-comparison"),
    "metrics compare --json": (lambda d: ["metrics", "compare", d / "m.json", d / "m.json",
                                          "--json"], "relight/metrics-comparison"),
    "dgsm-build --lights-out": (lambda d: ["dgsm-build", d / "ball.ply", "--receivers",
                                           d / "room.ply", "--lights", d / "lights.json",
                                           "--size", "4", "--bins", "2", "-o", "{t}/s.exr",
                                           "--lights-out", "-"], "relight/lights"),
    "fit-geometry --report": (lambda d: ["fit-geometry", "-o", "{t}/h.npz", "--report", "-"],
                              None),
}


@pytest.mark.parametrize("case", sorted(JSON_TO_STDOUT))
def test_json_outputs_go_to_stdout(data, tmp_path, case):
    build, fmt = JSON_TO_STDOUT[case]
    args = [str(a).replace("{t}", str(tmp_path)) for a in build(data)]
    r = CliRunner().invoke(cli, args + ["-q"])
    assert r.exit_code == 0, r.output
    record = json.loads(r.stdout)
    if fmt is not None:
        assert record["format"] == fmt


def test_metrics_compare_json_is_written_even_on_a_regression(data, tmp_path):
    worse = json.loads((data / "m.json").read_text())
    worse["metrics"]["ssim"] = worse["metrics"]["ssim"] - 0.5
    (tmp_path / "worse.json").write_text(json.dumps(worse))
    out = tmp_path / "cmp.json"
    r = CliRunner().invoke(cli, ["metrics", "compare", str(tmp_path / "worse.json"),
                                 str(data / "m.json"), "-o", str(out)])
    assert r.exit_code == 3, r.output
    from relight_cli.formats.metrics_json import loads_comparison
    record = loads_comparison(out.read_text(), str(out))
    assert record["regressed"] and record["exit_code"] == 3 and record["kind"] == "image"
    rows = {row["metric"]: row for row in record["rows"]}
    assert rows["ssim"]["status"] == "REGRESSED" and rows["ssim"]["change"] == pytest.approx(-0.5)
    assert rows["mse"]["status"] == "ok" and not rows["mse"]["regressed"]
    assert record["counts"]["regressed"] == 1 == sum(r["regressed"] for r in record["rows"])
    assert record["inputs"]["baseline"]["sha256"] == hashlib.sha256(
        (data / "m.json").read_bytes()).hexdigest()
    # -o -: the JSON alone on stdout, the table on stderr
    r = CliRunner().invoke(cli, ["metrics", "compare", str(tmp_path / "worse.json"),
                                 str(data / "m.json"), "-o", "-"])
    assert r.exit_code == 3 and json.loads(r.stdout)["regressed"]
    assert "REGRESSED" in r.stderr
    # --no-clobber: refused before any work, the file untouched
    before = out.read_bytes()
    _run_inproc_fail(["metrics", "compare", data / "m.json", data / "m.json", "-o", out,
                      "--no-clobber"], 2, "--no-clobber")
    assert out.read_bytes() == before


# One JSON input of each kind read from stdin ('-'): (argv given data, output; the input
# piped in; where provenance records it, as a path into the output's JSON or None for EXR/PLY)
STDIN_INPUTS = {
    "relight --probe -": (lambda d, o: ["relight", d / "ball.ply", "--probe", "-", "-o",
                                        o / "g.ply"], "probe.json"),
    "dgsm-build --lights -": (lambda d, o: ["dgsm-build", d / "ball.ply", "--receivers",
                                            d / "room.ply", "--lights", "-", "--size", "4",
                                            "--bins", "2", "-o", o / "s.exr", "--lights-out",
                                            o / "l.json"], "lights.json"),
    "relight --lights -": (lambda d, o: ["relight", d / "hand.npz", "--lights", "-", "--size",
                                         "8x8", "--tex-res", "8", "--aa", "1", "-o",
                                         o / "r.exr"], "lights.json"),
    "relight --camera -": (lambda d, o: ["relight", d / "hand.npz", d / "sky.exr", "--camera",
                                         "-", "--tex-res", "8", "--aa", "1", "--env-res", "8x4",
                                         "-o", o / "r.exr"], "cam.json"),
    "camera --from -": (lambda d, o: ["camera", "--from", "-", "-o", o / "c.json"], "cam.json"),
    "bake-features --camera -": (lambda d, o: ["bake-features", d / "hand.npz", d / "sky.exr",
                                               "--camera", "-", "--res", "8", "--env-res", "8x4",
                                               "-o", o / "f.exr"], "cam.json"),
    "metrics compare NEW -": (lambda d, o: ["metrics", "compare", "-", d / "m.json", "-o",
                                            o / "c.json"], "m.json"),
    "metrics compare BASELINE -": (lambda d, o: ["metrics", "compare", d / "m.json", "-", "-o",
                                                 o / "c.json"], "m.json"),
    "train-teacher --config -": (lambda d, o: ["train-teacher", d / "cap", "--config", "-",
                                               "--iters", "1", "-o", o / "t.pt",
                                               "--metrics-out", o / "v.json"], "small.json"),
}


def _provenance_inputs(path: Path) -> dict:
    if path.suffix == ".json":
        record = json.loads(path.read_text())
        return (record.get("provenance") or record)["inputs"]
    if path.suffix == ".pt":
        import torch
        record = torch.load(path, weights_only=True)["provenance"]
        return (json.loads(record) if isinstance(record, str) else record)["inputs"]
    from relight_cli.formats.exr import read_exr
    if path.suffix == ".exr":
        return json.loads(read_exr(str(path)).attributes["relight.provenance"])["inputs"]
    from relight_cli.formats.gaussians_ply import read_gaussians
    return read_gaussians(str(path)).provenance["inputs"]


@pytest.mark.parametrize("case", sorted(STDIN_INPUTS))
def test_json_inputs_read_stdin(data, tmp_path, case):
    """`-` reads the JSON input from stdin; provenance records it as `-` with the SHA-256
    of the bytes read, and the output equals the one made from the file."""
    build, source = STDIN_INPUTS[case]
    piped, named = tmp_path / "piped", tmp_path / "named"
    piped.mkdir()
    named.mkdir()
    text = (data / source).read_bytes()
    r = CliRunner().invoke(cli, [str(a) for a in build(data, piped)] + ["-q"], input=text)
    assert r.exit_code == 0, r.output
    args = [str(data / source) if a == "-" else str(a) for a in build(data, named)]
    assert CliRunner().invoke(cli, args + ["-q"]).exit_code == 0
    first = sorted(p for p in piped.iterdir() if p.suffix != ".pt" or "train" in case)[0]
    inputs = _provenance_inputs(first)
    stdin = [v for v in inputs.values() if v["path"] == "-"]
    assert stdin and stdin[0]["sha256"] == hashlib.sha256(text).hexdigest(), inputs


STDIN_TWICE = {
    "metrics compare - -": lambda d, o: ["metrics", "compare", "-", "-"],
    "relight --camera - --lights -": lambda d, o: ["relight", d / "hand.npz", "--camera", "-",
                                                   "--lights", "-", "-o", o],
    "relight --probe - --camera -": lambda d, o: ["relight", d / "ball.ply", "--probe", "-",
                                                  "--camera", "-", "-o", o],
}


@pytest.mark.parametrize("case", sorted(STDIN_TWICE))
def test_only_one_input_reads_stdin(data, tmp_path, case):
    out = tmp_path / "x.exr"
    before = _snapshot(data, tmp_path)
    r = CliRunner().invoke(cli, [str(a) for a in STDIN_TWICE[case](data, out)], input="{}")
    _assert_one_error(r.exit_code, r.stderr, 2, "only one input can come from stdin")
    assert _snapshot(data, tmp_path) == before


@pytest.mark.parametrize("args", [
    lambda d: ["envmap", "-", "-o", "{t}/x.exr"],
    lambda d: ["relight", "-", "--probe", d / "probe.json", "-o", "{t}/x.ply"],
    lambda d: ["dgsm-build", "-", "--lights", d / "lights.json", "--t-max", "1", "-o", "{t}/x.exr"],
    lambda d: ["metrics", "image", "-", d / "img.exr"],
], ids=["envmap", "relight", "dgsm-build", "metrics-image"])
def test_binary_inputs_do_not_read_stdin(data, tmp_path, args):
    argv = [str(a).replace("{t}", str(tmp_path)) for a in args(data)]
    r = CliRunner().invoke(cli, argv, input=b"\x00" * 8)
    assert r.exit_code in (1, 2), r.output
    assert "Traceback" not in r.output and len(r.stderr.splitlines()) == 1, r.stderr
    assert os.listdir(tmp_path) == []


def test_broken_stdout_pipe_exits_quietly(data, tmp_path):
    """`relight metrics image a b -o - | head -c 10`: the reader is gone before relight
    writes; exit 141 (128 + SIGPIPE, as git), nothing on stderr, no file committed."""
    rows = tmp_path / "rows.jsonl"
    proc = subprocess.Popen([relight_executable(), "metrics", "image", str(data / "img.exr"),
                             str(data / "img2.exr"), "-o", "-", "--jsonl", str(rows)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            env=dict(os.environ, PYTHONWARNINGS="ignore"))
    proc.stdout.close()              # the reader goes away at once (head has had enough)
    stderr = proc.stderr.read().decode()
    proc.wait(timeout=120)
    proc.stderr.close()
    assert proc.returncode == 141, stderr
    assert stderr == "", stderr
    assert os.listdir(tmp_path) == []   # neither rows.jsonl nor a temporary file
    assert _temps_of(proc.pid) == []


def test_broken_pipe_through_a_shell_pipeline(data, tmp_path):
    """The same through `| head -c 10`, as a user types it: no error, 10 bytes."""
    cmd = (f"{_quote(relight_executable())} metrics image {_quote(data / 'img.exr')} "
           f"{_quote(data / 'img2.exr')} -o - -q | head -c 10")
    p = subprocess.run(["bash", "-o", "pipefail", "-c", cmd], capture_output=True,
                       timeout=120, env=dict(os.environ, PYTHONWARNINGS="ignore"))
    assert p.returncode in (0, 141), p.stderr
    assert p.stderr == b"" and len(p.stdout) == 10
