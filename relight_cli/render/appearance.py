"""Hand appearance in UV space: albedo and GGX roughness maps.

The built-in hand gets a procedural skin (:func:`procedural_material`) from its
region labels (palm, dorsum, finger, nail, crease): per-region base colours,
low-frequency colour variation from smooth noise of the *rest-pose* position
(continuous across UV seams, identical in every pose), fine mottling, darkened
palmar creases, and glossier nails.  Any hand can instead use image maps
(:func:`material_from_maps`).

Maps follow the UV convention of formats/hand_npz.md: an H×W map's texel (row r,
col c) is centred at u = (c + ½)/W, v = 1 − (r + ½)/H.  Lookups are bilinear
with clamped borders, identical to ``torch.nn.functional.grid_sample(...,
align_corners=False, padding_mode="border")``, which the torch path uses.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Linear-RGB skin reflectances per region (palm, dorsum, finger, nail, crease):
# within the range of measured light-skin albedos (≈0.3–0.65 red, lower green/blue).
REGION_ALBEDO = np.array([
    [0.62, 0.40, 0.33],    # palm: pinker, lighter
    [0.52, 0.34, 0.26],    # dorsum: slightly darker, more tanned
    [0.57, 0.37, 0.30],    # finger
    [0.80, 0.62, 0.58],    # nail: whitish pink
    [0.40, 0.24, 0.19],    # crease: darker folds
])
REGION_ROUGHNESS = np.array([0.50, 0.42, 0.45, 0.18, 0.60])
SKIN_ALBEDO = REGION_ALBEDO[2]
SKIN_ROUGHNESS = 0.45
# Palmar creases of the right hand's palm (rest pose, metres, palm faces +Z): polylines
# in (x, y) for the distal transverse ("heart"), proximal transverse ("head") and
# thenar ("life") lines; darkened with a Gaussian of this width.
_PALM_LINES = (
    ((-0.038, 0.072), (-0.010, 0.068), (0.012, 0.076), (0.026, 0.082)),
    ((-0.036, 0.050), (-0.008, 0.055), (0.018, 0.062), (0.034, 0.066)),
    ((0.030, 0.062), (0.018, 0.040), (0.012, 0.018), (0.012, -0.010)),
)
_CREASE_SIGMA = 0.0009


@dataclass
class Material:
    """UV-space maps of one hand.

    Attributes:
        albedo: [Ha, Wa, 3] float32 linear diffuse reflectance in [0, 1].
        roughness: [Hr, Wr] float32 GGX perceptual roughness in (0, 1].
        f0: Fresnel reflectance at normal incidence (0.04: skin is a dielectric).
        specular: scale of the specular lobe (1 = physical; 0 = diffuse only).
    """

    albedo: np.ndarray
    roughness: np.ndarray
    f0: float = 0.04
    specular: float = 1.0

    def albedo_at(self, uv: np.ndarray) -> np.ndarray:
        """[N, 3] bilinear albedo at ``uv`` [N, 2]."""
        return bilinear(self.albedo, uv)

    def roughness_at(self, uv: np.ndarray) -> np.ndarray:
        """[N] bilinear roughness at ``uv`` [N, 2]."""
        return bilinear(self.roughness, uv)


def bilinear(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup of an [H, W] or [H, W, C] map at ``uv`` [N, 2] (clamped borders;
    the taps of :func:`relight_cli.uvraster.bilinear_taps`).

    Returns [N] or [N, C] float64.
    """
    from relight_cli.uvraster import bilinear_taps, gather_taps
    image = np.asarray(image)
    return gather_taps(image, bilinear_taps(uv, image.shape[0], image.shape[1]))


def constant_material(albedo=SKIN_ALBEDO, roughness: float = SKIN_ROUGHNESS, f0: float = 0.04,
                      specular: float = 1.0) -> Material:
    """A uniform material (1×1 maps)."""
    return Material(np.asarray(albedo, np.float32).reshape(1, 1, 3),
                    np.full((1, 1), roughness, np.float32), f0, specular)


def material_from_maps(albedo: np.ndarray | None, roughness: np.ndarray | float | None,
                       ) -> Material:
    """A material from image maps (either may be None → skin constant).

    Raises ValueError for maps with the wrong shape or out-of-range values.
    """
    if albedo is None:
        albedo = np.asarray(SKIN_ALBEDO, np.float32).reshape(1, 1, 3)
    albedo = np.asarray(albedo, np.float32)
    if albedo.ndim != 3 or albedo.shape[2] < 3:
        raise ValueError(f"albedo map must be [H, W, 3], got shape {albedo.shape}")
    albedo = albedo[..., :3]
    if not np.isfinite(albedo).all() or albedo.min() < 0 or albedo.max() > 1:
        raise ValueError("albedo map values must be finite and in [0, 1]")
    if roughness is None:
        roughness = SKIN_ROUGHNESS
    roughness = np.asarray(roughness, np.float32)
    if roughness.ndim == 0:
        roughness = roughness.reshape(1, 1)
    if roughness.ndim == 3:
        roughness = roughness[..., 0]
    if roughness.ndim != 2:
        raise ValueError(f"roughness map must be [H, W], got shape {roughness.shape}")
    if not np.isfinite(roughness).all() or roughness.min() <= 0 or roughness.max() > 1:
        raise ValueError("roughness values must be finite and in (0, 1]")
    return Material(albedo, roughness)


def _value_noise(points: np.ndarray, seed: int, wavelengths) -> np.ndarray:
    """[N] smooth noise in about [−1, 1]: sums of random plane waves in 3-D (metres)."""
    rng = np.random.default_rng(seed)
    total = np.zeros(len(points))
    norm = 0.0
    for wl in wavelengths:
        for _ in range(4):
            k = rng.normal(size=3)
            k *= 2 * np.pi / (wl * np.linalg.norm(k))
            total += np.sin(points @ k + rng.uniform(0, 2 * np.pi))
            norm += 1.0
    return total / np.sqrt(norm / 2)


def _polyline_distance(xy: np.ndarray, line) -> np.ndarray:
    """[N] distance (metres) from points [N, 2] to a polyline."""
    pts = np.asarray(line, np.float64)
    best = np.full(len(xy), np.inf)
    for a, b in zip(pts[:-1], pts[1:]):
        ab = b - a
        t = np.clip(((xy - a) @ ab) / (ab @ ab), 0, 1)
        best = np.minimum(best, np.linalg.norm(xy - (a + t[:, None] * ab), axis=1))
    return best


def procedural_material(mesh, label_names, resolution: int = 512, seed: int = 0,
                        mirrored: bool = False) -> Material:
    """Procedural skin maps for a hand model with region labels.

    Args:
        mesh: ``HandMesh`` (rest-pose vertices, faces, uv, faces_uv, labels).  Without
            labels the whole hand is "finger" skin.
        label_names: names of the label values (palm, dorsum, finger, nail, crease
            are recognized; others count as finger skin).
        resolution: N of the N×N maps.
        seed: noise seed.
        mirrored: the model is a left hand stored mirrored (palm lines mirror too).

    Returns:
        Material with [N, N, 3] albedo and [N, N] roughness (filled past the charts).
    """
    from relight_cli.uvraster import rasterize_uv

    raster = rasterize_uv(mesh.uv, mesh.faces_uv, resolution)
    known = ("palm", "dorsum", "finger", "nail", "crease")
    n_vert = len(mesh.vertices)
    onehot = np.zeros((n_vert, len(known)))
    if mesh.labels is None or not len(label_names):
        onehot[:, 2] = 1
    else:
        names = [str(n) for n in label_names]
        col = np.array([known.index(n) if n in known else 2 for n in names], np.int64)
        onehot[np.arange(n_vert), col[np.asarray(mesh.labels, np.int64)]] = 1
    regions = raster.interpolate(onehot, mesh.faces, fill=None)                # [N, N, 5]
    rest = raster.interpolate(np.asarray(mesh.vertices, np.float64), mesh.faces, fill=None)
    inside = raster.inside
    p = rest[inside]                                                           # [K, 3]
    w = regions[inside]                                                        # [K, 5]
    albedo = w @ REGION_ALBEDO                                                 # [K, 3]
    rough = w @ REGION_ROUGHNESS
    # Colour variation: blotches (≈2–4 cm) change redness and brightness; mottling (≈3 mm).
    low = _value_noise(p, seed, (0.04, 0.025))
    redness = _value_noise(p, seed + 1, (0.03,))
    fine = _value_noise(p, seed + 2, (0.003, 0.002))
    albedo = albedo * (1 + 0.07 * low[:, None] + 0.025 * fine[:, None])
    albedo[:, 0] *= 1 + 0.04 * redness
    albedo[:, 1:] *= (1 - 0.03 * redness)[:, None]
    rough = rough * (1 + 0.08 * fine)
    # Palmar creases, on the palm side only (z > 0 in the rest pose of the right hand).
    xy = p[:, :2] * ([-1.0, 1.0] if mirrored else [1.0, 1.0])
    crease = np.zeros(len(p))
    for line in _PALM_LINES:
        crease = np.maximum(crease, np.exp(-0.5 * (_polyline_distance(xy, line)
                                                  / _CREASE_SIGMA) ** 2))
    crease *= w[:, 0] * (p[:, 2] > 0)
    albedo *= (1 - 0.35 * crease)[:, None]
    rough = rough + 0.15 * crease
    albedo_map = np.zeros((resolution, resolution, 3))
    rough_map = np.zeros((resolution, resolution))
    albedo_map[inside] = np.clip(albedo, 0.02, 0.95)
    rough_map[inside] = np.clip(rough, 0.05, 1.0)
    # Texels outside the charts copy their nearest inside texel, so bilinear lookups
    # near chart edges stay on skin values.
    from scipy.ndimage import distance_transform_edt
    _, (iy, ix) = distance_transform_edt(~inside, return_indices=True)
    albedo_map, rough_map = albedo_map[iy, ix], rough_map[iy, ix]
    return Material(albedo_map.astype(np.float32), rough_map.astype(np.float32))


def hand_materials(hand, mesh: str = "fine", resolution: int = 512, seed: int = 0,
                   albedo=None, roughness=None) -> list:
    """One Material per hand of ``hand`` (HandData), in ``posed_meshes`` order.

    Image maps (``albedo`` [H, W, 3], ``roughness`` [H, W] or a number) win; without
    them a model with region labels gets :func:`procedural_material` and one without
    labels the plain skin constants.  The procedural skin is computed on each hand's own
    rest surface (the mirrored model for a mirrored instance), so it depends only on the
    hand's handedness and ``seed``: the left hand of a two-hand scene made from a right
    model has exactly the skin of a left-hand model's capture (one subject, captured hand
    by hand and with both hands), and a scene's two hands have different blotches.
    """
    model = hand.mesh(mesh)
    if albedo is not None or roughness is not None or model.labels is None:
        base = material_from_maps(albedo, roughness)
        return [base for _ in hand.hands]
    from relight_cli.hand.model import mirror_mesh
    from relight_cli.hand.scene import handedness

    from relight_cli.formats.hand_npz import HandMesh
    cache = {}
    out = []
    for inst in hand.hands:
        if inst.mirror not in cache:
            surface = model
            if inst.mirror:
                v, f, fuv = mirror_mesh(model.vertices, model.faces, model.faces_uv)
                surface = HandMesh(v, f, model.uv, fuv, model.weights, model.labels)
            cache[inst.mirror] = procedural_material(surface, hand.label_names, resolution, seed,
                                                     mirrored=handedness(hand, inst) == "left")
        out.append(cache[inst.mirror])
    return out
