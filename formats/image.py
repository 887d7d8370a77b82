"""Images: 8-bit PNG writing and reading of any image OpenImageIO reads.

PNG is only ever a preview (tone mapping and captions: relight_cli.preview); data
stays in EXR (see exr.py).  Reading of arbitrary image formats (masks, ground
truth) goes through OpenImageIO.
"""

from __future__ import annotations

import os

import numpy as np

from relight_cli.errors import DataError


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
    with atomic_path(path, suffix=".png", verify=read_image) as tmp:
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
    inp = oiio.ImageInput.open(path)
    if inp is None:
        first = (oiio.geterror().splitlines() or ["unknown format"])[0]
        raise DataError("unreadable image: " + first.replace(path, "").strip(' :"'), path)
    try:
        spec = inp.spec()
        names = list(spec.channelnames)
        pixels = inp.read_image(0, 0, 0, spec.nchannels, "float")
        if pixels is None:
            raise DataError("damaged image: " + (inp.geterror().splitlines() or ["read failed"])[0]
                            .replace(path, "").strip(' :"'), path)
    finally:
        inp.close()
    pixels = np.asarray(pixels, np.float32)
    if pixels.ndim == 2:
        pixels = pixels[..., None]
    return pixels, names
