"""Images: 8-bit PNG writing and reading of any image OpenImageIO reads.

PNG is only ever a preview (tone mapping and captions: relight_cli.preview); data
stays in EXR (see exr.py).  Reading of arbitrary image formats (masks, ground
truth) goes through OpenImageIO.

Errors are ours only: a damaged or cut-short PNG is one DataError/OutputError naming the
file; libpng's own ``libpng error: …`` lines are kept off stderr (:func:`_library_quiet`),
and a written PNG is read back before it is committed (a short write that libpng did not
report never leaves a cut-short preview).
"""

from __future__ import annotations

import contextlib
import os
import sys
import threading

import numpy as np

from relight_cli.errors import DataError


_QUIET_LOCK = threading.Lock()
_QUIET = {"depth": 0, "saved": None}


@contextlib.contextmanager
def _library_quiet():
    """Silence the C libraries' own stderr (libpng prints ``libpng error: …`` before it
    reports the failure to OpenImageIO) for the length of one call: every error is
    reported by us, as one line, from OpenImageIO's ``geterror()``.  Threads share one
    redirection (the first in makes it, the last out restores fd 2)."""
    with _QUIET_LOCK:
        if _QUIET["depth"] == 0:
            try:
                sys.stderr.flush()
            except (OSError, ValueError, AttributeError):
                pass
            try:
                saved = os.dup(2)
            except OSError:              # no fd 2 at all: nothing to protect
                saved = None
            if saved is not None:
                try:
                    null = os.open(os.devnull, os.O_WRONLY)
                    try:
                        os.dup2(null, 2)
                    finally:
                        os.close(null)
                except OSError:
                    os.close(saved)
                    saved = None
            _QUIET["saved"] = saved
        _QUIET["depth"] += 1
    try:
        yield
    finally:
        with _QUIET_LOCK:
            _QUIET["depth"] -= 1
            if _QUIET["depth"] == 0 and _QUIET["saved"] is not None:
                os.dup2(_QUIET["saved"], 2)
                os.close(_QUIET["saved"])
                _QUIET["saved"] = None


def _first_line(message: str, path: str, default: str) -> str:
    return (message.splitlines() or [default])[0].replace(path, "").strip(' :"') or default


def write_png(path: str, display: np.ndarray) -> None:
    """Write display-referred [H, W, C] values in [0, 1] as 8-bit PNG, atomically."""
    import OpenImageIO as oiio

    from relight_cli.errors import OutputError
    from relight_cli.formats.exr import write_failure
    from relight_cli.fileio import atomic_path

    pixels = np.ascontiguousarray(np.clip(np.rint(np.asarray(display) * 255.0), 0, 255).astype(np.uint8))
    if pixels.ndim == 2:
        pixels = pixels[..., None]
    pixels = np.ascontiguousarray(pixels)
    h, w, c = pixels.shape
    with atomic_path(path, suffix=".png", verify=read_image) as tmp, _library_quiet():
        out = oiio.ImageOutput.create(tmp)
        if out is None:
            raise OutputError("cannot create PNG writer: " + oiio.geterror(), path)
        spec = oiio.ImageSpec(w, h, c, oiio.UINT8)
        spec.attribute("Software", "relight")
        if not out.open(tmp, spec) or not out.write_image(pixels):
            msg = out.geterror()
            out.close()
            raise write_failure(RuntimeError(msg or "PNG writer failed"), tmp, path)
        if not out.close():
            raise write_failure(RuntimeError(out.geterror() or "PNG writer failed"), tmp, path)
        # libpng can drop the error of a short write (a full disk, a file size limit):
        # read the PNG back, so that a cut-short file is never committed
        try:
            _read(oiio, tmp)
        except DataError:
            raise OutputError("cannot write: the PNG was cut short (is the disk full?)",
                              path) from None


def read_image(path: str) -> tuple[np.ndarray, list[str]]:
    """Any OpenImageIO-readable image, level 0, as ([H, W, C] float32, channel names).

    EXR values come back as stored (linear); 8-bit formats are scaled to [0, 1]
    without any colour transform.
    """
    import OpenImageIO as oiio

    if not os.path.exists(path):
        raise DataError("no such file", path)
    if os.path.isdir(path):
        raise DataError("is a directory, expected an image", path)
    with _library_quiet():
        pixels, names = _read(oiio, path)
    pixels = np.asarray(pixels, np.float32)
    if pixels.ndim == 2:
        pixels = pixels[..., None]
    return pixels, names


def _read(oiio, path: str):
    """OpenImageIO's read of ``path`` (level 0, float), DataError on failure."""
    inp = oiio.ImageInput.open(path)
    if inp is None:
        raise DataError("unreadable image: " + _first_line(oiio.geterror(), path, "unknown format"),
                        path)
    try:
        spec = inp.spec()
        names = list(spec.channelnames)
        pixels = inp.read_image(0, 0, 0, spec.nchannels, "float")
        if pixels is None:
            raise DataError("damaged image: " + _first_line(inp.geterror(), path, "read failed"),
                            path)
    finally:
        inp.close()
    return pixels, names
