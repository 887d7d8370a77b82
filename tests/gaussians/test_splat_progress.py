"""A long Gaussian render says how far it is (issue 53, item 6): progress over the tiles
on stderr (a plain line off a terminal), only when the render looks long, never under
--quiet, and the pixels are the same with or without it."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest

from relight_cli.formats.camera import Camera
from relight_cli.gaussians import splat


def _scene(n=300, seed=0):
    from relight_cli.formats.gaussians_ply import Gaussians
    rng = np.random.default_rng(seed)
    return Gaussians(rng.uniform(-0.3, 0.3, (n, 3)), np.full((n, 3), 0.05),
                     np.tile([1.0, 0, 0, 0], (n, 1)), np.full(n, 0.7),
                     rng.uniform(-1, 1, (n, 1, 3)), 0)


def _camera(size=48):
    f = size * 1.2
    K = np.array([[f, 0, (size - 1) / 2], [0, f, (size - 1) / 2], [0, 0, 1]])
    return Camera(K, np.eye(3), np.array([0, 0, 1.5]), size, size)


def test_long_render_shows_tile_progress_and_same_pixels(monkeypatch, capsys):
    g, cam = _scene(), _camera()
    quiet = splat.render(g, cam)
    assert capsys.readouterr().err == ""                 # quiet by default (library use)
    splat.render(g, cam, quiet=False)                     # a short render stays silent
    assert capsys.readouterr().err == ""
    monkeypatch.setattr(splat, "PROGRESS_SECONDS", 0.0)   # every render counts as long
    loud = splat.render(g, cam, quiet=False)
    err = capsys.readouterr().err.splitlines()
    busy = int(err[-1].split("/")[1].split()[0])
    assert err[-1].startswith("relight") and err[-1].endswith(f": {busy}/{busy} tiles (100%)"), err
    assert 0 < busy <= (48 // 8) ** 2
    assert len(err) == 1                                  # one final line, no bar redraws
    assert np.array_equal(loud.image, quiet.image) and np.array_equal(loud.alpha, quiet.alpha)
    splat.render(g, cam, quiet=True)
    assert capsys.readouterr().err == ""


def test_late_progress_opens_only_for_long_work():
    """The estimate: after a fifth of the threshold, elapsed × total / done ≥ threshold."""
    from relight_cli import progress as P
    now = [0.0]
    stream = io.StringIO()
    real = P.progress
    P.progress = lambda **kw: P.PlainProgress(stream=stream, clock=lambda: now[0],
                                              **{k: v for k, v in kw.items()})
    try:
        fast = P.LateProgress(100, unit="tiles", seconds=5.0, clock=lambda: now[0])
        for _ in range(100):
            now[0] += 0.02                                 # 2 s in all: never shown
            fast.update(1)
        fast.close()
        assert stream.getvalue() == ""
        now[0] = 0.0
        slow = P.LateProgress(100, unit="tiles", seconds=5.0, clock=lambda: now[0])
        for i in range(100):
            now[0] += 0.125                                # 12.5 s in all: shown at 1 s
            slow.update(1)
            if i == 6:
                assert slow.bar is None                    # 0.875 s: too early to tell
            if i == 7:
                assert slow.bar is not None and slow.bar.n == 8
        slow.close()
        assert stream.getvalue().splitlines()[-1].endswith(": 100/100 tiles (100%)")
    finally:
        P.progress = real


@pytest.mark.parametrize("quiet", [False, True])
def test_relight_command_says_tile_progress(run_cli_stderr, tmp_path, monkeypatch, quiet):
    """``relight relight AVATAR --camera`` with a long render: the tile line on stderr
    (the CLI's command name), none with -q; the EXR is written either way."""
    monkeypatch.setattr(splat, "PROGRESS_SECONDS", 0.0)
    probe = tmp_path / "probe.json"
    cam = tmp_path / "cam.json"
    r = run_cli_stderr("sh-probe", "builtin:uniform", "--degree", "0", "-o", probe, "-q")
    assert r.exit_code == 0, r.stderr
    r = run_cli_stderr("camera", "--eye", "0,0.2,0.5", "--target", "0,0,0", "--size", "32x24",
                       "-o", cam, "-q")
    assert r.exit_code == 0, r.stderr
    out = tmp_path / "x.exr"
    r = run_cli_stderr("relight", "builtin:hand", "--probe", probe, "--camera", cam, "-o", out,
                       *(["-q"] if quiet else []))
    assert r.exit_code == 0, r.stderr
    assert out.exists()
    lines = [s for s in r.stderr.splitlines() if "tiles (" in s]
    if quiet:
        assert lines == [], r.stderr
    else:
        assert lines and lines[-1].startswith("relight relight: ") and \
            lines[-1].endswith("tiles (100%)"), r.stderr


@pytest.fixture
def run_cli_stderr():
    from click.testing import CliRunner

    from relight_cli.cli import cli

    def run(*args):
        try:
            runner = CliRunner(mix_stderr=False)
        except TypeError:                                  # click ≥ 8.2: always separate
            runner = CliRunner()
        return runner.invoke(cli, [str(a) for a in args], catch_exceptions=False)
    return run
