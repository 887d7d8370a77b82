"""Issue 52, causes 1, 3 and 6: a command's outputs are committed all or none (two-phase:
staged, checked, renamed with backups; devices and FIFOs written last; a failure restores
what was there), a run records the hash of the input bytes it read (not of a file that
replaced them mid-run), and a full disk under ``torch.save`` is the usual one-line error.

Everything here is small (8×8 renders, 16×8 env maps) and runs in seconds."""

from __future__ import annotations

import errno
import hashlib
import os
from pathlib import Path

import pytest
from click.testing import CliRunner

from relight_cli.cli import cli
from relight_cli.errors import OutputError
from relight_cli.fileio import TEMP_MARK, atomic_path, output_transaction


def _invoke(*args):
    return CliRunner().invoke(cli, [str(a) for a in args])


def _error_lines(result) -> list[str]:
    text = getattr(result, "stderr", None) or result.output
    return [line for line in text.splitlines() if ": error: " in line]


def _no_temps(folder: Path) -> None:
    assert not [n for n in os.listdir(folder) if TEMP_MARK in n], os.listdir(folder)


# ----------------------------------------------------------------------------- cause 1


def test_a_device_output_that_fails_leaves_the_other_outputs_as_they_were(tmp_path):
    """The issue's command: the EXR is staged and the preview goes to /dev/full; the old
    x.exr must still be there, byte for byte, and the line must name /dev/full."""
    target = tmp_path / "x.exr"
    target.write_text("old\n")
    r = _invoke("envmap", "builtin:studio", "--to", "latlong", "--size", "16x8",
                "-o", target, "--preview", "/dev/full")
    assert r.exit_code == 1, r.output
    lines = _error_lines(r)
    assert len(lines) == 1 and "/dev/full" in lines[0] and "no space" in lines[0], r.output
    assert target.read_bytes() == b"old\n"
    _no_temps(tmp_path)


def test_a_failed_run_says_no_wrote_line_and_a_good_one_says_each(tmp_path):
    """Without -q: "wrote FILE" is said once FILE is committed, so the run whose preview
    fails on /dev/full claims no output written; a good run says every one."""
    from conftest import run_relight
    target = tmp_path / "x.exr"
    target.write_text("old\n")
    bad = run_relight("envmap", "builtin:studio", "--to", "latlong", "--size", "16x8",
                      "-o", target, "--preview", "/dev/full")
    assert bad.returncode == 1, bad.stderr
    assert "wrote" not in bad.stderr, bad.stderr
    assert bad.stderr.strip().splitlines()[-1].startswith("relight envmap: error: cannot write")
    good = run_relight("envmap", "builtin:studio", "--to", "latlong", "--size", "16x8",
                       "-o", tmp_path / "y.exr", "--preview", tmp_path / "y.png")
    assert good.returncode == 0, good.stderr
    said = [line for line in good.stderr.splitlines() if line.startswith("wrote ")]
    assert said == [f"wrote {tmp_path / 'y.exr'}", f"wrote {tmp_path / 'y.png'}"], good.stderr


def test_a_new_output_is_removed_when_a_device_output_fails(tmp_path):
    target = tmp_path / "new.exr"
    r = _invoke("envmap", "builtin:studio", "--to", "latlong", "--size", "16x8",
                "-o", target, "--preview", "/dev/full")
    assert r.exit_code == 1, r.output
    assert os.listdir(tmp_path) == []


def _stage(path, text):
    with atomic_path(path) as tmp:
        with open(tmp, "w") as f:
            f.write(text)


def test_a_failed_later_rename_restores_the_earlier_ones(tmp_path, monkeypatch):
    """Three staged outputs, the third rename fails: the first (replacing an old file) is
    restored, the second (a new name) removed, nothing temporary left."""
    a, b, c = tmp_path / "a.txt", tmp_path / "b.txt", tmp_path / "c.txt"
    a.write_text("old a")
    c.write_text("old c")
    real_replace = os.replace

    def replace(src, dst, *args, **kw):
        if os.fspath(dst) == str(c) and not os.fspath(src).endswith(".bak"):
            raise OSError(errno.EIO, "Input/output error")
        return real_replace(src, dst, *args, **kw)
    monkeypatch.setattr(os, "replace", replace)
    with pytest.raises(OutputError) as info:
        with output_transaction():
            _stage(a, "new a")
            _stage(b, "new b")
            _stage(c, "new c")
    assert info.value.path == str(c)
    monkeypatch.setattr(os, "replace", real_replace)
    assert a.read_text() == "old a" and c.read_text() == "old c" and not b.exists()
    _no_temps(tmp_path)


@pytest.mark.parametrize("special", ["fifo", "/dev/full"])
@pytest.mark.parametrize("first", [True, False])
def test_a_special_target_that_fails_fails_the_whole_transaction(tmp_path, special, first):
    """A FIFO with no reader or /dev/full, staged first or last: it is written after
    every regular output is renamed, and its failure puts them all back."""
    a, b = tmp_path / "a.txt", tmp_path / "b.txt"
    a.write_text("old a")
    if special == "fifo":
        target = tmp_path / "pipe"
        os.mkfifo(target)
    else:
        target = Path(special)
    with pytest.raises(OutputError) as info:
        with output_transaction():
            if first:
                _stage(target, "to the special file")
            _stage(a, "new a")
            _stage(b, "new b")
            if not first:
                _stage(target, "to the special file")
    assert info.value.path == str(target)
    assert a.read_text() == "old a" and not b.exists()
    _no_temps(tmp_path)
    # and a successful transaction still commits every output, the old file replaced
    with output_transaction():
        _stage(a, "new a")
        _stage(b, "new b")
    assert a.read_text() == "new a" and b.read_text() == "new b"
    _no_temps(tmp_path)


@pytest.fixture(scope="module")
def hand(tmp_path_factory):
    root = tmp_path_factory.mktemp("transactions")
    r = _invoke("fit-geometry", "--pose", "random", "--n-frames", "4", "--seed", "1",
                "-o", root / "hand.npz", "-q")
    assert r.exit_code == 0, r.output
    for name, env in (("env.exr", "builtin:sky"), ("other.exr", "builtin:studio")):
        r = _invoke("envmap", env, "--to", "latlong", "--size", "8x4", "-o", root / name, "-q")
        assert r.exit_code == 0, r.output
    return root


RENDER = ["--size", "8x8", "--tex-res", "8", "--env-res", "8x4", "-q"]


def test_a_sequence_that_fails_at_frame_3_leaves_no_frame(hand, tmp_path):
    """`relight --frames` is one transaction: frame 2's output is a FIFO with no reader;
    no frame of this run stays on disk and the old frame 0 is as it was."""
    out = tmp_path / "seq"
    out.mkdir()
    (out / "f_0.exr").write_text("old frame")
    os.mkfifo(out / "f_2.exr")
    r = _invoke("relight", hand / "hand.npz", hand / "env.exr", *RENDER,
                "--frames", "0:4", "-o", out / "f_{frame}.exr")
    assert r.exit_code == 1, r.output
    assert len(_error_lines(r)) == 1 and "f_2.exr" in _error_lines(r)[0], r.output
    assert sorted(os.listdir(out)) == ["f_0.exr", "f_2.exr"]
    assert (out / "f_0.exr").read_text() == "old frame"


# ----------------------------------------------------------------------------- cause 3


def test_provenance_records_the_env_map_that_was_read(hand, tmp_path, monkeypatch):
    """The env map is replaced by another file after frame 0 is written: every frame was
    rendered from the first map, so every frame records the first map's hash."""
    import relight_cli.formats.exr as exr
    env = tmp_path / "env.exr"
    env.write_bytes((hand / "env.exr").read_bytes())
    first = hashlib.sha256(env.read_bytes()).hexdigest()
    real_write = exr.write_exr
    calls = []

    def write_exr(path, *args, **kw):
        real_write(path, *args, **kw)
        calls.append(path)
        if len(calls) == 1:       # another process replaces the env map mid-run
            new = tmp_path / "new.exr"
            new.write_bytes((hand / "other.exr").read_bytes())
            os.replace(new, env)
    monkeypatch.setattr(exr, "write_exr", write_exr)
    out = tmp_path / "seq"
    out.mkdir()
    r = _invoke("relight", hand / "hand.npz", env, *RENDER, "--frames", "0:3",
                "-o", out / "f_{frame}.exr")
    assert r.exit_code == 0, r.output
    assert len(calls) == 3
    assert hashlib.sha256(env.read_bytes()).hexdigest() != first
    for frame in range(3):
        record = exr.read_exr(str(out / f"f_{frame}.exr")).provenance()
        assert record["inputs"]["env"]["sha256"] == first, frame


def test_provenance_outside_a_command_hashes_the_file_now(tmp_path):
    from relight_cli.provenance import file_sha256
    p = tmp_path / "a.json"
    p.write_text("{}")
    assert file_sha256(p) == hashlib.sha256(b"{}").hexdigest()
    p.write_text("[]")
    assert file_sha256(p) == hashlib.sha256(b"[]").hexdigest()


def test_a_file_read_twice_in_a_run_has_one_hash(tmp_path, monkeypatch):
    """Within one command an input has one hash, whatever name it is given by (relative,
    absolute, through a symlink) and however often an output's provenance asks: the
    bytes hashed when it was first declared."""
    from relight_cli.fileio import declare_input
    from relight_cli.provenance import file_sha256, provenance
    p = tmp_path / "in.json"
    p.write_text("{}")
    (tmp_path / "link.json").symlink_to(p)
    monkeypatch.chdir(tmp_path)
    first = hashlib.sha256(b"{}").hexdigest()
    with output_transaction():
        declare_input("in.json")
        p.write_text("[]")              # rewritten in place by someone else
        assert file_sha256(str(p)) == first
        assert provenance("x", 1, {"a": "in.json", "b": "link.json"})["inputs"]["b"][
            "sha256"] == first
    assert file_sha256(str(p)) == hashlib.sha256(b"[]").hexdigest()   # the run is over


# ----------------------------------------------------------------------------- cause 6


def test_a_full_disk_under_torch_save_is_one_line(tmp_path, monkeypatch):
    """torch.save's zip writer turns the file's ENOSPC into RuntimeError('[enforce fail at
    inline_container.cc…]'); write_checkpoint reports it as every output does."""
    torch = pytest.importorskip("torch")
    from formats.checkpoint import write_checkpoint
    real_save = torch.save

    class Full:
        def __init__(self, f):
            self.f, self.n = f, 0

        def write(self, data):
            self.n += len(data)
            if self.n > 200:
                raise OSError(errno.ENOSPC, "No space left on device")
            return self.f.write(data)

        def flush(self):
            return self.f.flush()

    monkeypatch.setattr(torch, "save", lambda obj, f, *a, **kw: real_save(obj, Full(f), *a, **kw))
    target = tmp_path / "model.pt"
    with pytest.raises(OutputError) as info:
        with output_transaction():
            write_checkpoint(str(target), {"weights": torch.zeros(1000)})
    assert str(info.value) == f"cannot write: no space left on device ({target})"
    assert os.listdir(tmp_path) == []


def test_a_checkpoint_on_dev_full(tmp_path):
    torch = pytest.importorskip("torch")
    from formats.checkpoint import write_checkpoint
    with pytest.raises(OutputError) as info:
        with output_transaction():
            write_checkpoint("/dev/full", {"weights": torch.zeros(1000)})
    assert "no space left on device" in str(info.value) and "/dev/full" in str(info.value)


def test_a_checkpoint_on_a_really_full_disk(tmp_path):
    """The same on a 64 KiB tmpfs (an unprivileged mount namespace): torch's zip writer
    gets a short write, not an OSError; the line still says the disk is full."""
    pytest.importorskip("torch")
    import subprocess
    import sys

    from sweep import _full_filesystem_available
    reason = _full_filesystem_available()
    if reason:
        pytest.skip(reason)
    script = tmp_path / "save.py"
    script.write_text(
        "import os, sys, torch\n"
        "from relight_cli.fileio import output_transaction\n"
        "from formats.checkpoint import write_checkpoint\n"
        "d = sys.argv[1]\n"
        "try:\n"
        "    with output_transaction():\n"
        "        write_checkpoint(os.path.join(d, 'm.pt'), {'w': torch.randn(100000)})\n"
        "except Exception as e:\n"
        "    print(type(e).__name__, e)\n"
        "print(sorted(os.listdir(d)))\n")
    root = Path(__file__).resolve().parents[2]
    r = subprocess.run(["unshare", "-rm", "sh", "-c",
                        'd=$(mktemp -d) && mount -t tmpfs -o size=64k tmpfs "$d" && '
                        f'"{sys.executable}" "{script}" "$d"; s=$?; umount "$d"; exit $s'],
                       capture_output=True, text=True, cwd=root, timeout=120,
                       env=dict(os.environ, PYTHONPATH=os.pathsep.join(
                           filter(None, [os.environ.get("PYTHONPATH"), str(root)]))))
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert lines[0].startswith("OutputError cannot write: no space left on device ("), r.stdout
    assert lines[0].endswith("/m.pt)") and lines[1] == "[]", r.stdout
