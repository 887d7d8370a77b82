"""OpenEXR reading and writing with named channels and provenance attributes.

Channels use OpenEXR's layer naming (``diffuse.R``); RGB images use ``R G B``.
Header attributes ``relight.format`` (str), ``relight.version`` (int) and
``relight.provenance`` (JSON str) are written on every file this toolkit makes.
Renders also carry OpenEXR's standard ``worldToCamera`` and ``worldToNDC``
(M44f, see ``formats/camera.py:openexr_matrices``).
Reading uses the OpenEXR Python bindings (level 0 of mip-mapped / tiled files);
anything the library rejects becomes a one-line :class:`DataError`.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import warnings
from dataclasses import dataclass, field

import numpy as np

from relight_cli.errors import DataError

FORMAT_KEY = "relight.format"
VERSION_KEY = "relight.version"
PROVENANCE_KEY = "relight.provenance"

# OpenEXR's own header attributes; everything else is user metadata.
_STANDARD = {"channels", "compression", "dataWindow", "displayWindow", "lineOrder",
             "pixelAspectRatio", "screenWindowCenter", "screenWindowWidth", "tiles",
             "type", "preview", "chunkCount", "version", "name"}


@dataclass
class ExrImage:
    """An EXR file in memory.

    Attributes:
        channels: name -> [H, W] float32 pixels (half is widened on read).
        attributes: non-standard header attributes (str/int/float/list/array).
        envmap: "latlong", "cube" or None (the ``envmap`` header attribute).
        path: where it came from (for error messages).
    """

    channels: dict[str, np.ndarray]
    attributes: dict = field(default_factory=dict)
    envmap: str | None = None
    path: str = ""

    @property
    def height(self) -> int:
        return next(iter(self.channels.values())).shape[0]

    @property
    def width(self) -> int:
        return next(iter(self.channels.values())).shape[1]

    def layer(self, prefix: str, names=("R", "G", "B")) -> np.ndarray:
        """Stack ``prefix.R``, ``prefix.G`` ... (or bare ``R`` for prefix '') as [H, W, C]."""
        keys = [f"{prefix}.{n}" if prefix else n for n in names]
        missing = [k for k in keys if k not in self.channels]
        if missing:
            raise DataError(f"missing channel(s) {', '.join(missing)}; file has "
                            f"{', '.join(sorted(self.channels)) or 'none'}", self.path)
        return np.stack([self.channels[k] for k in keys], axis=-1)

    def provenance(self) -> dict | None:
        text = self.attributes.get(PROVENANCE_KEY)
        if not text:
            return None
        from ._common import parse_json
        if not isinstance(text, str):
            raise DataError("damaged relight.provenance header attribute", self.path)
        try:
            return parse_json(text, self.path, non_finite="allow")
        except DataError:
            raise DataError("damaged relight.provenance header attribute", self.path) from None


def _plain(value):
    """Convert an OpenEXR header value to a plain Python value."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (str, int, float, bool, list, tuple, dict)) or value is None:
        return value
    return str(value)


@contextlib.contextmanager
def _capture_library_output():
    """Silence what the OpenEXR library prints on stdout and stderr.

    The bindings report damage as a Python exception too, and the user gets
    that as one line; the library's own messages (some on stdout, which may be
    carrying JSON) would bury it.  Both the C-level file descriptors and
    Python's sys.stdout/sys.stderr are redirected.
    """
    import sys
    import tempfile
    saved = []
    try:
        for stream, fd in ((sys.stdout, 1), (sys.stderr, 2)):
            try:
                stream.flush()
            except (AttributeError, OSError, ValueError):
                pass
            saved.append((fd, os.dup(fd)))
    except OSError:
        for _, dup in saved:
            os.close(dup)
        saved = []
    with tempfile.TemporaryFile() as sink:
        for fd, _ in saved:
            os.dup2(sink.fileno(), fd)
        try:
            with contextlib.redirect_stdout(io.StringIO()), \
                    contextlib.redirect_stderr(io.StringIO()), warnings.catch_warnings():
                warnings.simplefilter("ignore")
                yield
        finally:
            for fd, dup in saved:
                os.dup2(dup, fd)
                os.close(dup)


def read_exr(path: str) -> ExrImage:
    """Read every channel of part 0, level 0, as float32.  Raises DataError."""
    import OpenEXR

    path = str(path)
    if not os.path.exists(path):
        raise DataError("no such file", path)
    if os.path.isdir(path):
        raise DataError("is a directory, expected an EXR file", path)
    if not os.path.isfile(path):      # a FIFO or device would block or never end
        raise DataError("not a regular file, expected an EXR file", path)
    with open(path, "rb") as f:
        magic = f.read(4)
    if magic != b"\x76\x2f\x31\x01":
        raise DataError("not an OpenEXR file (bad magic number)", path)
    try:
        with _capture_library_output():
            exr = OpenEXR.File(path, separate_channels=True)
            header = exr.header()
            raw = exr.channels()
            del exr  # the bindings may print warnings on destruction
        channels = {}
        for name, ch in raw.items():
            pixels = np.asarray(ch.pixels)
            if pixels.ndim != 2:
                raise DataError(f"channel {name!r} is not a flat 2-D image", path)
            channels[name] = pixels.astype(np.float32, copy=False)
    except DataError:
        raise
    except MemoryError:
        raise DataError("damaged EXR file (implausible size)", path) from None
    except Exception as exc:  # the bindings raise RuntimeError/ValueError/... on damage
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        msg = " ".join(msg.replace(path, "").replace("''", "").split()).strip(" :'")
        raise DataError(f"damaged or unsupported EXR file: {msg[:160]}", path) from None
    if not channels:
        raise DataError("EXR file has no channels", path)
    shapes = {c.shape for c in channels.values()}
    if len(shapes) != 1:
        raise DataError("channels have different sizes (subsampled channels are not supported)", path)
    env = header.get("envmap")
    envmap = None
    if env is not None:
        envmap = "cube" if "CUBE" in str(env).upper() or str(env) == "1" else "latlong"
    attributes = {k: _plain(v) for k, v in header.items() if k not in _STANDARD and k != "envmap"}
    return ExrImage(channels=channels, attributes=attributes, envmap=envmap, path=path)


def write_exr(path: str, channels: dict[str, np.ndarray], attributes: dict | None = None,
              half: bool = False, envmap: str | None = None,
              provenance: dict | None = None, camera=None) -> None:
    """Write named [H, W] channels atomically.

    Args:
        path: target file (written via a temporary file in the same folder).
        channels: name -> [H, W] array; all the same shape.
        attributes: extra header attributes; str/int/float, lists of floats,
            anything else is stored as a JSON string.
        half: store 16-bit half floats (float32 otherwise).
        envmap: "latlong" or "cube" sets OpenEXR's ``envmap`` attribute.
        provenance: record from :func:`relight_cli.provenance.provenance`; its
            format and version also go to ``relight.format``/``relight.version``.
        camera: the ``formats.camera.Camera`` that rendered the image: OpenEXR's
            standard ``worldToCamera`` and ``worldToNDC`` attributes (M44f).
    """
    import OpenEXR

    from relight_cli.fileio import atomic_path

    dtype = np.float16 if half else np.float32
    pixels = {}
    for name, array in channels.items():
        array = np.asarray(array)
        if array.ndim != 2:
            raise ValueError(f"channel {name} must be 2-D, got shape {array.shape}")
        if half:
            # Values beyond half's range would become Inf; clamp to the largest half.
            array = np.clip(array, -65504.0, 65504.0)
        with np.errstate(over="ignore", invalid="ignore"):
            pixels[name] = np.ascontiguousarray(array, dtype=dtype)
        if not half and not np.isfinite(pixels[name]).all() and np.isfinite(
                array[~np.isfinite(pixels[name])]).any():
            # the last line: finite values that overflow float32 (inputs too large) are
            # never written as Inf (NaN/Inf given as such are the caller's to check)
            raise DataError(f"channel {name} would hold NaN/Inf in float32 (inputs too "
                            f"large); nothing written", path)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    if envmap is not None:
        header["envmap"] = (OpenEXR.Envmap.ENVMAP_CUBE if envmap == "cube"
                            else OpenEXR.Envmap.ENVMAP_LATLONG)
    for key, value in (attributes or {}).items():
        header[key] = _header_value(value)
    if camera is not None:
        from .camera import openexr_matrices
        if (camera.height, camera.width) != next(iter(pixels.values())).shape:
            raise ValueError("the camera's image size differs from the channels'")
        header["worldToCamera"], header["worldToNDC"] = openexr_matrices(camera)
    if provenance is not None:
        header[FORMAT_KEY] = str(provenance["format"])
        header[VERSION_KEY] = int(provenance["version"])
        header[PROVENANCE_KEY] = json.dumps(provenance, sort_keys=True)
    with atomic_path(path, suffix=".exr", verify=read_exr) as tmp:
        try:
            OpenEXR.File(header, pixels).write(tmp)
        except Exception as exc:  # the bindings raise RuntimeError for I/O errors
            raise write_failure(exc, tmp, path) from None


def write_failure(exc: Exception, tmp: str, path: str):
    """A one-line OutputError for what a C++ writer raised (its temp name left out)."""
    from relight_cli.errors import OutputError
    text = (str(exc).splitlines() or [type(exc).__name__])[0]
    if "No space left on device" in text:
        return OutputError("cannot write: no space left on device", path)
    text = " ".join(text.replace(f'"{tmp}"', "").replace(tmp, "").split()).strip(" :.'")
    return OutputError(f"cannot write: {text[:160]}", path)


def _header_value(value):
    if isinstance(value, bool):
        return int(value)
    if isinstance(value, (str, int, float)):
        return value
    if isinstance(value, (list, tuple, np.ndarray)):
        arr = np.asarray(value)
        if arr.ndim == 1 and arr.dtype.kind in "fiu" and arr.size > 0:
            return [float(v) for v in arr]
    return json.dumps(value, sort_keys=True)


def check_format(image: ExrImage, format_name: str, max_version: int) -> int:
    """Require ``relight.format == format_name`` and a known major version; return it."""
    from ._common import check_format_version
    return check_format_version(image.attributes.get(FORMAT_KEY), image.attributes.get(VERSION_KEY),
                                format_name, max_version, image.path)
