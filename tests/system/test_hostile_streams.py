"""Hostile streams and special files (issue 23): every case ends with one line
``relight CMD: error: WHAT (FILE)``, the documented exit code, no traceback, nothing
written and the inputs untouched.

- stdout cut short (a reader that went away mid-document, a full disk, /dev/full, a
  closed descriptor): 141 for a closed pipe, else 1 naming ``stdout``; a command with
  file outputs commits none of them (relight_cli.fileio._emit_stdout, run by
  output_transaction before the commit).
- special files as inputs: a FIFO or device where a binary file is needed is refused
  (cli.tools.check_input); a JSON input may be a FIFO but is read at most 256 MiB.
- an input the reader may not open (permissions, a folder, EIO), a library message in
  raw bytes (OpenImageIO on damaged EXRs), a MemoryError from an .npy header, a
  message ending ``(<in memory>)``: one line naming the file (relight_cli/cli/__init__.py).

Cases that need a real descriptor (pipes, /dev/full, ``>&-``, ``ulimit -f``, another
user) run the console script; the rest run in-process through click's CliRunner.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import shlex
import shutil
import stat
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from conftest import SHARED_DATA, relight_executable
from models import SWEEP_CAPTURE, SWEEP_TEACHER, SWEEP_TEACHER_CONFIG, copy_entry
from relight_cli.cli import cli

TEMP_MARK = ".relight-tmp-"


# ----------------------------------------------------------------------------- inputs


def _inproc(*args, **kw):
    return CliRunner().invoke(cli, [str(a) for a in args], **kw)


@pytest.fixture(scope="module")
def data(tmp_path_factory, tiny_models):
    """Tiny inputs: an env map, a probe, a Gaussians PLY, keypoints, a 3-frame capture
    and a teacher trained on it for one iteration (those two made once per run,
    tests/models.py, and copied here)."""
    d = tmp_path_factory.mktemp("hostile")
    os.chmod(d, 0o755)
    for args in (["envmap", "builtin:sky", "--size", "8x4", "-o", d / "sky.exr"],
                 ["sh-probe", d / "sky.exr", "--degree", "1", "-o", d / "probe.json"]):
        r = _inproc(*args)
        assert r.exit_code == 0, r.output
    copy_entry(tiny_models.get("capture", SWEEP_CAPTURE), d / "cap")
    (d / "small.json").write_text(json.dumps(SWEEP_TEACHER_CONFIG))
    copy_entry(tiny_models.get(SWEEP_TEACHER[0], SWEEP_CAPTURE, *SWEEP_TEACHER[1:]),
               d / "teacher.pt")
    import trimesh

    from relight_cli.formats.gaussians_ply import write_gaussians
    from relight_cli.gaussians.from_mesh import gaussians_from_mesh
    from relight_cli.hand.model import builtin_hand
    ball = trimesh.creation.icosphere(subdivisions=1, radius=0.1)
    write_gaussians(str(d / "ball.ply"), gaussians_from_mesh(ball.vertices, ball.faces))
    rest = builtin_hand("right", pose=None).rest_joints
    np.save(d / "kp40.npy", np.repeat(rest[None], 40, 0))          # a ~6 KB fit report
    np.save(d / "kp_far.npy", np.repeat(rest[None], 2, 0) + 1e5)   # fits 100 km away
    (d / "pose_far.json").write_text(json.dumps(
        {"poses": np.zeros((1, 25, 3)).tolist(), "translations": [[1e6, 0.0, 0.0]]}))
    from numpy.lib import format as npy_format
    with open(d / "huge.npy", "wb") as f:   # declares 600 TB of float64, holds 64 bytes
        npy_format.write_array_header_1_0(
            f, {"descr": "<f8", "fortran_order": False, "shape": (10**6, 25, 3 * 10**6)})
        f.write(b"\0" * 64)
    with open(d / "big.json", "wb") as f:   # sparse: 257 MiB that take no disk
        f.truncate(257 * 1024 * 1024)
    for root, dirs, files in os.walk(d):
        for name in dirs:
            os.chmod(os.path.join(root, name), 0o755)
        for name in files:
            os.chmod(os.path.join(root, name), 0o644)
    return d


def _digest(folder: Path) -> dict:
    """Every entry under ``folder`` (hidden ones too): type and content hash."""
    seen = {}
    for root, dirs, files in os.walk(folder):
        for name in dirs + files:
            p = os.path.join(root, name)
            st = os.lstat(p)
            digest = None
            if stat.S_ISREG(st.st_mode) and st.st_size < 1 << 20:
                digest = hashlib.sha256(Path(p).read_bytes()).hexdigest()
            seen[p] = (stat.S_IFMT(st.st_mode), st.st_size, digest)
    return seen


@pytest.fixture
def untouched(data):
    """The inputs are the same after the test as before it."""
    before = _digest(data)
    yield
    assert _digest(data) == before


def _assert_one_error(code, stderr, expected_code, *words):
    if isinstance(stderr, bytes):
        stderr = stderr.decode("utf-8", "replace")
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert code == expected_code, stderr
    assert len(lines) == 1, stderr
    assert lines[0].startswith("relight "), lines[0]
    assert ": error: " in lines[0], lines[0]
    assert "traceback" not in stderr.lower() and "internal error" not in stderr, stderr
    for w in words:
        assert w in lines[0], lines[0]
    return lines[0]


def _env(**extra):
    # PYTHONUNBUFFERED makes Python's stdout accept a short write silently: the
    # condition under which a cut-short document used to exit 0.
    return dict(os.environ, PYTHONWARNINGS="ignore", PYTHONUNBUFFERED="1",
                OMP_NUM_THREADS="1", **extra)


def _sh(script: str, cwd, timeout=120) -> subprocess.CompletedProcess:
    """Run a bash script in which $R is the relight console script."""
    return subprocess.run(["bash", "-c", f"R={shlex.quote(relight_executable())}; {script}"],
                          capture_output=True, timeout=timeout, cwd=cwd, env=_env())


def _no_temps(folder: Path) -> None:
    left = [p for p in folder.rglob("*") if TEMP_MARK in p.name]
    assert left == [], left


# ----------------------------------------------------------------------------- stdout


ORBIT = "$R camera --orbit 2000 --radius 1 -o -"   # an 800 KB JSON document

STREAM_CASES = {
    # name: (bash script run in tmp_path, exit code, words of the line, files left)
    "closed-pipe-head": (f"set -o pipefail; {ORBIT} | head -c 10 > head.out",
                         141, (), ["head.out"]),
    "dev-full": (f"{ORBIT} > /dev/full", 1, ("cannot write: no space left on device",
                                             "(stdout)"), []),
    "closed-stdout": (f"{ORBIT} >&-", 1, ("cannot write: stdout is closed", "(stdout)"), []),
    "full-file": (f"ulimit -f 32; {ORBIT} > out.json", 1, ("cannot write:", "(stdout)"),
                  ["out.json"]),
    "full-file-append": (f"printf '{{}}\\n' > out.json; ulimit -f 32; {ORBIT} >> out.json", 1,
                         ("cannot write:", "(stdout)"), ["out.json"]),
    "report-to-full-device": ("$R fit-geometry --pose fist -q -o h.npz --report - > /dev/full",
                              1, ("no space left on device", "(stdout)"), []),
    "report-to-closed-stdout": ("$R fit-geometry --pose fist -q -o h.npz --report - >&-",
                                1, ("stdout is closed", "(stdout)"), []),
    "info-to-full-device": ("$R envmap builtin:sky --size 8x4 -q --info -o - > /dev/full",
                            1, ("no space left on device", "(stdout)"), []),
}


@pytest.mark.parametrize("name", sorted(STREAM_CASES))
def test_stdout_that_cannot_take_the_document(data, tmp_path, name, untouched):
    script, code, words, left = STREAM_CASES[name]
    p = _sh(script, tmp_path)
    if code == 141:
        assert p.returncode == 141 and p.stderr == b"", p.stderr
    else:
        _assert_one_error(p.returncode, p.stderr, code, *words)
    assert sorted(os.listdir(tmp_path)) == left          # no .npz, no temporary file
    if name == "closed-pipe-head":
        assert (tmp_path / "head.out").read_bytes() == b'{\n  "forma'
    if name == "full-file":             # cut back: the shell's file holds nothing
        assert (tmp_path / "out.json").read_bytes() == b""
    if name == "full-file-append":      # what was there before is all there is
        assert (tmp_path / "out.json").read_bytes() == b"{}\n"


def test_reader_gone_mid_document_commits_no_file(data, tmp_path, untouched):
    """`fit-geometry --keypoints K -o h.npz --report - | head`: the report is bigger than
    the pipe (shrunk to one page), the reader takes 10 bytes and goes: exit 141, and
    h.npz, staged, is never committed."""
    import fcntl
    r, w = os.pipe()
    fcntl.fcntl(w, fcntl.F_SETPIPE_SZ, 4096)
    proc = subprocess.Popen([relight_executable(), "fit-geometry", "--keypoints",
                             str(data / "kp40.npy"), "--iterations", "1", "-q",
                             "-o", str(tmp_path / "h.npz"), "--report", "-"],
                            stdout=w, stderr=subprocess.PIPE, env=_env())
    os.close(w)
    with os.fdopen(r, "rb") as reader:
        assert len(reader.read(10)) == 10
    stderr = proc.stderr.read()
    proc.wait(timeout=120)
    proc.stderr.close()
    assert proc.returncode == 141, stderr
    assert stderr == b""
    assert os.listdir(tmp_path) == []


def test_a_whole_document_still_goes_through(data, tmp_path):
    """The same commands with a reader that takes everything: exit 0, every byte."""
    p = _sh(f"{ORBIT} | cat > all.json && $R fit-geometry --pose fist -o h.npz --report - "
            f"> report.json", tmp_path)
    assert p.returncode == 0, p.stderr
    assert len(json.loads((tmp_path / "all.json").read_text())["cameras"]) == 2000
    assert json.loads((tmp_path / "report.json").read_text())["format"] == "relight/fit-report"
    assert (tmp_path / "h.npz").exists()


def test_stdout_document_waits_for_the_command():
    """In-process: a JSON document for stdout is held until the command succeeds and
    dropped when it fails; outside a transaction it is written at once."""
    import io

    from relight_cli import fileio as F

    raw = io.BytesIO()
    saved = sys.stdout
    sys.stdout = io.TextIOWrapper(raw, encoding="utf-8")
    try:
        with pytest.raises(RuntimeError):
            with F.output_transaction():
                F.write_text_atomic("-", "{}\n")
                assert raw.getvalue() == b""
                raise RuntimeError("the command failed")
        assert raw.getvalue() == b""
        with F.output_transaction():
            F.write_text_atomic("-", '{"a": 1}\n')
            assert raw.getvalue() == b""
        assert raw.getvalue() == b'{"a": 1}\n'
        F.write_text_atomic("-", "[]\n")
        assert raw.getvalue() == b'{"a": 1}\n[]\n'
    finally:
        sys.stdout = saved


def test_short_writes_are_finished(monkeypatch):
    """os.write taking a few bytes at a time: the loop finishes the document."""
    from relight_cli import fileio as F
    r, w = os.pipe()
    real = os.write
    monkeypatch.setattr(os, "write", lambda fd, b: real(fd, bytes(b)[:7]))
    try:
        F._write_fd(w, b"0123456789" * 30)
    finally:
        os.close(w)
    with os.fdopen(r, "rb") as f:
        assert f.read() == b"0123456789" * 30


# ----------------------------------------------------------------------------- special inputs


def test_fifo_as_a_binary_input_is_refused_at_once(data, tmp_path, untouched):
    """`mkfifo e.exr; relight envmap e.exr --info` used to block for ever."""
    fifo = tmp_path / "e.exr"
    os.mkfifo(fifo)
    p = _sh(f"$R envmap {shlex.quote(str(fifo))} --info", tmp_path, timeout=60)
    _assert_one_error(p.returncode, p.stderr, 1, "FIFO", "not a regular file", f"({fifo})")
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode)


def _node(folder: Path, name: str, kind: str) -> Path:
    """A FIFO, or a symlink to /dev/zero, named ``name`` (its extension says binary)."""
    folder.mkdir(exist_ok=True)
    path = folder / name
    if kind == "fifo":
        os.mkfifo(path)
    else:
        os.symlink("/dev/zero", path)
    return path


SPECIAL_INPUT_CASES = {
    # name: (argv given the data, inputs and output folders; words of the line)
    "dev-zero-as-envmap": (lambda d, i, t: ["envmap", "/dev/zero", "--info"],
                           ("character device", "(/dev/zero)")),
    "dev-zero-as-ply": (lambda d, i, t: ["relight", _node(i, "zero.ply", "zero"), "--probe",
                                         d / "probe.json", "-o", t / "x.ply"],
                        ("character device", "zero.ply)")),
    "dev-zero-as-hand-npz": (lambda d, i, t: ["relight", _node(i, "zero.npz", "zero"),
                                              d / "sky.exr", "-o", t / "x.exr"],
                             ("character device", "zero.npz)")),
    "fifo-as-checkpoint": (lambda d, i, t: ["relight", d / "cap", "--model", "teacher",
                                            "--checkpoint", _node(i, "t.pt", "fifo"),
                                            "--eval-samples", "1", "-o", t / "r.json"],
                           ("FIFO", "t.pt)")),
    "fifo-as-metrics-image": (lambda d, i, t: ["metrics", "image", _node(i, "a.exr", "fifo"),
                                               d / "sky.exr", "-o", t / "m.json"],
                              ("FIFO", "a.exr)")),
    "dev-zero-as-probe": (lambda d, i, t: ["relight", d / "ball.ply", "--probe", "/dev/zero",
                                           "-o", t / "x.ply"], ("256 MiB", "(/dev/zero)")),
    "sparse-json-over-the-limit": (lambda d, i, t: ["relight", d / "ball.ply", "--probe",
                                                    d / "big.json", "-o", t / "x.ply"],
                                   ("256 MiB", "big.json)")),
}


@pytest.mark.parametrize("name", sorted(SPECIAL_INPUT_CASES))
def test_special_files_as_inputs(data, tmp_path, name, untouched):
    build, words = SPECIAL_INPUT_CASES[name]
    out = tmp_path / "out"
    out.mkdir()
    r = _inproc(*build(data, tmp_path / "in", out), "-q")
    _assert_one_error(r.exit_code, r.stderr, 1, *words)
    assert os.listdir(out) == []


def test_stdin_over_the_limit_is_refused(data, tmp_path, monkeypatch):
    from relight_cli import fileio as F
    monkeypatch.setattr(F, "MAX_JSON_BYTES", 1000)
    probe = (data / "probe.json").read_bytes()
    r = CliRunner().invoke(cli, ["relight", str(data / "ball.ply"), "--probe", "-",
                                 "-o", str(tmp_path / "x.ply")], input=probe + b" " * 1000)
    _assert_one_error(r.exit_code, r.stderr, 1, "the most relight reads", "(-)")
    assert os.listdir(tmp_path) == []


def test_json_input_through_a_pipe_is_read_once_and_hashed(data, tmp_path):
    """A JSON input may be a FIFO (`--probe <(...)`): parsed, and its provenance hash is
    the hash of the bytes read (the FIFO is not opened a second time)."""
    probe = data / "probe.json"
    p = _sh(f"$R relight {shlex.quote(str(data / 'ball.ply'))} --probe <(cat "
            f"{shlex.quote(str(probe))}) -o x.ply -q", tmp_path, timeout=120)
    assert p.returncode == 0, p.stderr
    header = (tmp_path / "x.ply").read_bytes().split(b"end_header", 1)[0]
    assert hashlib.sha256(probe.read_bytes()).hexdigest().encode() in header, header[-600:]


# ----------------------------------------------------------------------------- unreadable files


@pytest.fixture
def refuse_open(monkeypatch):
    """builtins.open raising ``error`` for every path under ``folder`` (root reads mode-000
    files, so permissions are simulated in-process)."""
    import builtins
    real = builtins.open

    def install(folder: Path, error: int):
        prefix = os.path.realpath(folder) + os.sep

        def fake(file, *args, **kwargs):
            if isinstance(file, (str, os.PathLike)) and \
                    os.path.realpath(os.fspath(file)).startswith(prefix):
                raise OSError(error, os.strerror(error), os.fspath(file))
            return real(file, *args, **kwargs)
        monkeypatch.setattr(builtins, "open", fake)
    return install


UNREADABLE_CASES = {
    # name: (argv given data and output folder, errno, words)
    "train-teacher-permission": (
        lambda d, t: ["train-teacher", d / "cap", "--config", d / "small.json", "--iters", "1",
                      "-o", t / "t.pt"], errno.EACCES, "cannot read: permission denied"),
    "relight-capture-permission": (
        lambda d, t: ["relight", d / "cap", "--model", "teacher", "--checkpoint",
                      d / "teacher.pt", "--eval-samples", "1", "-o", t / "r.json"],
        errno.EACCES, "cannot read: permission denied"),
    "train-teacher-is-a-directory": (
        lambda d, t: ["train-teacher", d / "cap", "--config", d / "small.json", "--iters", "1",
                      "-o", t / "t.pt"], errno.EISDIR, "cannot read: is a directory"),
    "relight-capture-io-error": (
        lambda d, t: ["relight", d / "cap", "--model", "teacher", "--checkpoint",
                      d / "teacher.pt", "--eval-samples", "1", "-o", t / "r.json"],
        errno.EIO, "cannot read: input/output error"),
}


@pytest.mark.parametrize("name", sorted(UNREADABLE_CASES))
def test_unreadable_capture_image(data, tmp_path, name, refuse_open, untouched):
    build, error, words = UNREADABLE_CASES[name]
    argv = [str(a) for a in build(data, tmp_path)] + ["-q"]
    refuse_open(data / "cap" / "images", error)
    r = CliRunner().invoke(cli, argv)
    line = _assert_one_error(r.exit_code, r.stderr, 1, words)
    assert f"({data / 'cap' / 'images'}" in line, line
    assert os.listdir(tmp_path) == []


def _without_root_override():
    """preexec_fn: drop CAP_DAC_OVERRIDE and CAP_DAC_READ_SEARCH, so root obeys modes."""
    import ctypes
    libc = ctypes.CDLL(None, use_errno=True)
    for cap in (1, 2):
        if libc.prctl(24, cap, 0, 0, 0) != 0:  # PR_CAPBSET_DROP
            raise OSError(ctypes.get_errno(), "prctl(PR_CAPBSET_DROP)")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="Linux permissions")
def test_mode_000_image_as_a_user(data, tmp_path):
    """The real thing: a capture image with mode 000, relight run without root's override."""
    cap = tmp_path / "cap"
    shutil.copytree(data / "cap", cap)
    image = next(cap.glob("images/*/*.exr"))
    os.chmod(image, 0)
    out = tmp_path / "out"
    out.mkdir()
    try:
        p = subprocess.run([relight_executable(), "train-teacher", str(cap), "--config",
                            str(data / "small.json"), "--iters", "1", "-q",
                            "-o", str(out / "t.pt")], capture_output=True, timeout=120,
                           env=_env(),
                           preexec_fn=_without_root_override if os.geteuid() == 0 else None)
    except (OSError, subprocess.SubprocessError) as exc:
        pytest.skip(f"cannot drop root's permission override here: {exc}")
    finally:
        os.chmod(image, 0o644)
    _assert_one_error(p.returncode, p.stderr, 1, "cannot read: permission denied", f"({cap}/")
    assert os.listdir(out) == []


# ----------------------------------------------------------------------------- naming the file


NAMING_CASES = {
    "pose-json-far-away": (lambda d, t: ["fit-geometry", "--pose", d / "pose_far.json",
                                         "-o", t / "h.npz"], "pose_far.json)"),
    "keypoints-far-away": (lambda d, t: ["fit-geometry", "--keypoints", d / "kp_far.npy",
                                         "--iterations", "1", "-o", t / "h.npz"],
                           "kp_far.npy)"),
    "npy-with-a-huge-shape": (lambda d, t: ["fit-geometry", "--keypoints", d / "huge.npy",
                                            "-o", t / "h.npz"], "huge.npy)"),
}


@pytest.mark.parametrize("name", sorted(NAMING_CASES))
def test_messages_name_the_file(data, tmp_path, name, untouched):
    build, words = NAMING_CASES[name]
    r = _inproc(*build(data, tmp_path), "-q")
    line = _assert_one_error(r.exit_code, r.stderr, 1, words)
    assert "<in memory>" not in line and "smaller resolution" not in line, line
    assert os.listdir(tmp_path) == []


# ----------------------------------------------------------------------------- damaged EXRs


DAMAGED = (SHARED_DATA / "damaged-exr")
DAMAGED_FILES = sorted(p.name for p in DAMAGED.iterdir()) if DAMAGED.is_dir() else []


@pytest.fixture(scope="module")
def damaged(tmp_path_factory):
    """Each fuzzed file under its own name and as NAME.exr (so that OpenImageIO picks
    its EXR reader, whose messages hold raw header bytes)."""
    if not DAMAGED_FILES:
        pytest.skip(f"real test data not available: {DAMAGED}")
    folder = tmp_path_factory.mktemp("damaged")
    for name in DAMAGED_FILES:
        os.symlink(DAMAGED / name, folder / (name + ".exr"))
    return folder


@pytest.mark.parametrize("suffix", ["", ".exr"])
def test_damaged_exrs_get_one_line_each(damaged, tmp_path, suffix):
    """`relight metrics image F F -o o.json` and `relight envmap F --info` on every fuzzed
    EXR: exit 1 and one line naming F, never an internal error."""
    failures = []
    before = {name: (DAMAGED / name).stat().st_size for name in DAMAGED_FILES}
    for name in DAMAGED_FILES:
        f = str(damaged / (name + ".exr")) if suffix else str(DAMAGED / name)
        for argv in (["metrics", "image", f, f, "-o", str(tmp_path / "o.json")],
                     ["envmap", f, "--info"]):
            r = CliRunner().invoke(cli, argv)
            lines = [line for line in r.stderr.splitlines() if line.strip()]
            if (r.exit_code != 1 or len(lines) != 1 or "internal error" in r.stderr
                    or "Traceback" in r.output or not lines[0].endswith(f"({f})")
                    or r.stdout):
                failures.append((argv[0], name, r.exit_code, r.stderr[:300]))
    assert failures == [], failures[:5]
    assert os.listdir(tmp_path) == []
    assert before == {name: (DAMAGED / name).stat().st_size for name in DAMAGED_FILES}


#: every other command that reads an image (each refuses a damaged file before any work, so
#: the whole cross product costs a few seconds)
IMAGE_READERS = {
    "envmap-convert": lambda f, o: ["envmap", f, "--to", "latlong", "--size", "8x4", "-o",
                                    str(o / "o.exr")],
    "sh-probe": lambda f, o: ["sh-probe", f, "--degree", "1", "-o", str(o / "o.json")],
    "relight-env": lambda f, o: ["relight", "builtin:right", f, "--model", "physical",
                                 "--size", "16x16", "-o", str(o / "o.exr")],
    "bake-features": lambda f, o: ["bake-features", "builtin:right", f, "-o",
                                   str(o / "o.exr")],
    "camera-from": lambda f, o: ["camera", "--from", f, "-o", str(o / "o.json")],
}


@pytest.mark.parametrize("command", sorted(IMAGE_READERS))
def test_damaged_exrs_into_every_image_reader(damaged, tmp_path, command):
    """Every fuzzed EXR (as NAME.exr) into each command that reads an image: exit 1 and one
    line naming the file, nothing written, the file untouched."""
    failures = []
    sample = DAMAGED_FILES
    before = {name: (DAMAGED / name).stat().st_size for name in sample}
    for name in sample:
        f = str(damaged / (name + ".exr"))
        r = CliRunner().invoke(cli, IMAGE_READERS[command](f, tmp_path))
        lines = [line for line in r.stderr.splitlines() if line.strip()]
        if (r.exit_code != 1 or len(lines) != 1 or "internal error" in r.stderr
                or "Traceback" in r.output or not lines[0].endswith(f"({f})") or r.stdout):
            failures.append((name, r.exit_code, r.stderr[:300]))
    assert failures == [], failures[:5]
    assert os.listdir(tmp_path) == []
    assert before == {name: (DAMAGED / name).stat().st_size for name in sample}
