"""Placing Gaussian objects in a scene: similarity transforms, robust bounds, a spec language.

A placement maps an object's own frame to the world by a similarity
x' = s·Q·x + t (uniform scale s > 0, proper rotation Q, translation t, metres).
Applied to 3D Gaussians (:func:`transform_gaussians`) it moves every part
exactly:

* means: μ' = s Q μ + t;
* covariances: Σ' = s² Q Σ Qᵀ, i.e. rotations R' = Q R (quaternion product)
  and scales s·S (so Σ' = R' S'² R'ᵀ exactly; a non-uniform scale would not
  keep the R S Sᵀ Rᵀ form per Gaussian and is not offered);
* view-dependent colour: c'(d) = c(Qᵀ d), i.e. each SH band l rotated by its
  (2l+1)² block (found exactly by least squares on 2(2l+1)+1 directions,
  because band l is closed under rotation); degree 0 is unchanged;
* stored normals: n' = Q n.

Spec language (``SOURCE[:KEY=VALUE;KEY=VALUE;FLAG]``, see :func:`split_spec`):

=================  ==============================================================
``crop=BOX``       BOX = X0,Y0,Z0,X1,Y1,Z1: keep only the Gaussians whose centres
                   lie in this axis-aligned box (bounds included), in the source's
                   own frame and units, before any transform (X0 < X1, Y0 < Y1,
                   Z0 < Z1)
``min-opacity=A``  drop the Gaussians whose opacity (activated, in [0, 1]) is < A
``max-scale=S``    drop the Gaussians whose largest std dev (activated scale, the
                   source's own units) is > S: a capture's needle floaters
``fit=S``          scale so the largest side of the robust box is S metres, and
                   move the robust box's centre to the origin (first, after pruning)
``centre``         move the robust box's centre to the origin (no scaling)
``scale=s``        multiply by s > 0 (after fit/centre)
``rotate-x=deg``   rotate about the world x axis through the origin (also
``rotate-y=deg``   -y, -z; several apply in the order written, after scale)
``rotate-z=deg``
``on-floor``       then lift/lower so the robust box's bottom is at y = 0
``translate=x,y,z`` finally add this offset (metres)
``frame=K``        for a hand .npz source: the pose (frame K) made into Gaussians
                   (not a transform; refused for other sources)
``path=FILE.json`` a clip's per-frame translation (a ``relight/path``, formats/
                   path_json.md), added after everything else: a static object
                   moves (``relight --frames``, ``dgsm-build --frames``)
=================  ==============================================================

The order is fixed, whatever the order of the keys: crop/min-opacity/max-scale
(:func:`prune`, on the source as read) → fit/centre → scale → rotations → on-floor →
translate, so ``fit`` and ``on-floor`` measure what is kept (a clip prunes every
frame and resolves the similarity on its first).  The robust box is the alpha(opacity)-
weighted 1st–99th percentile of the centres per axis (floaters of a trained
scene do not inflate it); it ignores the Gaussians' own extents, so a
surface "on the floor" may dip by about one std dev of its bottom Gaussians.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from relight_cli.formats.gaussians_ply import (Gaussians, matrix_to_quaternion,
                                               quaternion_to_matrix)
from relight_cli.sh import sh_basis

KEYS = ("fit", "centre", "scale", "rotate-x", "rotate-y", "rotate-z", "on-floor", "translate",
        "frame", "path", "crop", "min-opacity", "max-scale")
USAGE = ("SOURCE[:KEY=VALUE;...] with keys crop=X0,Y0,Z0,X1,Y1,Z1, min-opacity=A, "
         "max-scale=S (these three prune the source first), fit=SIZE, centre, scale=S, "
         "rotate-x|y|z=DEG, on-floor, translate=X,Y,Z, frame=K (a hand .npz's pose), "
         "path=FILE.json (a clip's per-frame translations) "
         "(e.g. donut.ply:fit=0.15;on-floor;translate=0.3,0,0)")


@dataclass
class Placement:
    """A parsed placement (see the module doc for the order of operations).

    Attributes:
        fit: target size (metres) of the robust box's largest side, or None.
        centre: move the robust box's centre to the origin first (implied by fit).
        scale: uniform scale factor (> 0).
        rotations: [(axis "x"|"y"|"z", degrees)] in the order applied.
        on_floor: rest the robust box's bottom on y = 0.
        translate: [3] final offset, metres.
        frame: for a hand .npz source, the frame whose pose becomes Gaussians (None: 0).
        path: a relight/path JSON of per-frame translations (None: none), read by
            relight_cli.gaussians.sequence (a clip); not part of the similarity.
        crop: (x0, y0, z0, x1, y1, z1) box of centres kept, the source's frame, or None.
        min_opacity: drop opacities below this (None: keep all).
        max_scale: drop Gaussians whose largest std dev exceeds this (None: keep all).
    """

    fit: float | None = None
    centre: bool = False
    scale: float = 1.0
    rotations: list = field(default_factory=list)
    on_floor: bool = False
    translate: tuple = (0.0, 0.0, 0.0)
    frame: int | None = None
    path: str | None = None
    crop: tuple | None = None
    min_opacity: float | None = None
    max_scale: float | None = None

    def prunes(self) -> bool:
        """Whether crop, min-opacity or max-scale drops Gaussians (:func:`prune`)."""
        return self.crop is not None or self.min_opacity is not None \
            or self.max_scale is not None

    def is_identity(self) -> bool:
        """Whether the similarity is the identity (pruning aside: see :meth:`prunes`)."""
        return (self.fit is None and not self.centre and self.scale == 1.0
                and not self.rotations and not self.on_floor and tuple(self.translate) == (0, 0, 0))


@dataclass
class Similarity:
    """x' = scale · rotation · x + translation (rotation [3, 3] proper, scale > 0, translation [3])."""

    scale: float
    rotation: np.ndarray
    translation: np.ndarray

    def apply(self, points: np.ndarray) -> np.ndarray:
        """[N, 3] points → [N, 3] transformed points."""
        return self.scale * np.asarray(points, np.float64) @ self.rotation.T + self.translation

    def then(self, other: "Similarity") -> "Similarity":
        """The composition ``other ∘ self`` (self first)."""
        return Similarity(other.scale * self.scale, other.rotation @ self.rotation,
                          other.scale * other.rotation @ self.translation + other.translation)


def identity() -> Similarity:
    return Similarity(1.0, np.eye(3), np.zeros(3))


def axis_rotation(axis: str, degrees: float) -> np.ndarray:
    """[3, 3] right-handed rotation by ``degrees`` about world axis "x", "y" or "z"."""
    a = math.radians(degrees)
    c, s = math.cos(a), math.sin(a)
    if axis == "x":
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]], np.float64)
    if axis == "y":
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]], np.float64)
    if axis == "z":
        return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], np.float64)
    raise ValueError(f"axis must be x, y or z, got {axis!r}")


# ------------------------------------------------------------------ transforms


def sh_rotation_blocks(rotation: np.ndarray, degree: int) -> list[np.ndarray]:
    """Per band l, the [(2l+1), (2l+1)] matrix X_l with sh'_l = X_l sh_l for c'(d) = c(Qᵀ d).

    Band l of the real SH basis is closed under rotation, so Y_l(Qᵀ d) = D_l Y_l(d)
    holds for every d; D_l is recovered exactly (to round-off) by least squares
    on 2(2l+1)+1 generic directions, and X_l = D_lᵀ.
    """
    Q = np.asarray(rotation, np.float64)
    blocks = [np.ones((1, 1))]
    if degree == 0:
        return blocks
    rng = np.random.default_rng(12345)            # fixed generic directions (no seed semantics)
    dirs = rng.normal(size=(2 * (2 * degree + 1) + 1, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    A_all = sh_basis(dirs, degree)                 # [N, K]
    B_all = sh_basis(dirs @ Q, degree)             # rows: Y(Qᵀ d_n)  (d @ Q = (Qᵀ d)ᵀ)
    for l in range(1, degree + 1):
        sl = slice(l * l, (l + 1) * (l + 1))
        X, *_ = np.linalg.lstsq(A_all[:, sl], B_all[:, sl], rcond=None)   # A X = B, X = D_lᵀ
        blocks.append(X)
    return blocks


def rotate_sh(sh: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """[N, K, 3] SH coefficients of c(d) → those of c(Qᵀ d) (the object rotated by Q)."""
    sh = np.asarray(sh, np.float64)
    degree = int(round(math.sqrt(sh.shape[1]))) - 1
    out = sh.copy()
    for l, X in enumerate(sh_rotation_blocks(rotation, degree)):
        if l == 0:
            continue
        sl = slice(l * l, (l + 1) * (l + 1))
        out[:, sl] = np.einsum("jk,nkc->njc", X, sh[:, sl])
    return out


def transform_gaussians(g: Gaussians, similarity: Similarity) -> Gaussians:
    """A copy of ``g`` moved by the similarity (see the module doc); ``g`` is not changed.

    Raises:
        ValueError: scale not finite and > 0, or rotation not a proper rotation.
    """
    s = float(similarity.scale)
    Q = np.asarray(similarity.rotation, np.float64).reshape(3, 3)
    t = np.asarray(similarity.translation, np.float64).reshape(3)
    if not (math.isfinite(s) and s > 0):
        raise ValueError(f"scale must be a finite number > 0, got {similarity.scale}")
    if not (np.isfinite(Q).all() and np.isfinite(t).all()):
        raise ValueError("rotation/translation must be finite")
    if not (np.allclose(Q @ Q.T, np.eye(3), atol=1e-9) and np.linalg.det(Q) > 0):
        raise ValueError("rotation must be a proper rotation matrix (orthonormal, det +1)")
    rotations = matrix_to_quaternion(Q[None] @ quaternion_to_matrix(g.rotations))
    sh = g.sh if g.sh_degree == 0 else rotate_sh(g.sh, Q)
    normals = None if g.normals is None else g.normals @ Q.T
    return Gaussians(s * g.means @ Q.T + t, s * g.scales, rotations, g.opacities.copy(),
                     sh.copy(), g.sh_degree, normals,
                     source_colour_space=g.source_colour_space)


def weighted_percentile(values: np.ndarray, weights: np.ndarray, q: float) -> float:
    """The q-th (0..100) percentile of ``values`` [N] under non-negative ``weights`` [N]
    (inverse of the weighted CDF, midpoint rule; equal weights give numpy's 'hazen')."""
    order = np.argsort(values, kind="stable")
    v, w = np.asarray(values, np.float64)[order], np.asarray(weights, np.float64)[order]
    total = w.sum()
    if not total > 0:
        raise ValueError("weights sum to zero")
    cdf = (np.cumsum(w) - 0.5 * w) / total
    return float(np.interp(q / 100.0, cdf, v))


def robust_bounds(g: Gaussians, low: float = 1.0, high: float = 99.0) -> tuple[np.ndarray, np.ndarray]:
    """([3], [3]) opacity-weighted ``low``–``high`` percentile box of the centres, metres.

    Weighting by opacity makes faint floaters of a trained scene count little.
    """
    if len(g) == 0:
        raise ValueError("no Gaussians")
    w = g.opacities
    if not w.sum() > 0:
        w = np.ones(len(g))
    lo = np.array([weighted_percentile(g.means[:, i], w, low) for i in range(3)])
    hi = np.array([weighted_percentile(g.means[:, i], w, high) for i in range(3)])
    return lo, hi


def prune_mask(g: Gaussians, placement: Placement) -> np.ndarray:
    """[N] bool: the Gaussians that ``placement``'s crop box, min-opacity and max-scale
    keep (centres inside the box, bounds included; opacity ≥ A; largest scale ≤ S)."""
    keep = np.ones(len(g), bool)
    if placement.crop is not None:
        box = np.asarray(placement.crop, np.float64)
        keep &= np.all((g.means >= box[:3]) & (g.means <= box[3:]), axis=1)
    if placement.min_opacity is not None:
        keep &= g.opacities >= placement.min_opacity
    if placement.max_scale is not None:
        keep &= g.scales.max(axis=1) <= placement.max_scale
    return keep


def prune(g: Gaussians, placement: Placement) -> Gaussians:
    """``g`` less what crop/min-opacity/max-scale drop (``g`` itself when none is given).

    Raises:
        ValueError: nothing is left (the message counts what each key dropped).
    """
    if not placement.prunes():
        return g
    keep = prune_mask(g, placement)
    if keep.all():
        return g
    if not keep.any():
        dropped = []
        if placement.crop is not None:
            box = np.asarray(placement.crop, np.float64)
            outside = ~np.all((g.means >= box[:3]) & (g.means <= box[3:]), axis=1)
            dropped.append(f"{int(outside.sum()):,} outside the crop box")
        if placement.min_opacity is not None:
            dropped.append(f"{int((g.opacities < placement.min_opacity).sum()):,} below "
                           f"min-opacity {placement.min_opacity:g}")
        if placement.max_scale is not None:
            dropped.append(f"{int((g.scales.max(axis=1) > placement.max_scale).sum()):,} "
                           f"above max-scale {placement.max_scale:g}")
        raise ValueError(f"no Gaussians left after pruning (of {len(g):,}: "
                         + ", ".join(dropped) + ")")
    return g.subset(keep)


def resolve(placement: Placement, g: Gaussians) -> Similarity:
    """The similarity that ``placement`` means for these Gaussians (fit and on-floor read
    them, after :func:`prune`)."""
    g = prune(g, placement)
    sim = identity()
    if placement.fit is not None or placement.centre:
        lo, hi = robust_bounds(g)
        s = 1.0
        if placement.fit is not None:
            side = float((hi - lo).max())
            if not side > 0:
                raise ValueError("the object's robust box has zero size; cannot fit it")
            s = placement.fit / side
        sim = Similarity(s, np.eye(3), -s * (lo + hi) / 2)
    if placement.scale != 1.0:
        sim = sim.then(Similarity(placement.scale, np.eye(3), np.zeros(3)))
    for axis, degrees in placement.rotations:
        sim = sim.then(Similarity(1.0, axis_rotation(axis, degrees), np.zeros(3)))
    if placement.on_floor:
        moved = Gaussians(sim.apply(g.means), g.scales, g.rotations, g.opacities,
                          g.sh[:, :1], 0)
        lo, _ = robust_bounds(moved)
        sim = sim.then(Similarity(1.0, np.eye(3), np.array([0.0, -lo[1], 0.0])))
    t = np.asarray(placement.translate, np.float64)
    if np.any(t != 0):
        sim = sim.then(Similarity(1.0, np.eye(3), t))
    return sim


def place(g: Gaussians, placement: Placement) -> Gaussians:
    """:func:`prune`, then :func:`transform_gaussians` by :func:`resolve` (nothing to do
    returns ``g`` unchanged)."""
    g = prune(g, placement)
    if placement.is_identity():
        return g
    return transform_gaussians(g, resolve(placement, g))


# ------------------------------------------------------------------ spec language


def split_spec(spec: str) -> tuple[str, str | None]:
    """``"SOURCE:KEYS"`` → (SOURCE, KEYS); ``"SOURCE"`` → (SOURCE, None).

    The placement is the text after the LAST colon when it contains ``=`` or
    names a flag (``on-floor``, ``centre``), so ``builtin:hand`` is a source
    and ``builtin:hand:scale=2`` a placed one.
    """
    if ":" in spec:
        source, tail = spec.rsplit(":", 1)
        words = [w.strip() for w in tail.split(";")]
        if "=" in tail or any(w in ("on-floor", "centre") for w in words):
            return source, tail
    return spec, None


def parse_placement(text: str | None) -> Placement:
    """Parse ``KEY=VALUE;KEY;...`` (see the module doc).  Raises ValueError with the reason."""
    p = Placement(rotations=[])
    if text is None:
        return p
    seen = set()
    for item in text.split(";"):
        item = item.strip()
        if not item:
            continue
        key, _, value = item.partition("=")
        key = key.strip().lower()
        if key not in KEYS:
            raise ValueError(f"unknown placement key {key!r}")
        if key in seen and not key.startswith("rotate-"):
            raise ValueError(f"placement key {key!r} given twice")
        seen.add(key)
        if key in ("on-floor", "centre"):
            if value:
                raise ValueError(f"{key} takes no value")
            if key == "on-floor":
                p.on_floor = True
            else:
                p.centre = True
            continue
        if not value:
            raise ValueError(f"{key} needs a value ({key}=...)")
        if key == "translate":
            try:
                vec = tuple(float(v) for v in value.split(","))
            except ValueError:
                raise ValueError(f"translate must be X,Y,Z numbers, got {value!r}") from None
            if len(vec) != 3 or not all(math.isfinite(v) for v in vec):
                raise ValueError(f"translate must be 3 finite numbers X,Y,Z, got {value!r}")
            p.translate = vec
            continue
        if key == "path":
            if not value.lower().endswith(".json"):
                raise ValueError(f"path names a relight/path .json file, got {value!r}")
            p.path = value
            continue
        if key == "crop":
            try:
                box = tuple(float(v) for v in value.split(","))
            except ValueError:
                raise ValueError(f"crop must be X0,Y0,Z0,X1,Y1,Z1 numbers, got {value!r}") \
                    from None
            if len(box) != 6 or not all(math.isfinite(v) for v in box):
                raise ValueError(f"crop must be 6 finite numbers X0,Y0,Z0,X1,Y1,Z1, got "
                                 f"{value!r}")
            for axis, lo, hi in zip("XYZ", box[:3], box[3:]):
                if not lo < hi:
                    raise ValueError(f"crop box is empty: {axis}0 = {lo:g} must be < "
                                     f"{axis}1 = {hi:g}")
            p.crop = box
            continue
        if key == "frame":
            if not value.isdigit():
                raise ValueError(f"frame must be an integer ≥ 0, got {value!r}")
            p.frame = int(value)
            continue
        try:
            number = float(value)
        except ValueError:
            raise ValueError(f"{key} must be a number, got {value!r}") from None
        if not math.isfinite(number):
            raise ValueError(f"{key} must be finite, got {value!r}")
        if key in ("fit", "scale", "max-scale") and not number > 0:
            raise ValueError(f"{key} must be > 0, got {value!r}")
        if key == "min-opacity" and not 0 <= number <= 1:
            raise ValueError(f"min-opacity must be in [0, 1] (an activated opacity), got "
                             f"{value!r}")
        if key == "min-opacity":
            p.min_opacity = number
        elif key == "max-scale":
            p.max_scale = number
        elif key == "fit":
            p.fit = number
        elif key == "scale":
            p.scale = number
        else:
            p.rotations.append((key[-1], number))
    return p


def parse_spec(spec: str) -> tuple[str, Placement]:
    """``SOURCE[:PLACEMENT]`` → (SOURCE, :class:`Placement`).  Raises ValueError."""
    source, tail = split_spec(spec)
    if not source:
        raise ValueError("empty source before the placement")
    return source, parse_placement(tail)
