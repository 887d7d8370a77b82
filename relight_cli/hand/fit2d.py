"""Fitting the hand template to a few calibrated photos: 2D keypoints and masks (torch).

URHand's personalisation (supp. 9) optimises, per frame, the global rotation, pose and
translation and, shared by all frames, the identity, against (1) the L1 distance
between projected joints and 2D detections, (2) rendered masks against segmentation
masks (weight 50) and (3) rendered depth against the phone's depth (weight 100).  We
have no depth sensor and no differentiable rasterizer, so:

* the identity is the template's per-bone length scales (:mod:`relight_cli.hand.fitting`),
  shared by every view; the pose is shared by the views of one *pose group* (a hand held
  still while the phone moves round it — the paper's scans keep the fingers neutral and
  the hand in place), since one view alone leaves the depth of every joint free;
* **initialisation**: each joint is triangulated per group from the views that see it
  (linear DLT, then iteratively reweighted with Geman–McClure weights on the pixel
  residuals, so one wild detection does not move it), and the 3D fitter
  (:func:`relight_cli.hand.fitting.fit`: multi-start, joint limits) fits pose,
  translation and bone scales to those points;
* **refinement** on the images themselves: robust reprojection of the joints
  (Geman–McClure ρ(r) = r²/(r² + σ²), σ annealed 12 → 6 → 3 px, confidence-weighted:
  the paper's L1 becomes a robust loss that stops pulling at outliers), plus a silhouette
  term standing in for the rendered-mask loss: every projected coarse-mesh vertex must
  fall inside its view's mask (the mask's distance transform sampled bilinearly), and
  every mask pixel must lie near a projected vertex (a 2D chamfer, nearest neighbours
  found outside the graph), plus the joint limits and the bone-scale prior of the 3D fit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Fit2DOptions:
    iterations: int = 200          # refinement iterations, and the initial 3D fit's
    w_mask: float = 0.5            # silhouette terms against the keypoint term
    w_limits: float = 10.0
    w_scale: float = 1e-3
    mask_points: int = 1500        # mask pixels sampled per view for the chamfer
    seed: int = 0


@dataclass
class Fit2DResult:
    """Attributes:
        poses: [G, J, 3] axis-angle per pose group; translations: [G, 3] metres.
        bone_scales: [J] (1 for the root); rest_joints: [J, 3] personalised rest joints.
        reprojection_px: [V] mean confidence-weighted joint reprojection error per view.
        outside_px: [V] mean distance (pixels) of projected coarse vertices outside
            the view's mask (0 when every vertex projects inside), or NaN without masks.
        triangulated: [G, J] bool, joints seen by ≥ 2 views of the group.
    """

    poses: np.ndarray
    translations: np.ndarray
    bone_scales: np.ndarray
    rest_joints: np.ndarray
    reprojection_px: np.ndarray
    outside_px: np.ndarray
    triangulated: np.ndarray


def projection(camera) -> np.ndarray:
    """[3, 4] P = K [R | t] of a relight/camera."""
    return np.asarray(camera.K, np.float64) @ np.hstack(
        [np.asarray(camera.R, np.float64), np.asarray(camera.t, np.float64)[:, None]])


def triangulate(P: np.ndarray, uv: np.ndarray, w: np.ndarray, iterations: int = 6,
                sigma_px: float = 4.0) -> np.ndarray | None:
    """A point X [3] seen at ``uv`` [M, 2] through projections ``P`` [M, 3, 4] with
    weights ``w`` [M] (the detector's confidences): weighted linear DLT, then IRLS with
    Geman–McClure weights on the pixel residuals.  None when fewer than two views with
    positive weight, or the views' rays are (near) parallel."""
    keep = w > 0
    if keep.sum() < 2:
        return None
    P, uv, w = P[keep], uv[keep], w[keep].astype(np.float64)
    robust = np.ones(len(w))
    X = None
    for _ in range(iterations):
        A = np.concatenate([uv[:, :1] * P[:, 2] - P[:, 0], uv[:, 1:] * P[:, 2] - P[:, 1]])
        # rows scaled by 1/‖P₂ᵀ‖ approximate pixel units; weights per view
        scale = np.sqrt(w * robust)
        A = A * np.concatenate([scale, scale])[:, None]
        _, s, vt = np.linalg.svd(A)
        h = vt[-1]
        if abs(h[3]) < 1e-12 or (len(s) > 1 and s[-2] < 1e-9 * s[0]):
            return None
        X = h[:3] / h[3]
        proj = P @ np.append(X, 1.0)
        if np.any(proj[:, 2] <= 0):
            return None
        r2 = np.sum((proj[:, :2] / proj[:, 2:] - uv) ** 2, 1)
        robust = (sigma_px**2 / (sigma_px**2 + r2)) ** 2
    return X


def fit_views(template, cameras: list, uv: np.ndarray, confidence: np.ndarray,
              groups: np.ndarray, masks: list | None = None,
              options: Fit2DOptions | None = None, progress=None) -> Fit2DResult:
    """Fit ``template`` (HandData, one hand; its rest pose is used) to 2D keypoints.

    Args:
        cameras: V relight/camera objects; uv: [V, J, 2] pixels; confidence: [V, J];
        groups: [V] pose group of each view (0 … G−1, each with ≥ 2 views);
        masks: V boolean [H, W] foreground masks (the camera's size), or None.
        progress: optional callable(stage, step, total).
    Raises:
        ValueError: a group with fewer than two views, or fewer than 3 joints triangulated.
    """
    import torch

    from .fitting import FitOptions, fit

    opt = options or Fit2DOptions()
    uv = np.asarray(uv, np.float64)
    confidence = np.asarray(confidence, np.float64)
    groups = np.asarray(groups, np.int64)
    G = int(groups.max()) + 1
    J = len(template.rest_joints)
    Ps = np.stack([projection(c) for c in cameras])
    kp3 = np.zeros((G, J, 3))
    seen = np.zeros((G, J), bool)
    for g in range(G):
        views = np.nonzero(groups == g)[0]
        if len(views) < 2:
            raise ValueError(f"pose {g} has {len(views)} view; each pose needs at least two "
                             f"views (one view leaves the hand's depth free)")
        for j in range(J):
            X = triangulate(Ps[views], uv[views, j], confidence[views, j])
            if X is not None:
                kp3[g, j], seen[g, j] = X, True
        if seen[g].sum() < 3:
            raise ValueError(f"pose {g}: fewer than 3 joints are seen by two views; nothing "
                             f"to fit")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        init = fit(template, kp3, seen.astype(np.float64),
                   options=FitOptions(iterations=opt.iterations, seed=opt.seed),
                   progress=progress)
        return _refine(template, init, cameras, uv, confidence, groups, masks, opt, seen,
                       progress)
    finally:
        torch.set_num_threads(threads)


def _refine(template, init, cameras, uv, confidence, groups, masks, opt, seen, progress):
    import torch
    from scipy.ndimage import distance_transform_edt
    from scipy.spatial import cKDTree

    from .fitting import _Adam, _scaled_joints_torch, displacement_basis, scaled_joints
    from .poses import joint_axes, joint_limits
    from .skinning import lbs_torch

    dtype = torch.float64
    rng = np.random.default_rng(opt.seed)
    parents = np.asarray(template.parents)
    rest = np.asarray(template.rest_joints, np.float64)
    J, V = len(rest), len(cameras)
    mesh = template.coarse
    t_rest = torch.tensor(rest, dtype=dtype)
    verts0 = torch.tensor(mesh.vertices, dtype=dtype)
    weights = torch.tensor(mesh.weights, dtype=dtype)
    basis = torch.tensor(displacement_basis(mesh.vertices, mesh.weights, rest, parents),
                         dtype=dtype)
    K = torch.tensor(np.stack([c.K for c in cameras]), dtype=dtype)
    R = torch.tensor(np.stack([c.R for c in cameras]), dtype=dtype)
    T = torch.tensor(np.stack([c.t for c in cameras]), dtype=dtype)
    target = torch.tensor(uv, dtype=dtype)
    conf = torch.tensor(confidence, dtype=dtype)
    g_of = torch.as_tensor(groups)
    axes = torch.tensor(joint_axes(rest, template.side, parents), dtype=dtype)
    lim = joint_limits()
    lo, hi = torch.tensor(lim[..., 0], dtype=dtype), torch.tensor(lim[..., 1], dtype=dtype)
    limited = torch.ones(J, 1, dtype=dtype)
    limited[0] = 0
    free = torch.tensor([[1.0] if (j == 0 or np.any(parents == j)) else [0.0] for j in range(J)],
                        dtype=dtype)
    outside_maps, mask_pixels = [], []
    if masks is not None:
        for m in masks:
            outside_maps.append(torch.tensor(distance_transform_edt(~m), dtype=dtype))
            ys, xs = np.nonzero(m)
            mask_pixels.append(np.stack([xs, ys], 1).astype(np.float64))

    poses = torch.tensor(init.poses, dtype=dtype, requires_grad=True)
    trans = torch.tensor(init.translations, dtype=dtype, requires_grad=True)
    log_scales = torch.tensor(np.log(init.bone_scales), dtype=dtype, requires_grad=True)

    def project(points, v):            # points [..., 3] world → [..., 2] pixels, depth
        cam = points @ R[v].T + T[v]
        z = cam[..., 2:].clamp_min(1e-6)
        xy = cam[..., :2] / z
        return xy @ K[v, :2, :2].T + K[v, :2, 2], cam[..., 2]

    def sample(dmap, pix):             # bilinear distance-to-mask at pixel positions
        h, w = dmap.shape
        x = pix[:, 0].clamp(0, w - 1)
        y = pix[:, 1].clamp(0, h - 1)
        x0, y0 = x.floor().clamp(max=w - 2), y.floor().clamp(max=h - 2)
        fx, fy = x - x0, y - y0
        x0, y0 = x0.long(), y0.long()
        d = (dmap[y0, x0] * (1 - fx) * (1 - fy) + dmap[y0, x0 + 1] * fx * (1 - fy)
             + dmap[y0 + 1, x0] * (1 - fx) * fy + dmap[y0 + 1, x0 + 1] * fx * fy)
        # outside the image: the distance to it plus the map's value at its edge
        return d + (pix[:, 0] - x).abs() + (pix[:, 1] - y).abs()

    def energy(sigma, report=False):
        scales = torch.exp(log_scales)
        joints_rest = _scaled_joints_torch(t_rest, parents, scales)
        p = poses * free
        verts = verts0 + basis @ (joints_rest - t_rest)
        posed_v, posed_j = lbs_torch(verts, weights, joints_rest, parents, p, trans)
        total = poses.new_zeros(())
        errors, outside = [], []
        for v in range(V):
            g = int(g_of[v])
            pix, _ = project(posed_j[g], v)
            r2 = ((pix - target[v]) ** 2).sum(-1)
            c = conf[v]
            total = total + (c * r2 / (r2 + sigma**2)).sum() / c.sum().clamp_min(1e-9) / V
            if report:
                errors.append(float((c * r2.sqrt()).sum() / c.sum().clamp_min(1e-9)))
            if masks is not None:
                vpix, _ = project(posed_v[g], v)
                d = sample(outside_maps[v], vpix)
                s_px = sigma
                term = (d**2 / (d**2 + s_px**2)).mean()
                pts = mask_pixels[v]
                if len(pts) > opt.mask_points:
                    pts = pts[rng.choice(len(pts), opt.mask_points, replace=False)]
                _, idx = cKDTree(vpix.detach().numpy()).query(pts)
                e2 = ((vpix[torch.as_tensor(idx)] - torch.tensor(pts, dtype=dtype)) ** 2).sum(-1)
                term = term + (e2 / (e2 + s_px**2)).mean()
                total = total + opt.w_mask * term / V
                if report:
                    outside.append(float(d.detach().mean()))
        angles = torch.einsum("jab,gjb->gja", axes, p)
        excess = torch.relu(lo - angles) + torch.relu(angles - hi)
        total = total + opt.w_limits * ((excess**2) * limited).sum((1, 2)).mean()
        total = total + opt.w_scale * (log_scales[1:] ** 2).sum()
        return total, errors, outside

    adam = _Adam([([poses], 0.01), ([trans], 0.001), ([log_scales], 0.005)], opt.iterations)
    for it in range(opt.iterations):
        frac = it / max(opt.iterations - 1, 1)
        sigma = 12.0 if frac < 0.3 else (6.0 if frac < 0.6 else 3.0)
        adam.zero_grad()
        e, _, _ = energy(sigma)
        e.backward()
        adam.step()
        if progress is not None:
            progress("refine on the images", it + 1, opt.iterations)
    with torch.no_grad():
        _, errors, outside = energy(3.0, report=True)
    scales = np.exp(log_scales.detach().numpy())
    scales[0] = 1.0
    return Fit2DResult((poses * free).detach().numpy(), trans.detach().numpy(), scales,
                       scaled_joints(rest, parents, scales), np.asarray(errors),
                       np.asarray(outside) if outside else np.full(V, np.nan), seen)
