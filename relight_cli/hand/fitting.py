"""Fitting a skinned hand template to 3D keypoints and/or scans (torch).

Unknowns: per frame the pose θ [N, J, 3] (leaf joints stay 0: nothing
observes them) and translation t [N, 3]; shared across frames the
personalization — per-bone length scales s_j (offset J_j − J_p(j) scaled by
s_j) and, optionally with scans, per-vertex offsets of the coarse mesh.

Energy (each term normalized per observation):

    E = E_keypoints      Geman–McClure ρ(r) = r²/(r² + σ²) of joint residuals,
                         weighted by confidence; σ anneals 30 → 10 → 5 mm so
                         outliers stop pulling once the fit is close
      + E_scan           point-to-plane (scan → nearest model vertex) and
                         chamfer (model → nearest scan point), both robust
      + w_limits·E_lim   squared excess of the joint-axis projection of θ_j over
                         the anatomical limits (poses.joint_limits)
      + w_smooth·E_t     squared differences of θ and t between consecutive frames
      + w_scale·Σ log²s  keeps unobserved bones at scale 1
      + w_lap·|L·o|²     uniform Laplacian of the vertex offsets o

Initialization: a robust (IRLS) Kabsch alignment of the palm joints gives
the wrist rotation and t (without keypoints: PCA axes + trimmed ICP of the
relaxed template onto the scan); local rotations start from swing-only IK
(each bone turned onto its keypoint direction), the relaxed, the open and
the fist pose.  A pose-only stage runs all starts; fingers are independent
given the palm, so each finger of each frame keeps the start whose energy on
that finger (keypoint terms, or scan terms of the vertices it dominates) is
lowest.  Then all unknowns are optimized jointly.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .model import N_JOINTS
from .poses import joint_axes, joint_limits, named_pose


@dataclass
class FitOptions:
    iterations: int = 300          # joint stage (the pose-only stage runs a third of this)
    fit_bone_scales: bool = True
    fit_offsets: bool = False      # per-vertex offsets (only meaningful with scans)
    w_limits: float = 10.0
    w_smooth: float = 0.0
    # rows that start a new sequence (e.g. a second hand's frames stacked after the first's):
    # no smoothness term links such a row to the one before it
    sequence_starts: tuple = ()
    w_scale: float = 1e-3
    w_laplacian: float = 10.0
    w_scan: float = 1.0
    scan_points: int = 1500        # scan points sampled per frame per iteration batch
    seed: int = 0


@dataclass
class FitResult:
    """Attributes:
        poses: [N, J, 3] axis-angle; translations: [N, 3] metres.
        bone_scales: [J] (1 for the root).
        offsets: [V, 3] coarse-vertex offsets in the rest pose (metres), or None.
        rest_joints: [J, 3] personalized rest joints.
        joint_error_mm: [N] mean distance fitted joint ↔ keypoint over observed joints (mm).
        joint_median_mm: [N] median of the same.
        scan_mm: [N] mean |point-to-plane| distance scan → fitted coarse mesh (mm), or None.
        energy: final energy per frame [N].
        joint_errors_mm: [N, J] distance fitted joint ↔ keypoint (mm), NaN where the
            keypoint is missing (confidence 0); None without keypoints.
    """

    poses: np.ndarray
    translations: np.ndarray
    bone_scales: np.ndarray
    offsets: np.ndarray | None
    rest_joints: np.ndarray
    joint_error_mm: np.ndarray
    joint_median_mm: np.ndarray
    scan_mm: np.ndarray | None
    energy: np.ndarray
    history: list = field(default_factory=list)
    joint_errors_mm: np.ndarray | None = None


# ----------------------------------------------------------------------------- personalization

def primary_children(parents) -> np.ndarray:
    """[J] the only child of each joint, −1 for leaves and joints with several children."""
    J = len(parents)
    count = np.bincount(np.asarray(parents[1:]), minlength=J)
    child = np.full(J, -1)
    for j in range(1, J):
        p = parents[j]
        if count[p] == 1:
            child[p] = j
    return child


def displacement_basis(vertices, weights, rest_joints, parents) -> np.ndarray:
    """[V, J] B such that rest-vertex displacement = B @ ΔJ when joints move by ΔJ [J, 3].

    A vertex bound to joint j follows j and slides along the bone towards the
    joint's child by its projected fraction α ∈ [0, 1]:
    d(v) = Σ_j w_j·((1 − α_j)·ΔJ_j + α_j·ΔJ_child(j)).
    """
    v = np.asarray(vertices, np.float64)
    rest = np.asarray(rest_joints, np.float64)
    child = primary_children(parents)
    B = np.zeros((len(v), len(rest)))
    for j in range(len(rest)):
        w = weights[:, j]
        if not np.any(w):
            continue
        c = child[j]
        if c < 0:
            B[:, j] += w
            continue
        bone = rest[c] - rest[j]
        alpha = np.clip((v - rest[j]) @ bone / (bone @ bone), 0.0, 1.0)
        B[:, j] += w * (1 - alpha)
        B[:, c] += w * alpha
    return B


def scaled_joints(rest_joints, parents, scales) -> np.ndarray:
    """[J, 3] rest joints with each offset J_j − J_p(j) scaled by scales[j] (numpy)."""
    rest = np.asarray(rest_joints, np.float64)
    out = rest.copy()
    for j in range(1, len(rest)):
        p = parents[j]
        out[j] = out[p] + scales[j] * (rest[j] - rest[p])
    return out


def personalize_mesh(vertices, weights, rest_joints, parents, scales, offsets=None):
    """Rest vertices [V, 3] of the personalized template (bone scales, then offsets)."""
    new_joints = scaled_joints(rest_joints, parents, scales)
    B = displacement_basis(vertices, weights, rest_joints, parents)
    out = np.asarray(vertices, np.float64) + B @ (new_joints - np.asarray(rest_joints))
    if offsets is not None:
        out = out + offsets
    return out


def _scaled_joints_torch(rest, parents, scales):
    import torch
    out = [rest[0]]
    for j in range(1, rest.shape[0]):
        p = int(parents[j])
        out.append(out[p] + scales[j] * (rest[j] - rest[p]))
    return torch.stack(out)


# ----------------------------------------------------------------------------- initialization

def _kabsch(src, dst, w):
    """Weighted rigid R, t with R·src + t ≈ dst ([K, 3] each, weights [K])."""
    w = w / max(w.sum(), 1e-12)
    cs, cd = w @ src, w @ dst
    H = ((src - cs) * w[:, None]).T @ (dst - cd)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    R = Vt.T @ np.diag([1, 1, d]) @ U.T
    return R, cd - R @ cs


def _robust_global(rest, target, conf, idx, sigma=0.01, iters=8):
    """IRLS Kabsch of rest joints ``idx`` onto targets (Geman–McClure weights)."""
    src, dst = rest[idx], target[idx]
    w0 = conf[idx].astype(np.float64)
    if (w0 > 0).sum() < 3:
        return np.eye(3), (w0 @ (dst - src)) / max(w0.sum(), 1e-12) if w0.sum() > 0 else np.zeros(3)
    w = w0.copy()
    for _ in range(iters):
        R, t = _kabsch(src, dst, w)
        r2 = np.sum((src @ R.T + t - dst) ** 2, 1)
        w = w0 * (sigma**2 / (sigma**2 + r2)) ** 2
    return R, t


def _rigid_scan_init(source, target, iterations=25):
    """Rigid R, t aligning template points ``source`` [V, 3] to scan points ``target`` [P, 3].

    Tries the four proper rotations that map the principal axes of one onto
    the other, refines each by trimmed point-to-point ICP (the 80% closest
    pairs, both directions), and keeps the one with the lowest symmetric
    mean distance.  Used when no keypoints fix the wrist.
    """
    from scipy.spatial import cKDTree

    src = np.asarray(source, np.float64)
    dst = np.asarray(target, np.float64)
    cs, cd = src.mean(0), dst.mean(0)
    _, _, vs = np.linalg.svd(src - cs, full_matrices=False)
    _, _, vd = np.linalg.svd(dst - cd, full_matrices=False)
    tree_dst, best = cKDTree(dst), None
    for signs in ([1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]):
        R = vd.T @ np.diag(signs) @ vs
        if np.linalg.det(R) < 0:
            R = vd.T @ np.diag(signs) @ np.diag([1, 1, -1]) @ vs
        t = cd - R @ cs
        for _ in range(iterations):
            moved = src @ R.T + t
            d1, i1 = tree_dst.query(moved)
            d2, i2 = cKDTree(moved).query(dst)
            a = np.concatenate([src, src[i2]])
            b = np.concatenate([dst[i1], dst])
            dist = np.concatenate([d1, d2])
            keep = dist <= np.quantile(dist, 0.8)
            R, t = _kabsch(a[keep], b[keep], np.ones(keep.sum()))
        moved = src @ R.T + t
        cost = tree_dst.query(moved)[0].mean() + cKDTree(moved).query(dst)[0].mean()
        if best is None or cost < best[0]:
            best = (cost, R, t)
    return best[1], best[2]


def _swing(a, b):
    """Axis-angle of the minimal rotation taking direction a to direction b."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    axis = np.cross(a, b)
    s = np.linalg.norm(axis)
    c = np.clip(a @ b, -1, 1)
    if s < 1e-9:
        return np.zeros(3)
    return axis / s * np.arctan2(s, c)


def _ik_init(rest, parents, target, conf, R0):
    """Local rotations turning each bone onto its keypoint direction (swing only)."""
    from .skinning import rodrigues

    child = primary_children(parents)
    poses = np.zeros((len(rest), 3))
    glob = [None] * len(rest)
    glob[0] = R0
    for j in range(1, len(rest)):
        Rp = glob[parents[j]]
        c = child[j]
        if c >= 0 and conf[j] > 0 and conf[c] > 0:
            want = Rp.T @ (target[c] - target[j])
            if np.linalg.norm(want) > 1e-6:
                poses[j] = _swing(rest[c] - rest[j], want)
        glob[j] = Rp @ rodrigues(poses[j])
    return poses


# ----------------------------------------------------------------------------- fitting

def fit(template, keypoints=None, confidence=None, scans=None, options: FitOptions | None = None,
        side: str | None = None, progress=None) -> FitResult:
    """Fit poses and personalization of ``template`` (HandData) to the targets.

    Args:
        template: HandData (its first frame's pose is ignored; the rest pose is used).
        keypoints: [N, J, 3] metres, or None; the coordinates of missing joints are
            ignored (they may be NaN, as Leap recordings leave them).
        confidence: [N, J] in [0, 1] (0 = missing), or None (all 1).
        scans: list of N point arrays [P_n, 3] (sampled from scan meshes), or None.
        options: FitOptions.
        side: handedness for joint axes (default template.side).
        progress: optional callable(stage: str, step: int, total: int).
    """
    import torch

    # Tensors here are tiny ([N, 25, 3]); thread hand-offs cost more than they
    # save (10× slower with 2 threads on a busy 2-core machine).
    if keypoints is not None:
        keypoints = np.asarray(keypoints, np.float64)
        confidence = (np.ones(keypoints.shape[:2]) if confidence is None
                      else np.asarray(confidence, np.float64))
        observed = confidence > 0
        if not np.isfinite(keypoints[observed]).all():
            raise ValueError("observed keypoints (confidence > 0) must be finite")
        keypoints = np.where(observed[..., None], keypoints, 0.0)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return _fit(template, keypoints, confidence, scans, options, side, progress)
    finally:
        torch.set_num_threads(threads)


def _fit(template, keypoints, confidence, scans, options, side, progress):
    import torch

    opt = options or FitOptions()
    torch.manual_seed(opt.seed)
    rng = np.random.default_rng(opt.seed)
    side = side or template.side
    parents = np.asarray(template.parents)
    rest = np.asarray(template.rest_joints, np.float64)
    J = len(rest)
    if keypoints is None and scans is None:
        raise ValueError("need keypoints, scans or both")
    N = len(keypoints) if keypoints is not None else len(scans)
    if keypoints is not None and confidence is None:
        confidence = np.ones(keypoints.shape[:2])
    axes = joint_axes(rest, side, parents)
    limits = joint_limits()
    child = primary_children(parents)
    free = np.array([child[j] >= 0 or j == 0 for j in range(J)])        # leaves unobservable
    # Scales of bones ending in a joint: observable if any keypoint pair sees them.
    dtype = torch.float64

    # --- initialization (numpy, per frame)
    palm = [0, 1, 5, 6, 10, 11, 15, 16, 20, 21] if J == N_JOINTS else list(range(min(J, 4)))
    init_a = np.zeros((N, J, 3))
    init_b = np.zeros((N, J, 3))
    relaxed = named_pose("relaxed", side, rest)
    trans0 = np.zeros((N, 3))
    from scipy.spatial.transform import Rotation
    if keypoints is None:
        from .skinning import lbs as _lbs
        relaxed_vertices = _lbs(template.coarse.vertices, template.coarse.weights, rest, parents,
                                relaxed)
    for n in range(N):
        if keypoints is not None:
            R0, t0 = _robust_global(rest, keypoints[n], confidence[n], palm)
        else:
            R0, t0 = _rigid_scan_init(relaxed_vertices, scans[n])
        # Our t is applied after rotating about J_0: x = R0·(x − J_0) + J_0 + t.
        t_ours = t0 + R0 @ rest[0] - rest[0]
        theta0 = Rotation.from_matrix(R0).as_rotvec()
        init_b[n] = relaxed
        init_b[n, 0] = theta0
        if keypoints is not None:
            init_a[n] = _ik_init(rest, parents, keypoints[n], confidence[n], R0)
        else:
            init_a[n] = relaxed
        init_a[n, 0] = theta0
        trans0[n] = t_ours
    init_a[:, ~free] = 0
    init_b[:, ~free] = 0

    t_rest = torch.tensor(rest, dtype=dtype)
    t_axes = torch.tensor(axes, dtype=dtype)
    t_lo = torch.tensor(limits[..., 0], dtype=dtype)
    t_hi = torch.tensor(limits[..., 1], dtype=dtype)
    t_free = torch.tensor(free[:, None], dtype=dtype)
    limited = torch.ones(J, 1, dtype=dtype)
    limited[0] = 0.0
    kp = None if keypoints is None else torch.tensor(keypoints, dtype=dtype)
    cf = None if keypoints is None else torch.tensor(confidence, dtype=dtype)

    mesh = template.coarse
    need_mesh = scans is not None
    # With keypoints, the multi-start pose stage ignores the scans (the keypoints
    # choose among starts; nearest-neighbour scan terms are the expensive part).
    use_scans = [True]
    if need_mesh:
        verts0 = torch.tensor(mesh.vertices, dtype=dtype)
        weights = torch.tensor(mesh.weights, dtype=dtype)
        basis = torch.tensor(displacement_basis(mesh.vertices, mesh.weights, rest, parents),
                             dtype=dtype)
        faces = torch.tensor(mesh.faces, dtype=torch.int64)
        lap = _laplacian(len(mesh.vertices), mesh.faces)
        vertex_owner = torch.nn.functional.one_hot(
            torch.as_tensor(mesh.weights.argmax(1)), J).to(dtype)                # [V, J]
        scan_t = [torch.tensor(s, dtype=dtype) for s in scans]
        from scipy.spatial import cKDTree
        scan_trees = [cKDTree(s) for s in scans]

    from .skinning import forward_kinematics_torch, lbs_torch

    def energy(poses, trans, log_scales, offsets, sigma, per_frame=False, per_joint=False):
        scales = torch.exp(log_scales)
        joints_rest = _scaled_joints_torch(t_rest, parents, scales)
        poses = poses * t_free
        terms = torch.zeros(poses.shape[0], dtype=dtype)
        if need_mesh:
            v = verts0 + basis @ (joints_rest - t_rest)
            if offsets is not None:
                v = v + offsets
            posed_v, posed_j = lbs_torch(v, weights, joints_rest, parents, poses, trans)
        else:
            _, pj = forward_kinematics_torch(poses, joints_rest, parents)
            posed_j = pj + trans[:, None, :]
        if kp is not None:
            r2 = ((posed_j - kp) ** 2).sum(-1)
            rho = r2 / (r2 + sigma**2)
            joint_terms = cf * rho / cf.sum(1, keepdim=True).clamp_min(1e-9)   # [N, J]
            terms = terms + joint_terms.sum(1)
        scan_joint_terms = None
        if need_mesh and use_scans[0]:
            scan_terms, per_vertex = _scan_energy(posed_v, faces, scan_t, sigma, rng,
                                                  opt.scan_points, scan_trees)
            terms = terms + opt.w_scan * scan_terms
            if per_joint:   # each vertex's share goes to its dominant joint
                scan_joint_terms = opt.w_scan * per_vertex @ vertex_owner
        angles = torch.einsum("jab,njb->nja", t_axes, poses)
        excess = torch.relu(t_lo - angles) + torch.relu(angles - t_hi)
        limit_terms = opt.w_limits * ((excess**2) * limited).sum(2)         # [N, J]
        terms = terms + limit_terms.sum(1)
        if per_joint:
            out = limit_terms + (joint_terms if kp is not None else 0.0)
            return out if scan_joint_terms is None else out + scan_joint_terms
        if opt.w_smooth > 0 and poses.shape[0] > 1:
            d = ((poses[1:] - poses[:-1]) ** 2).sum((1, 2)) + ((trans[1:] - trans[:-1]) / 0.01).pow(2).sum(1)
            starts = [s - 1 for s in opt.sequence_starts if 0 < s < poses.shape[0]]
            if starts:
                d = d.index_fill(0, torch.tensor(starts), 0.0)
            terms = terms + opt.w_smooth * torch.cat([d, d.new_zeros(1)])
        if per_frame:
            return terms
        total = terms.mean() + opt.w_scale * (log_scales**2).sum()
        if offsets is not None:
            # Means over vertices (independent of the tessellation), in units of σ²
            # like the (near-quadratic) robust data terms, so the balance between
            # data and regularizer does not change as σ anneals.
            total = total + (opt.w_laplacian * (torch.sparse.mm(lap, offsets) ** 2).sum(1).mean()
                             + 1e-2 * (offsets**2).sum(1).mean()) / sigma**2
        return total

    def run(poses_init, trans_init, iters, fit_scales, fit_offsets, log_scales_init=None,
            offsets_init=None, stage=""):
        poses = torch.tensor(poses_init, dtype=dtype, requires_grad=True)
        trans = torch.tensor(trans_init, dtype=dtype, requires_grad=True)
        log_scales = torch.zeros(J, dtype=dtype) if log_scales_init is None else log_scales_init.clone()
        log_scales.requires_grad_(fit_scales)
        offsets = None
        if fit_offsets:
            offsets = (torch.zeros(len(mesh.vertices), 3, dtype=dtype) if offsets_init is None
                       else offsets_init.clone())
            offsets.requires_grad_(True)
        groups = [([poses], 0.03), ([trans], 0.002)]
        if fit_scales:
            groups.append(([log_scales], 0.01))
        if offsets is not None:
            groups.append(([offsets], 0.0005))
        adam = _Adam(groups, iters)
        history = []
        for it in range(iters):
            frac = it / max(iters - 1, 1)
            sigma = 0.030 if frac < 0.25 else (0.015 if frac < 0.5 else 0.008)
            adam.zero_grad()
            e = energy(poses, trans, log_scales, offsets, sigma)
            e.backward()
            adam.step()
            history.append(float(e.detach()))
            if progress is not None:
                progress(stage, it + 1, iters)
        with torch.no_grad():
            final = energy(poses, trans, log_scales, offsets, 0.008, per_frame=True)
            joint_final = energy(poses, trans, log_scales, offsets, 0.008, per_joint=True)
        return poses.detach(), trans.detach(), log_scales.detach(), \
            None if offsets is None else offsets.detach(), final, history, joint_final

    # Stage 1: pose only, from several starts ((swing IK,) relaxed, open, fist);
    # fingers are independent given the palm, so each finger of each frame
    # keeps the start that fits it best, and the wrist/translation come from
    # the start with the lowest energy overall.
    starts = [init_a, init_b] if keypoints is not None else [init_b]
    for name in ("open", "fist"):
        extra = init_b.copy()
        extra[:, 1:] = named_pose(name, side, rest)[1:]
        extra[:, ~free] = 0
        starts.append(extra)
    S = len(starts)
    all_p = np.concatenate(starts)
    all_t = np.concatenate([trans0] * S)
    if scans is not None:
        scan_t = scan_t * S  # noqa: F841  (same scans for every start)
    if keypoints is not None:
        kp = torch.cat([kp] * S)
        cf = torch.cat([cf] * S)
    pre = max(opt.iterations // 3, 1)
    saved_smooth = opt.w_smooth
    opt.w_smooth = 0.0  # the starts are stacked: no smoothness across them
    use_scans[0] = keypoints is None
    p1, t1, _, _, e1, hist1, j1 = run(all_p, all_t, pre, False, False, stage="initial poses")
    use_scans[0] = True
    opt.w_smooth = saved_smooth
    p1 = p1.numpy().reshape(S, N, J, 3)
    t1 = t1.numpy().reshape(S, N, 3)
    best = e1.numpy().reshape(S, N).argmin(0)                           # [N]
    frames = np.arange(N)
    poses_init = p1[best, frames].copy()
    trans_init = t1[best, frames].copy()
    if isinstance(j1, torch.Tensor) and j1.dim() == 2:
        j1 = j1.numpy().reshape(S, N, J)
        for chain in _finger_chains(parents):
            pick = j1[:, :, chain].sum(2).argmin(0)                     # [N]
            poses_init[:, chain] = p1[pick[:, None], frames[:, None], np.asarray(chain)[None]]
    if keypoints is not None:
        kp, cf = kp[:N], cf[:N]
    if scans is not None:
        scan_t = scan_t[:N]
    # Stage 2: everything.
    p2, t2, ls2, off2, e2, hist2, _ = run(poses_init, trans_init, opt.iterations, opt.fit_bone_scales,
                                       opt.fit_offsets and need_mesh, stage="fit")
    poses = (p2 * t_free).numpy()
    trans = t2.numpy()
    scales = np.exp(ls2.numpy())
    scales[0] = 1.0
    new_rest = scaled_joints(rest, parents, scales)
    from .skinning import posed_joints
    pj = posed_joints(poses, trans, new_rest, parents)
    joint_errors = None
    if keypoints is not None:
        obs = confidence > 0
        joint_errors = np.where(obs, np.linalg.norm(pj - keypoints, axis=-1) * 1000, np.nan)
        mean_mm = np.array([joint_errors[n][obs[n]].mean() if obs[n].any() else np.nan
                            for n in range(N)])
        med_mm = np.array([np.median(joint_errors[n][obs[n]]) if obs[n].any() else np.nan
                           for n in range(N)])
    else:
        mean_mm = med_mm = np.full(N, np.nan)
    offsets = None if off2 is None else off2.numpy()
    scan_mm = None
    if scans is not None:
        from .skinning import lbs, vertex_normals
        v = personalize_mesh(mesh.vertices, mesh.weights, rest, parents, scales, offsets)
        scan_mm = np.zeros(N)
        from scipy.spatial import cKDTree
        for n in range(N):
            pv = lbs(v, mesh.weights, new_rest, parents, poses[n], trans[n])
            nrm = vertex_normals(pv, mesh.faces)
            _, idx = cKDTree(pv).query(scans[n])
            scan_mm[n] = np.abs(np.einsum("ij,ij->i", scans[n] - pv[idx], nrm[idx])).mean() * 1000
    return FitResult(poses, trans, scales, offsets, new_rest, mean_mm, med_mm, scan_mm,
                     e2.numpy(), hist1 + hist2, joint_errors)


# ----------------------------------------------------------------------------- fit quality

def _spread(values) -> dict:
    """Mean, std and max |value − mean| of a 1-D sample (mm), rounded for JSON."""
    v = np.asarray(values, np.float64)
    mean = v.mean()
    return {"frames": int(len(v)), "mean": _mm(mean), "std": _mm(v.std()),
            "max_deviation": _mm(np.abs(v - mean).max())}


def _mm(x) -> float:
    return round(float(x), 4)


def bone_lengths(joints, observed, parents) -> np.ndarray:
    """[N, J] length of the bone parent(j) → j in each frame (mm), NaN where an end is
    missing and for the root.  joints: [N, J, 3] metres; observed: [N, J] bool."""
    parents = np.asarray(parents)
    out = np.full(observed.shape, np.nan)
    for j in range(1, len(parents)):
        both = observed[:, j] & observed[:, parents[j]]
        d = np.linalg.norm(joints[:, j] - joints[:, parents[j]], axis=-1) * 1000
        out[both, j] = d[both]
    return out


def fit_quality(result: FitResult, keypoints, confidence, parents, joint_names) -> dict:
    """Per-joint residuals and bone-length stability over time, as JSON-ready numbers (mm).

    Residuals are the distances fitted joint ↔ observed keypoint (missing joints:
    null).  Per bone parent(j) → j (named by j): the keypoints' length over the
    frames where both ends are observed, and the fitted hand's over all frames —
    mean, std and the largest deviation from the mean.  The fitted hand has one
    skeleton for the whole sequence (shared bone scales, rigid bones under
    skinning), so its std is 0 up to rounding; the keypoint side shows how much
    the tracker's bones stretch, and the difference of means the length bias.
    """
    from .skinning import posed_joints

    observed = np.asarray(confidence) > 0
    errors = result.joint_errors_mm
    per_joint = {}
    for j, name in enumerate(joint_names):
        e = errors[observed[:, j], j]
        per_joint[name] = None if len(e) == 0 else {
            "frames": int(len(e)), "mean": _mm(e.mean()), "median": _mm(np.median(e)),
            "p95": _mm(np.percentile(e, 95)), "max": _mm(e.max())}
    everything = errors[observed]
    overall = {"observations": int(len(everything)), "mean": _mm(everything.mean()),
               "median": _mm(np.median(everything)), "p95": _mm(np.percentile(everything, 95)),
               "max": _mm(everything.max())} if len(everything) else None
    fitted = posed_joints(result.poses, result.translations, result.rest_joints, parents)
    kp_len = bone_lengths(np.asarray(keypoints, np.float64), observed, parents)
    fit_len = bone_lengths(fitted, np.ones(observed.shape, bool), parents)
    bones = {}
    for j in range(1, len(joint_names)):
        seen = ~np.isnan(kp_len[:, j])
        entry = {"from": joint_names[int(parents[j])],
                 "keypoints": _spread(kp_len[seen, j]) if seen.any() else None,
                 "fitted": _spread(fit_len[:, j])}
        if seen.any():
            entry["fitted_minus_keypoints"] = _mm(fit_len[:, j].mean() - kp_len[seen, j].mean())
        bones[joint_names[j]] = entry
    return {"joint_residuals_mm": {"all": overall, "per_joint": per_joint},
            "bone_lengths_mm": bones}


class _Adam:
    """Adam with a cosine learning-rate decay (to 1e-3 of the start).

    A few lines instead of torch.optim: importing torch.optim pulls in
    torch._dynamo, which costs seconds per process on small machines.
    """

    def __init__(self, groups, iterations, betas=(0.9, 0.999), eps=1e-12):
        import torch
        self.groups = groups
        self.iterations = max(iterations, 1)
        self.betas, self.eps = betas, eps
        self.t = 0
        self.m = [[torch.zeros_like(p) for p in ps] for ps, _ in groups]
        self.v = [[torch.zeros_like(p) for p in ps] for ps, _ in groups]

    def zero_grad(self):
        for ps, _ in self.groups:
            for p in ps:
                p.grad = None

    def step(self):
        import torch
        b1, b2 = self.betas
        decay = 1e-3 + (1 - 1e-3) * 0.5 * (1 + np.cos(np.pi * min(self.t, self.iterations) / self.iterations))
        self.t += 1
        with torch.no_grad():
            for gi, (ps, lr) in enumerate(self.groups):
                for k, p in enumerate(ps):
                    if p.grad is None:
                        continue
                    m, v = self.m[gi][k], self.v[gi][k]
                    m.mul_(b1).add_(p.grad, alpha=1 - b1)
                    v.mul_(b2).addcmul_(p.grad, p.grad, value=1 - b2)
                    mhat = m / (1 - b1**self.t)
                    vhat = v / (1 - b2**self.t)
                    p.sub_(lr * decay * mhat / (vhat.sqrt() + self.eps))


def _finger_chains(parents) -> list[list[int]]:
    """Joint sets of each chain leaving the root (each finger with its metacarpal)."""
    parents = np.asarray(parents)
    chains = []
    for start in np.nonzero(parents == 0)[0]:
        chain, frontier = [], [int(start)]
        while frontier:
            j = frontier.pop()
            chain.append(j)
            frontier += [int(c) for c in np.nonzero(parents == j)[0]]
        chains.append(sorted(chain))
    return chains


def _laplacian(n_vertices, faces):
    """Uniform graph Laplacian L = I − D⁻¹A as a torch sparse [V, V] tensor."""
    import torch

    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e = np.unique(np.sort(e, 1), axis=0)
    i = np.concatenate([e[:, 0], e[:, 1]])
    j = np.concatenate([e[:, 1], e[:, 0]])
    deg = np.bincount(i, minlength=n_vertices).astype(np.float64)
    vals = -1.0 / deg[i]
    idx = np.concatenate([np.stack([i, j]), np.stack([np.arange(n_vertices)] * 2)], 1)
    vals = np.concatenate([vals, np.ones(n_vertices)])
    return torch.sparse_coo_tensor(torch.tensor(idx), torch.tensor(vals), (n_vertices, n_vertices),
                                   check_invariants=False).coalesce()


def _scan_energy(posed_v, faces, scans, sigma, rng, n_points, trees):
    """Per-frame robust point-to-plane (scan→model) + chamfer (model→scan) energy [N],
    and its split over model vertices [N, V] (each plane term goes to its nearest vertex).

    Correspondences are nearest neighbours found with KD-trees outside the
    autograd graph (the scan's tree is built once per frame, the posed model's
    each call); the energy is differentiable in the model vertices.
    """
    import torch
    from scipy.spatial import cKDTree

    out, per_vertex = [], []
    f = faces
    for n, pts in enumerate(scans):
        v = posed_v[n]
        fn = torch.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]], dim=1)
        vn = torch.zeros_like(v).index_add_(0, f[:, 0], fn).index_add_(0, f[:, 1], fn) \
            .index_add_(0, f[:, 2], fn)
        vn = vn / vn.norm(dim=1, keepdim=True).clamp_min(1e-12)
        sample = pts
        if len(pts) > n_points:
            sample = pts[torch.as_tensor(rng.choice(len(pts), n_points, replace=False))]
        v_np = v.detach().numpy()
        _, nearest_v = cKDTree(v_np).query(sample.numpy())
        _, nearest_p = trees[n % len(trees)].query(v_np)
        nearest_v = torch.as_tensor(nearest_v)
        r = ((sample - v[nearest_v]) * vn[nearest_v]).sum(1)
        plane_terms = r**2 / (r**2 + sigma**2)                               # [P]
        c2 = ((v - pts[torch.as_tensor(nearest_p)]) ** 2).sum(1)
        chamfer_terms = c2 / (c2 + sigma**2)                                 # [V]
        out.append(plane_terms.mean() + chamfer_terms.mean())
        per_vertex.append(chamfer_terms / len(v) + torch.zeros_like(chamfer_terms).index_add_(
            0, nearest_v, plane_terms / len(sample)))
    return torch.stack(out), torch.stack(per_vertex)


def synthetic_truth(template, n: int, seed: int):
    """Known-answer fitting targets: n random poses (the first ones replaced by hard
    cases: fist with self-contact, claw, every joint at its upper limit, then at its
    lower limits), translations ~ N(0, 0.1 m), bone scales in [0.95, 1.05].

    Used by the fitting tests and benchmarks/bench_hand.py, which add their own
    keypoint noise and outliers.

    Args:
        template: HandData of the right hand (rest joints are read).
        n: frames; seed: random seed.

    Returns:
        (poses [n, J, 3], translations [n, 3] metres, bone scales [J],
         scaled rest joints [J, 3], posed joints [n, J, 3] metres).
    """
    from .model import PARENTS
    from .poses import pose_from_angles, random_poses
    from .skinning import posed_joints

    rng = np.random.default_rng(seed)
    poses = random_poses(n, seed=seed, global_rotation=True)
    axes = joint_axes(template.rest_joints, "right")
    lim = joint_limits()
    hard = [named_pose("fist"), named_pose("claw"),
            pose_from_angles(lim[:, :, 1] * [1, 0, 0], axes),
            pose_from_angles(lim[:, :, 0] * [1, 1, 0], axes)]
    for k in range(min(n, len(hard))):
        poses[k, 1:] = hard[k][1:]
    poses[:, [4, 9, 14, 19, 24]] = 0  # fingertip joints have no rotation of their own
    translations = rng.normal(0, 0.1, (n, 3))
    scales = np.ones(N_JOINTS)
    scales[1:] = rng.uniform(0.95, 1.05, N_JOINTS - 1)
    rest = scaled_joints(template.rest_joints, PARENTS, scales)
    joints = posed_joints(poses, translations, rest, PARENTS)
    return poses, translations, scales, rest, joints
