"""Images: 8-bit PNG writing and reading of any image OpenImageIO reads.

PNG is only ever a preview (tone mapping and captions: relight_cli.preview); data
stays in EXR (see exr.py).  Reading of arbitrary image formats (masks, ground
truth) goes through OpenImageIO.

Errors are ours only: a damaged or cut-short PNG (even one missing only the bytes of its
final IEND chunk, which libpng never reads: :func:`check_png`) is one DataError/OutputError
naming the file; libpng's own ``libpng error: …`` lines are kept off stderr
(:func:`_library_quiet`), and a written PNG is read back before it is committed (a short
write that libpng did not report never leaves a cut-short preview).
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


#: Animation formats: extension → (Pillow format, its save options).  WebP: lossy at
#: quality 90 (small, plays in every browser); PNG: APNG, lossless.  Both encoders are
#: deterministic, so identical frames give identical bytes.
ANIMATIONS = {".webp": ("WEBP", {"quality": 90, "method": 4, "lossless": False}),
              ".png": ("PNG", {"optimize": False})}


def write_animation(path: str, frames: list, fps: float) -> None:
    """Write 8-bit display frames ([H, W, 3] uint8, all one size) as one animated WebP or
    PNG (by ``path``'s extension; a device or FIFO gets WebP), looping, each frame shown
    1000/fps ms (rounded to whole milliseconds, the formats' unit), atomically; the file
    is read back and its frame count checked before it is committed."""
    from PIL import Image

    from relight_cli.errors import OutputError
    from relight_cli.fileio import atomic_path

    if not frames:
        raise ValueError("an animation needs at least one frame")
    suffix = os.path.splitext(path)[1].lower()
    kind, options = ANIMATIONS.get(suffix, ANIMATIONS[".webp"])
    duration = max(1, int(round(1000.0 / fps)))

    def verify(tmp):
        with Image.open(tmp) as im:
            n = getattr(im, "n_frames", 1)
        if n != len(frames):
            raise DataError(f"the animation holds {n} frames, not {len(frames)}", path)

    images = [Image.fromarray(np.ascontiguousarray(f), "RGB") for f in frames]
    with atomic_path(path, suffix=suffix if suffix in ANIMATIONS else ".webp",
                     verify=verify) as tmp:
        try:
            images[0].save(tmp, format=kind, save_all=True, append_images=images[1:],
                           duration=duration, loop=0, **options)
        except OSError as exc:
            raise OutputError(f"cannot write the animation: {exc}", path) from None
        try:
            verify(tmp)
        except (DataError, OSError):
            raise OutputError("cannot write: the animation was cut short (is the disk full?)",
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


PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def check_png(path: str) -> None:
    """Refuse a PNG whose chunk structure is cut short or damaged (DataError naming the
    file); anything that is no PNG, or no regular file, is left to the decoder.

    libpng (under OpenImageIO) and Pillow both stop at the last image row and never read
    the final IEND chunk, so a PNG missing its last bytes decodes as if whole.  This walks
    the chunks up to IEND: each must fit in the file, and the critical ones (IHDR, PLTE,
    IDAT, IEND: libpng's own rule) must match their CRC."""
    import struct
    import zlib

    if not os.path.isfile(path):
        return
    with open(path, "rb") as f:
        if f.read(8) != PNG_SIGNATURE:
            return
        while True:
            head = f.read(8)
            if len(head) < 8:
                raise DataError("damaged PNG: cut short (no complete IEND chunk at the end)",
                                path)
            length, kind = struct.unpack(">I4s", head)
            if length > 0x7FFFFFFF or not kind.isalpha():
                raise DataError(f"damaged PNG: invalid chunk header {kind!r}"[:120], path)
            critical = not kind[0] & 0x20
            crc, left = zlib.crc32(kind), length
            if critical:
                while left:
                    block = f.read(min(left, 1 << 20))
                    if not block:
                        break
                    crc, left = zlib.crc32(block, crc), left - len(block)
            else:
                here = f.tell()
                left = max(0, here + length - f.seek(0, os.SEEK_END))
                f.seek(here + length - left)
            stored = f.read(4)
            if left or len(stored) < 4:
                raise DataError(f"damaged PNG: cut short in its {kind.decode()} chunk", path)
            if critical and struct.unpack(">I", stored)[0] != crc:
                raise DataError(f"damaged PNG: CRC error in its {kind.decode()} chunk", path)
            if kind == b"IEND":
                return


def _read(oiio, path: str):
    """OpenImageIO's read of ``path`` (level 0, float), DataError on failure (also for a
    PNG cut short that the decoder would take as whole: :func:`check_png`)."""
    check_png(path)
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
