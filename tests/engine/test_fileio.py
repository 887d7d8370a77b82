"""relight_cli/fileio.py: atomic outputs, the output transaction, missing folders, inputs
replaced during a run."""

from __future__ import annotations

import os

import pytest

from relight_cli.errors import UsageProblem
from relight_cli.fileio import atomic_path, output_transaction


def test_atomic_path_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "out.txt"
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            open(tmp, "w").write("half")
            raise RuntimeError("boom")
    assert os.listdir(tmp_path) == []
    with atomic_path(target) as tmp:
        open(tmp, "w").write("whole")
    assert target.read_text() == "whole"
    assert oct(target.stat().st_mode & 0o777) != oct(0o600)  # not mkstemp's private mode


def test_output_transaction_is_all_or_nothing(tmp_path):
    a, b = tmp_path / "a.txt", tmp_path / "b.txt"
    with pytest.raises(ValueError):
        with output_transaction():
            with atomic_path(a) as tmp:
                open(tmp, "w").write("a")
            assert not a.exists()  # staged until the whole command succeeds
            raise ValueError("second output failed")
    assert os.listdir(tmp_path) == []
    with output_transaction():
        for p in (a, b):
            with atomic_path(p) as tmp:
                open(tmp, "w").write(p.name)
    assert a.read_text() == "a.txt" and b.read_text() == "b.txt"


def test_atomic_path_missing_folder_is_usage_error(tmp_path):
    with pytest.raises(UsageProblem):
        with atomic_path(tmp_path / "nope" / "x.exr"):
            pass


def test_an_input_replaced_during_a_run_does_not_make_its_old_inode_an_input(tmp_path):
    """Inputs are compared with outputs by what their paths are *now*: an input rewritten
    atomically by another process mid-run leaves its old inode free, and a file this run
    writes later may get that inode number (a checkpoint save of a long ``distill`` was
    refused as "also an input" that way).  Moving the old inode onto the output path is
    the deterministic version of that reuse; the input's path itself is still refused."""
    from relight_cli.errors import UsageProblem
    from relight_cli.fileio import atomic_path, declare_input, output_transaction
    config, saved = tmp_path / "config.json", tmp_path / "student.pt"
    config.write_text("{}")
    with output_transaction():
        declare_input(str(config))
        os.rename(config, saved)               # the old inode now sits at the output path
        config.write_text('{"rewritten": true}')
        with atomic_path(saved) as tmp:
            open(tmp, "w").write("checkpoint")
        with pytest.raises(UsageProblem, match="also an input"):
            with atomic_path(config) as tmp:
                open(tmp, "w").write("clobber")
    assert saved.read_text() == "checkpoint" and config.read_text() == '{"rewritten": true}'



def test_declaring_a_fifo_input_does_not_open_it(tmp_path):
    """A JSON input may be a named FIFO (``mkfifo c.json; relight train-teacher ... --config
    c.json``): declaring it (check_input) must not open it to hash it.  Opening it blocked
    until a writer came, connected that writer to a reader that closed at once (its bytes
    lost), and the real read then blocked for ever: the sweep of issue 52 (train-teacher and
    distill --config FIFO, relight CAPTURE/ with a FIFO capture.json) ran > 60 s.  With no
    writer at all, the old code blocks here; a reader is then let go by opening the FIFO's
    other end."""
    import threading

    from relight_cli.fileio import declare_input, input_digest

    fifo = str(tmp_path / "c.json")
    os.mkfifo(fifo)
    done = {}

    def run():
        with output_transaction():
            declare_input(fifo)
            done["digest"] = input_digest(fifo)
    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(10)
    blocked = thread.is_alive()
    if blocked:   # let the stuck open() return (a writer that writes nothing)
        os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
        thread.join(5)
    assert not blocked, "declare_input opened the FIFO"
    assert done == {"digest": None}    # a FIFO's bytes are hashed as read (kept_stream)
