"""3D Gaussians in the INRIA 3DGS PLY layout (spec: ``formats/gaussians_ply.md``).

One ``vertex`` element, one row per Gaussian, float32 properties::

    x y z                      centre, metres, world
    [nx ny nz]                 optional normal (INRIA writes zeros: read as absent)
    f_dc_0 f_dc_1 f_dc_2       SH DC coefficient per RGB channel
    f_rest_0 … f_rest_{3(K−1)−1}  higher SH bands, channel-major (all R, then G, then B)
    opacity                    logit of the opacity
    scale_0 scale_1 scale_2    log of the per-axis standard deviation, metres
    rot_0 rot_1 rot_2 rot_3    quaternion w, x, y, z (need not be unit)

In memory (:class:`Gaussians`) everything is float64 and *activated*: linear
scales, unit w-first quaternions, opacities in (0, 1), SH as [N, K, 3].
Files this toolkit writes carry ``relight/gaussians`` version and provenance
JSON in PLY ``obj_info`` lines; files from other tools have none and load the same.

Colour space: a 3DGS PLY's colours are display-referred sRGB (what the training
photographs were; KHR_gaussian_splatting's default) unless the file is one this
toolkit wrote (a ``relight.colour-space linear`` or ``relight.format`` line):
:func:`read_gaussians` decodes sRGB files to linear once, on read
(:func:`srgb_to_linear_sh`), so in memory colours are always linear.
"""

from __future__ import annotations

import json
import math
import os
import re
from dataclasses import dataclass, field

import numpy as np

from relight_cli.errors import DataError

FORMAT = "relight/gaussians"
VERSION = 1
SH_C0 = 0.28209479177387814  # Y_0^0 = 1 / (2√π)

_REQUIRED = ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
             "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")
_FORMAT_TAG = "relight.format"
_PROVENANCE_TAG = "relight.provenance"
_COLOUR_TAG = "relight.colour-space"
#: The colour spaces a PLY's colours may be stored in ("auto": detect, see read_gaussians).
COLOUR_SPACES = ("srgb", "linear")


@dataclass
class Gaussians:
    """A set of N anisotropic 3D Gaussians with view-dependent SH colour.

    Attributes:
        means: [N, 3] float64 centres, metres, world.
        scales: [N, 3] float64 per-axis standard deviations (linear, metres, ≥ 0).
        rotations: [N, 4] float64 unit quaternions (w, x, y, z), local→world.
        opacities: [N] float64 peak opacities in (0, 1).
        sh: [N, K, 3] float64 SH coefficients, K = (sh_degree+1)², index l²+l+m;
            ``sh[:, 0]`` is the DC term (``f_dc``).  Colour in direction d
            (from the camera towards the Gaussian, as 3DGS) is
            ``0.5 + Σ_k sh[:, k] Y_k(d)``.
        sh_degree: the SH degree (0–4 in practice).
        normals: [N, 3] float64 or None.
        provenance: the provenance record of a file this toolkit wrote (or None).
        source_colour_space: the colour space the colours were stored in where they
            came from ("srgb" or "linear"); in memory they are always linear (an sRGB
            file is decoded on read).
    """

    means: np.ndarray
    scales: np.ndarray
    rotations: np.ndarray
    opacities: np.ndarray
    sh: np.ndarray
    sh_degree: int
    normals: np.ndarray | None = None
    provenance: dict | None = field(default=None, compare=False)
    source_colour_space: str = field(default="linear", compare=False)

    def __post_init__(self):
        self.means = np.asarray(self.means, np.float64).reshape(-1, 3)
        n = len(self.means)
        self.scales = np.asarray(self.scales, np.float64).reshape(n, 3)
        self.rotations = np.asarray(self.rotations, np.float64).reshape(n, 4)
        self.opacities = np.asarray(self.opacities, np.float64).reshape(n)
        self.sh_degree = int(self.sh_degree)
        k = (self.sh_degree + 1) ** 2
        self.sh = np.asarray(self.sh, np.float64).reshape(n, k, 3)
        if self.normals is not None:
            self.normals = np.asarray(self.normals, np.float64).reshape(n, 3)

    def __len__(self) -> int:
        return len(self.means)

    @property
    def count(self) -> int:
        return len(self.means)

    def colors(self, clamp: bool = True) -> np.ndarray:
        """[N, 3] degree-0 RGB, 0.5 + C0·f_dc (clamped at 0 like 3DGS unless ``clamp=False``)."""
        rgb = 0.5 + SH_C0 * self.sh[:, 0, :]
        return np.maximum(rgb, 0.0) if clamp else rgb

    def rotation_matrices(self) -> np.ndarray:
        """[N, 3, 3] local→world rotation matrices (columns are the Gaussian's axes)."""
        return quaternion_to_matrix(self.rotations)

    def covariances(self) -> np.ndarray:
        """[N, 3, 3] world covariances Σ = R diag(s²) Rᵀ, metres²."""
        R = self.rotation_matrices()
        return np.einsum("nij,nj,nkj->nik", R, self.scales ** 2, R)

    def subset(self, index) -> "Gaussians":
        """The Gaussians selected by a boolean mask or an index array."""
        return Gaussians(self.means[index], self.scales[index], self.rotations[index],
                         self.opacities[index], self.sh[index], self.sh_degree,
                         None if self.normals is None else self.normals[index],
                         source_colour_space=self.source_colour_space)

    def with_sh_degree(self, degree: int) -> "Gaussians":
        """A copy with SH truncated or zero-padded to ``degree``."""
        k_new = (degree + 1) ** 2
        sh = np.zeros((len(self), k_new, 3))
        k = min(k_new, self.sh.shape[1])
        sh[:, :k] = self.sh[:, :k]
        return Gaussians(self.means, self.scales, self.rotations, self.opacities, sh, degree,
                         self.normals, source_colour_space=self.source_colour_space)


def concatenate(parts: list[Gaussians]) -> Gaussians:
    """Join Gaussian sets (SH padded with zeros to the highest degree; normals kept if all have them)."""
    if not parts:
        raise ValueError("nothing to concatenate")
    degree = max(p.sh_degree for p in parts)
    parts = [p.with_sh_degree(degree) for p in parts]
    normals = (np.concatenate([p.normals for p in parts])
               if all(p.normals is not None for p in parts) else None)
    return Gaussians(np.concatenate([p.means for p in parts]),
                     np.concatenate([p.scales for p in parts]),
                     np.concatenate([p.rotations for p in parts]),
                     np.concatenate([p.opacities for p in parts]),
                     np.concatenate([p.sh for p in parts]), degree, normals,
                     source_colour_space=("srgb" if all(p.source_colour_space == "srgb"
                                                        for p in parts) else "linear"))


def quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    """[N, 4] w-first quaternions (normalized here) → [N, 3, 3] rotation matrices."""
    q = np.asarray(q, np.float64).reshape(-1, 4)
    q = q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-300)
    w, x, y, z = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], axis=1)


def matrix_to_quaternion(R: np.ndarray) -> np.ndarray:
    """[N, 3, 3] rotation matrices → [N, 4] unit w-first quaternions (w ≥ 0)."""
    from scipy.spatial.transform import Rotation
    xyzw = Rotation.from_matrix(np.asarray(R, np.float64).reshape(-1, 3, 3)).as_quat()
    q = np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1)
    return q * np.where(q[:, :1] < 0, -1.0, 1.0)


def rgb_to_sh_dc(rgb: np.ndarray) -> np.ndarray:
    """[N, 3] RGB → the DC coefficient that :meth:`Gaussians.colors` maps back to it."""
    return (np.asarray(rgb, np.float64) - 0.5) / SH_C0


def srgb_eotf(v: np.ndarray) -> np.ndarray:
    """The sRGB EOTF (IEC 61966-2-1, piecewise): encoded value → linear, per element.

    Negative values are clamped at 0 first (no NaN from a negative base); values above 1
    follow the same power segment (linear HDR above 1)."""
    v = np.maximum(np.asarray(v, np.float64), 0.0)
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def _srgb_eotf_slope(v: np.ndarray) -> np.ndarray:
    """d EOTF / dv at v (clamped at 0 like :func:`srgb_eotf`)."""
    v = np.maximum(np.asarray(v, np.float64), 0.0)
    return np.where(v <= 0.04045, 1 / 12.92, (2.4 / 1.055) * ((v + 0.055) / 1.055) ** 1.4)


def _srgb_eotf_curvature(v: np.ndarray) -> np.ndarray:
    """d² EOTF / dv² at v (0 on the linear segment)."""
    v = np.maximum(np.asarray(v, np.float64), 0.0)
    return np.where(v <= 0.04045, 0.0,
                    (2.4 * 1.4 / 1.055 ** 2) * ((v + 0.055) / 1.055) ** 0.4)


def srgb_to_linear_sh(sh: np.ndarray) -> np.ndarray:
    """[N, K, 3] SH of sRGB-encoded colour (``0.5 + Σ sh_k Y_k(d)``) → SH of linear colour.

    The decode is not linear, so SH bands cannot be mapped exactly; this expands the
    EOTF around each Gaussian's mean (DC) colour c̄ = max(0.5 + C0·sh_0, 0):
    bands l ≥ 1 are scaled by the EOTF's slope at c̄ (first order), and the DC term
    is EOTF(c̄) plus the second-order mean correction ½·EOTF''(c̄)·Σ_{k≥1} sh_k²/(4π)
    (the mean over the sphere of the squared view-dependent part).  Degree 0 is exact.
    A negative DC colour is clamped at 0 before decoding (3DGS clamps it when rendering).
    See formats/gaussians_ply.md for the measured error against a brute-force fit.
    """
    sh = np.asarray(sh, np.float64)
    mean = np.maximum(0.5 + SH_C0 * sh[:, 0, :], 0.0)                       # [N, 3]
    out = np.empty_like(sh)
    out[:, 1:] = sh[:, 1:] * _srgb_eotf_slope(mean)[:, None, :]
    var = (sh[:, 1:] ** 2).sum(axis=1) / (4 * math.pi)
    dc = srgb_eotf(mean) + 0.5 * _srgb_eotf_curvature(mean) * var
    out[:, 0] = (dc - 0.5) / SH_C0
    return out


def sigmoid(x: np.ndarray) -> np.ndarray:
    """Overflow-free logistic function."""
    x = np.asarray(x, np.float64)
    e = np.exp(-np.abs(x))
    return np.where(x >= 0, 1 / (1 + e), e / (1 + e))


def logit(p: np.ndarray, eps: float = 1e-7) -> np.ndarray:
    """log(p / (1−p)) with p clipped to [eps, 1−eps] (opacity exactly 0 or 1 has no logit)."""
    p = np.clip(np.asarray(p, np.float64), eps, 1 - eps)
    return np.log(p) - np.log1p(-p)


# ------------------------------------------------------------------ reading


def read_gaussians(path: str, colour_space: str = "auto") -> Gaussians:
    """Read and validate a 3DGS PLY file; its colours come back linear.

    ``colour_space`` is the space the file's colours are stored in: "srgb" (decoded to
    linear here by :func:`srgb_to_linear_sh`), "linear" (kept as stored) or "auto":
    linear for a file this toolkit wrote (a ``relight.colour-space`` line says which;
    an older file with only a ``relight.format`` line is linear), sRGB otherwise (3DGS
    training output).  The result's ``source_colour_space`` records the space used.

    Raises:
        DataError: missing file, not a PLY, no ``vertex`` element, missing or
            extra-inconsistent fields (named), non-finite values (field and first
            row named), zero quaternions, or an unknown relight format version.
    """
    import plyfile

    path = str(path)
    if not os.path.exists(path):
        raise DataError("no such file", path)
    if os.path.isdir(path):
        raise DataError("is a directory, expected a Gaussians PLY file", path)
    try:
        # copy-on-write memory map: plyfile's one fast path (mmap=False reads every property
        # of every vertex in a Python loop: 6.3 s for a 90k-Gaussian file against 0.05 s).
        # The columns are copied out below (np.asarray(..., float64)), so no view outlives
        # the file; the map is closed on return
        ply = plyfile.PlyData.read(path, mmap="c")
    except Exception as exc:  # plyfile raises PlyParseError, ValueError, struct errors …
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise DataError(f"not a readable PLY file: {msg}", path) from None
    if colour_space not in ("auto",) + COLOUR_SPACES:
        raise ValueError(f"colour_space must be auto, srgb or linear, got {colour_space!r}")
    provenance, stored = _check_header(ply, path)
    space = stored if colour_space == "auto" else colour_space
    if "vertex" not in [e.name for e in ply.elements]:
        raise DataError("PLY has no 'vertex' element (a 3DGS file stores one Gaussian per vertex)",
                        path)
    vertex = ply["vertex"]
    names = list(vertex.data.dtype.names or ())
    missing = [n for n in _REQUIRED if n not in names]
    if missing:
        raise DataError(f"missing 3DGS field(s) {', '.join(missing)}", path)
    n = len(vertex.data)
    if n == 0:
        raise DataError("the file holds no Gaussians", path)

    def column(name):
        a = np.asarray(vertex.data[name], np.float64)
        if not np.isfinite(a).all():
            row = int(np.flatnonzero(~np.isfinite(a))[0])
            count = int((~np.isfinite(a)).sum())
            raise DataError(f"field {name} has {count} non-finite value(s) (first at Gaussian {row})",
                            path)
        return a

    rest_names = sorted((m for m in names if re.fullmatch(r"f_rest_\d+", m)),
                        key=lambda m: int(m[7:]))
    n_rest = len(rest_names)
    degree = _degree_from_rest(n_rest)
    if degree is None or [int(m[7:]) for m in rest_names] != list(range(n_rest)):
        raise DataError(f"f_rest_* fields must be f_rest_0 … f_rest_{{3((d+1)²−1)−1}} for an SH "
                        f"degree d; found {n_rest} ({', '.join(rest_names[:3])}…)", path)
    k = (degree + 1) ** 2
    sh = np.empty((n, k, 3))
    for c in range(3):
        sh[:, 0, c] = column(f"f_dc_{c}")
        # INRIA stores features_rest [N, K−1, 3] transposed to [N, 3, K−1] then flattened.
        for j in range(k - 1):
            sh[:, 1 + j, c] = column(f"f_rest_{c * (k - 1) + j}")

    means = np.stack([column(a) for a in "xyz"], axis=1)
    log_scales = np.stack([column(f"scale_{i}") for i in range(3)], axis=1)
    with np.errstate(over="ignore"):
        scales = np.exp(log_scales)
    if not np.isfinite(scales).all():
        row = int(np.flatnonzero(~np.isfinite(scales).all(axis=1))[0])
        raise DataError(f"field scale_* overflows exp() (log scale {log_scales[row].max():.4g} "
                        f"at Gaussian {row})", path)
    quats = np.stack([column(f"rot_{i}") for i in range(4)], axis=1)
    norms = np.linalg.norm(quats, axis=1)
    zero = ~(norms > 1e-30)
    if zero.any():
        raise DataError(f"fields rot_0..rot_3: {int(zero.sum())} zero quaternion(s) "
                        f"(first at Gaussian {int(np.flatnonzero(zero)[0])})", path)
    quats = quats / norms[:, None]
    opacities = sigmoid(column("opacity"))
    normals = None
    if all(a in names for a in ("nx", "ny", "nz")):
        nrm = np.stack([column(a) for a in ("nx", "ny", "nz")], axis=1)
        if np.any(nrm != 0):  # INRIA writes all-zero placeholders: those are "no normals"
            normals = nrm
    if space == "srgb":
        sh = srgb_to_linear_sh(sh)
    return Gaussians(means, scales, quats, opacities, sh, degree, normals, provenance,
                     source_colour_space=space)


def _degree_from_rest(n_rest: int) -> int | None:
    if n_rest % 3:
        return None
    k = n_rest // 3 + 1
    d = int(round(math.sqrt(k))) - 1
    return d if (d + 1) ** 2 == k else None


def _check_header(ply, path: str) -> dict | None:
    """Read relight's format/provenance/colour-space lines (absent for foreign files);
    reject newer versions.  → (provenance or None, the stored colour space: the
    colour-space line's, else linear for a file with a format line, else srgb)."""
    provenance = None
    ours = False
    colour = None
    for line in list(ply.obj_info) + list(ply.comments):
        # the tag is the line's first word, whatever follows it (nothing, a tab, a space):
        # a tag line without its value is damaged, never skipped as a foreign line
        parts = line.split()
        tag = parts[0] if parts else ""
        if tag == _FORMAT_TAG:
            if (len(parts) != 3 or parts[1] != FORMAT
                    or not parts[2].isascii() or not parts[2].isdigit() or int(parts[2]) < 1):
                raise DataError(f"damaged '{_FORMAT_TAG}' header line: {line!r} (expected "
                                f"'{_FORMAT_TAG} {FORMAT} VERSION')"[:240], path)
            ours = True
            if int(parts[2]) > VERSION:
                raise DataError(f"{FORMAT} version {parts[2]} is newer than this relight "
                                f"understands (≤ {VERSION})", path, hint="upgrade relight")
        elif tag == _PROVENANCE_TAG:
            from ._common import parse_json
            text = line.strip()[len(_PROVENANCE_TAG):].strip()
            try:
                if not text:
                    raise DataError("empty", path)
                provenance = parse_json(text, path, non_finite="allow")
            except DataError:
                raise DataError("damaged relight.provenance header line", path) from None
            if not isinstance(provenance, dict):
                raise DataError("damaged relight.provenance header line (not a JSON object)",
                                path)
        elif tag == _COLOUR_TAG:
            if len(parts) != 2 or parts[1] not in COLOUR_SPACES:
                raise DataError(f"damaged '{_COLOUR_TAG}' header line: {line!r} (expected "
                                f"'{_COLOUR_TAG} srgb|linear')"[:240], path)
            colour = parts[1]
    return provenance, colour or ("linear" if ours else "srgb")


# ------------------------------------------------------------------ writing


def validate(g: Gaussians, what: str = "Gaussians") -> None:
    """Raise DataError if arrays hold non-finite values, negative scales or zero quaternions."""
    for name in ("means", "scales", "rotations", "opacities", "sh"):
        a = getattr(g, name)
        if not np.isfinite(a).all():
            raise DataError(f"{name} holds non-finite values", what)
    if (g.scales < 0).any():
        raise DataError("scales must be non-negative", what)
    if (np.linalg.norm(g.rotations, axis=1) <= 1e-30).any():
        raise DataError("rotations hold a zero quaternion", what)
    if ((g.opacities < 0) | (g.opacities > 1)).any():
        raise DataError("opacities must lie in [0, 1]", what)


@np.errstate(over="ignore", invalid="ignore")   # float32 overflow is checked below
def write_gaussians(path: str, g: Gaussians, provenance: dict | None = None) -> None:
    """Write Gaussians as a binary little-endian INRIA 3DGS PLY, atomically.

    Stored as float32: log scales (a zero scale is stored as log 1e-30 m),
    logit opacities (clipped to [1e-7, 1−1e-7]), unit quaternions, SH in the
    INRIA channel-major ``f_rest`` order.  ``provenance`` (from
    :func:`relight_cli.provenance.provenance`) goes in an ``obj_info`` line, and a
    ``relight.colour-space linear`` line says the colours are linear (they always are
    in memory).
    """
    import plyfile

    from relight_cli.fileio import atomic_path

    validate(g, str(path))
    n, k = len(g), g.sh.shape[1]
    props = ["x", "y", "z"]
    if g.normals is not None:
        props += ["nx", "ny", "nz"]
    props += ["f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(3 * (k - 1))]
    props += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    data = np.empty(n, dtype=[(p, "<f4") for p in props])
    for i, a in enumerate("xyz"):
        data[a] = g.means[:, i]
    if g.normals is not None:
        for i, a in enumerate(("nx", "ny", "nz")):
            data[a] = g.normals[:, i]
    for c in range(3):
        data[f"f_dc_{c}"] = g.sh[:, 0, c]
        for j in range(k - 1):
            data[f"f_rest_{c * (k - 1) + j}"] = g.sh[:, 1 + j, c]
    data["opacity"] = logit(g.opacities)
    log_scales = np.log(np.maximum(g.scales, 1e-30))
    quats = g.rotations / np.linalg.norm(g.rotations, axis=1, keepdims=True)
    for i in range(3):
        data[f"scale_{i}"] = log_scales[:, i]
    for i in range(4):
        data[f"rot_{i}"] = quats[:, i]
    bad = [p for p in props if not np.isfinite(data[p]).all()]
    if bad:   # the last line: finite float64 values that overflow float32
        raise DataError(f"property {bad[0]} would hold NaN/Inf in float32 (inputs too large); "
                        f"nothing written", str(path))
    obj_info = [f"{_FORMAT_TAG} {FORMAT} {VERSION}"]
    if provenance is not None:
        obj_info.append(f"{_PROVENANCE_TAG} " + json.dumps(provenance, sort_keys=True,
                                                             separators=(",", ":")))
    obj_info.append(f"{_COLOUR_TAG} linear")
    element = plyfile.PlyElement.describe(data, "vertex")
    ply = plyfile.PlyData([element], text=False, byte_order="<", obj_info=obj_info)
    with atomic_path(path, suffix=".ply") as tmp:
        ply.write(tmp)
