"""SH light probes in JSON (spec: ``formats/sh_probe_json.md``)."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field

import numpy as np

from relight_cli.errors import DataError

from ._common import MAX_POSITION, bounded, check_format_version

FORMAT = "relight/sh-probe"
VERSION = 1


@dataclass
class ShProbe:
    """Radiance L(ω) = Σ_k coefficients[k] · Y_k(ω) (real orthonormal SH, 3DGS convention).

    Attributes:
        coefficients: [(degree+1)², 3] float64, linear RGB radiance per SH basis function.
        degree: SH degree.
        ridge: λ of the ridge least-squares fit (paper Eq. 7).
        source: what was fitted (env-map path / builtin name, or scene PLY).
        position: [3] probe position (metres, world) for scene probes, else None.
        extra: other fields (degree search, resolution, …), kept on read.
        provenance: the provenance record.
    """

    coefficients: np.ndarray
    degree: int
    ridge: float = 0.0
    source: str = ""
    position: np.ndarray | None = None
    extra: dict = field(default_factory=dict)
    provenance: dict | None = None


def probe_to_json(probe: ShProbe) -> dict:
    out = {"format": FORMAT, "version": VERSION, "degree": int(probe.degree),
           "basis": "real orthonormal SH, Condon-Shortley phase (3DGS), index l*l+l+m",
           "coefficients": [[float(v) for v in row] for row in np.asarray(probe.coefficients)],
           "ridge": float(probe.ridge), "source": probe.source}
    if probe.position is not None:
        out["position"] = [float(v) for v in probe.position]
    out.update(probe.extra)
    if probe.provenance is not None:
        out["provenance"] = probe.provenance
    return out


def write_probe(path: str, probe: ShProbe) -> None:
    """Write a probe atomically ('-' for stdout); floats round-trip exactly (repr)."""
    from relight_cli.fileio import write_text_atomic
    if not np.isfinite(probe.coefficients).all():
        raise DataError("probe coefficients hold NaN/Inf", path)
    bounded(probe.coefficients, "probe coefficients", path)
    write_text_atomic(path, json.dumps(probe_to_json(probe), indent=2, allow_nan=False) + "\n")


def probe_from_json(obj, path: str = "") -> ShProbe:
    if not isinstance(obj, dict):
        raise DataError("expected a JSON object", path)
    check_format_version(obj.get("format"), obj.get("version"), FORMAT, VERSION, path)
    degree = obj.get("degree")
    if not isinstance(degree, int) or isinstance(degree, bool) or not 0 <= degree <= 20:
        raise DataError(f"'degree' must be an integer in 0..20, got {degree!r}", path)
    from ._common import number_array
    coeffs = number_array(obj.get("coefficients"), "'coefficients'", path)
    k = (degree + 1) ** 2
    if coeffs.shape != (k, 3):
        raise DataError(f"'coefficients' must be {k} rows of 3 for degree {degree}, got shape "
                        f"{coeffs.shape}", path)
    bounded(coeffs, "'coefficients'", path)      # NaN/Inf, and |c| ≤ MAX_VALUE
    ridge = obj.get("ridge", 0.0)
    if not isinstance(ridge, (int, float)) or isinstance(ridge, bool) or not math.isfinite(ridge) \
            or ridge < 0:
        raise DataError(f"'ridge' must be a finite number ≥ 0, got {ridge!r}", path)
    position = obj.get("position")
    if position is not None:
        position = number_array(position, "'position'", path)
        if position.shape != (3,):
            raise DataError("'position' must be [x, y, z]", path)
        bounded(position, "'position'", path, MAX_POSITION)
    known = {"format", "version", "degree", "basis", "coefficients", "ridge", "source", "position",
             "provenance"}
    extra = {k_: v for k_, v in obj.items() if k_ not in known}
    return ShProbe(coeffs, degree, float(ridge), str(obj.get("source", "")), position, extra,
                   obj.get("provenance"))


def read_probe(path: str) -> ShProbe:
    """Read and validate a probe JSON file (DataError naming the file otherwise)."""
    path = str(path)
    from ._common import read_json
    obj = read_json(path)
    return probe_from_json(obj, path)
