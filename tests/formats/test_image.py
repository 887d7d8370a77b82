"""formats/image.py: PNG reading and writing report errors as our one line only —
libpng's own ``libpng error: …`` never reaches stderr (issue 52, cause 13)."""

from __future__ import annotations

import resource
import signal

import numpy as np
import pytest

from relight_cli.errors import DataError, OutputError
from relight_cli.formats.image import read_image, write_png
from conftest import run_relight


@pytest.fixture
def pngs(tmp_path):
    rng = np.random.default_rng(0)
    write_png(str(tmp_path / "good.png"), rng.uniform(0, 1, (48, 64, 3)))
    data = (tmp_path / "good.png").read_bytes()
    (tmp_path / "cut.png").write_bytes(data[: len(data) // 2])
    return tmp_path


def test_truncated_png_raises_without_library_output(pngs, capfd):
    with pytest.raises(DataError) as info:
        read_image(str(pngs / "cut.png"))
    assert "cut.png" in str(info.value)
    out, err = capfd.readouterr()
    assert err == "" and out == ""


@pytest.mark.parametrize("where", ["pred", "gt", "mask"])
def test_truncated_png_input_one_line(pngs, where):
    d = pngs
    args = {"pred": [d / "cut.png", d / "good.png"], "gt": [d / "good.png", d / "cut.png"],
            "mask": [d / "good.png", d / "good.png", "--mask", d / "cut.png"]}[where]
    r = run_relight("metrics", "image", *args, "-o", d / "m.json", timeout=120)
    assert r.returncode == 1, r.stderr
    lines = r.stderr.splitlines()
    assert len(lines) == 1, r.stderr
    assert lines[0].startswith("relight metrics: error: ") and "cut.png" in lines[0]
    assert not (d / "m.json").exists()


def _file_size_limit():          # a write cut short, as on a full disk (EFBIG, not a signal)
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (3000, 3000))


def test_png_preview_cut_short_fails_cleanly(pngs, tmp_path):
    import subprocess

    from conftest import relight_executable
    d = pngs
    r = subprocess.run([relight_executable(), "metrics", "image", str(d / "good.png"),
                        str(d / "good.png"), "--preview", str(d / "p.png"), "-o", "-"],
                       capture_output=True, text=True, timeout=120, preexec_fn=_file_size_limit)
    assert r.returncode == 1, r.stderr
    assert "libpng" not in r.stderr
    assert r.stderr.splitlines()[-1].startswith("relight metrics: error: ")
    assert "p.png" in r.stderr.splitlines()[-1]
    assert not (d / "p.png").exists()


def test_png_preview_to_dev_full(pngs):
    d = pngs
    r = run_relight("metrics", "image", d / "good.png", d / "good.png", "--preview", "/dev/full",
                    "-o", d / "m.json", timeout=120)
    assert r.returncode == 1
    assert "libpng" not in r.stderr
    assert r.stderr.splitlines()[-1].startswith("relight metrics: error: ")


def test_write_png_cut_short_in_process(tmp_path, capfd):
    """write_png reads its PNG back: a short write is an OutputError, never a bad file."""
    import os
    pid = os.fork()
    if pid == 0:                                    # the limit must not outlive the test
        code = 3
        try:
            _file_size_limit()
            write_png(str(tmp_path / "x.png"),
                      np.random.default_rng(1).uniform(0, 1, (64, 64, 3)))
            code = 0
        except OutputError:
            code = 1
        except BaseException:
            code = 2
        os._exit(code)
    _, status = os.waitpid(pid, 0)
    assert os.WEXITSTATUS(status) == 1
    assert not (tmp_path / "x.png").exists()
    assert "libpng" not in capfd.readouterr().err


@pytest.mark.parametrize("cut", [1, 4, 8, 12, 13])
def test_png_missing_its_last_bytes_is_refused(pngs, capfd, cut):
    """A PNG cut short in (or just before) its final IEND chunk decodes in libpng and
    Pillow as if whole (neither reads past the last row); the reader walks the chunks
    (formats.image.check_png): one DataError naming the file, no library output."""
    data = (pngs / "good.png").read_bytes()
    bad = pngs / f"short{cut}.png"
    bad.write_bytes(data[:-cut])
    with pytest.raises(DataError) as info:
        read_image(str(bad))
    text = str(info.value)
    assert "cut short" in text and bad.name in text and "\n" not in text
    out, err = capfd.readouterr()
    assert err == "" and out == ""


def test_png_crc_error_in_a_critical_chunk_is_refused(pngs):
    data = bytearray((pngs / "good.png").read_bytes())
    data[-1] ^= 0xFF                                  # the last byte of IEND's CRC
    bad = pngs / "crc.png"
    bad.write_bytes(bytes(data))
    with pytest.raises(DataError, match="CRC error in its IEND chunk") as info:
        read_image(str(bad))
    assert "crc.png" in str(info.value)


def test_png_whole_or_with_bytes_after_iend_reads(pngs):
    data = (pngs / "good.png").read_bytes()
    (pngs / "tail.png").write_bytes(data + b"\0" * 7)
    assert read_image(str(pngs / "good.png"))[0].shape == (48, 64, 3)
    assert read_image(str(pngs / "tail.png"))[0].shape == (48, 64, 3)


def test_png_env_map_cut_short_is_refused(pngs, capfd):
    """formats/envmap.py reads PNG (and other non-EXR) env maps through read_image: the
    same check and the same silenced libpng."""
    from relight_cli.formats.envmap import read_envmap
    assert read_envmap(str(pngs / "good.png")).radiance.shape == (48, 64, 3)
    data = (pngs / "good.png").read_bytes()
    for cut, name in ((1, "iend.png"), (len(data) // 2, "half.png")):
        (pngs / name).write_bytes(data[:len(data) - cut])
        with pytest.raises(DataError) as info:
            read_envmap(str(pngs / name))
        assert name in str(info.value) and "\n" not in str(info.value)
    out, err = capfd.readouterr()
    assert err == "" and out == ""
