"""Texel-aligned shading features in OpenEXR (spec: ``formats/features_exr.md``).

Format ``relight/features`` version 1: channels ``diffuse.R/G/B``,
``phong{α}.R/G/B`` per shininess, ``ggx.R/G/B`` (optional), ``visibility.Y``
and ``mask.Y``; with several hands each layer is prefixed by the hand name
(``left.diffuse.R``).  Also the per-vertex companion ``.npz``
(``relight/vertex-features`` version 1).
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field

import numpy as np

from relight_cli.errors import DataError

FORMAT = "relight/features"
VERSION = 1
VERTEX_FORMAT = "relight/vertex-features"
VERTEX_VERSION = 1

_RGB = ("R", "G", "B")
# Layer names other tools rely on; phong layers are phong<number>.
_FEATURE = re.compile(r"^(diffuse|ggx|phong[0-9]+(\.[0-9]+)?)$")


@dataclass
class FeatureMaps:
    """Texel-aligned features of one or more hands.

    Attributes:
        layers: full layer name (``diffuse``, ``phong16``, ``right.diffuse`` …) →
            [H, W, 3] float32 for RGB features, [H, W] float32 for ``visibility``
            and ``mask``.
        attributes: header attributes (``relight.*``), e.g. env, shininess, view.
        path: source file (for messages).
    """

    layers: dict
    attributes: dict = field(default_factory=dict)
    path: str = ""

    @property
    def hands(self) -> list[str]:
        """Hand prefixes present ('' for a single-hand file)."""
        return sorted(name[:-len("mask")].rstrip(".") for name in self.layers
                      if name == "mask" or name.endswith(".mask"))

    def get(self, name: str, hand: str = "") -> np.ndarray:
        """A layer of a hand: ``get("diffuse")`` or ``get("diffuse", "left")``."""
        key = f"{hand}.{name}" if hand else name
        if key not in self.layers:
            raise KeyError(key)
        return self.layers[key]


def write_features(path: str, layers: dict, attributes: dict | None = None,
                   provenance: dict | None = None) -> None:
    """Write feature layers (see :class:`FeatureMaps`) as float32 EXR, atomically.

    float32, never half: features under a 1e6 sun exceed half's 65504.
    """
    from relight_cli.formats.exr import write_exr

    channels = {}
    for name, array in layers.items():
        array = np.asarray(array, np.float32)
        if array.ndim == 3:
            if array.shape[2] != 3:
                raise ValueError(f"layer {name} must be [H, W, 3] or [H, W]")
            for c, letter in enumerate(_RGB):
                channels[f"{name}.{letter}"] = array[..., c]
        else:
            channels[f"{name}.Y"] = array
    write_exr(path, channels, attributes=attributes, provenance=provenance)


def read_features(path: str) -> FeatureMaps:
    """Read and validate a ``relight/features`` EXR.  Raises DataError naming the file."""
    from relight_cli.formats.exr import check_format, read_exr

    image = read_exr(path)
    check_format(image, FORMAT, VERSION)
    groups: dict[str, dict[str, np.ndarray]] = {}
    for name, pixels in image.channels.items():
        if "." not in name:
            raise DataError(f"unexpected channel {name!r} (features are layer.R/G/B or layer.Y)",
                            path)
        layer, letter = name.rsplit(".", 1)
        groups.setdefault(layer, {})[letter] = pixels
    layers = {}
    for layer, chans in groups.items():
        base = layer if (_FEATURE.match(layer) or layer in ("visibility", "mask")) \
            else layer.split(".", 1)[-1]                       # strip a hand prefix
        if base in ("visibility", "mask"):
            if set(chans) != {"Y"}:
                raise DataError(f"layer {layer!r} must have exactly one channel Y", path)
            layers[layer] = chans["Y"]
        else:
            if not _FEATURE.match(base):
                raise DataError(f"unknown feature layer {layer!r}", path)
            if set(chans) != set(_RGB):
                raise DataError(f"layer {layer!r} must have channels R, G, B, has "
                                f"{', '.join(sorted(chans))}", path)
            layers[layer] = np.stack([chans[c] for c in _RGB], axis=-1)
        if not np.isfinite(layers[layer]).all():
            raise DataError(f"layer {layer!r} holds NaN or Inf", path)
    masks = [name for name in layers if name.rsplit(".", 1)[-1] == "mask"]
    if not masks:
        raise DataError("missing mask.Y channel", path)
    for mask in masks:
        prefix = mask[:-len("mask")]
        for required in ("diffuse", "visibility"):
            if prefix + required not in layers:
                raise DataError(f"missing {prefix}{required} layer", path)
    return FeatureMaps(layers, image.attributes, str(path))


# ---------------------------------------------------------------- per-vertex npz


def write_vertex_features(path: str, arrays: dict, provenance: dict) -> None:
    """Write the per-vertex companion npz atomically (no pickled objects).

    Args:
        arrays: key → array (``vertices``, ``faces``, ``normals``, ``diffuse``,
            ``phong16`` …, ``visibility``; hand-prefixed ``left.diffuse`` with several hands).
        provenance: the provenance record (stored as JSON in ``provenance``).
    """
    from relight_cli.fileio import atomic_path

    from ._common import save_npz

    payload = {"format": np.array(VERTEX_FORMAT), "version": np.array(VERTEX_VERSION),
               "provenance": np.array(json.dumps(provenance, sort_keys=True))}
    for key, value in arrays.items():
        value = np.asarray(value)
        payload[key] = value.astype(np.float32) if value.dtype.kind == "f" and key not in (
            "vertices", "normals") else value
    with atomic_path(path, suffix=".npz") as tmp:
        with open(tmp, "wb") as f:
            save_npz(f, payload)


def read_vertex_features(path: str) -> dict:
    """Read a ``relight/vertex-features`` npz into a dict of arrays.  Raises DataError."""
    import os
    import zipfile

    if not os.path.exists(path):
        raise DataError("no such file", path)
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except (zipfile.BadZipFile, ValueError, OSError, EOFError) as exc:
        raise DataError(f"not a readable npz file: {str(exc).splitlines()[0][:120]}", path) from None
    if str(data.get("format", "")) != VERTEX_FORMAT:
        raise DataError(f"not a {VERTEX_FORMAT} file", path)
    version = int(data.get("version", 0))
    if not 1 <= version <= VERTEX_VERSION:
        raise DataError(f"{VERTEX_FORMAT} version {version} is not supported "
                        f"(≤ {VERTEX_VERSION})", path)
    return data
