"""Can the student's features say what the teacher renders?  A per-texel linear ceiling.

RelightableHands' student (Sec. 4) maps texel-aligned, visibility-aware shading
features (diffuse and Phong lobes of the env map, Eq. 8-9) and the pose to a texture.
When a trained student sits far below the teacher it distils, two readings compete:
the features cannot express the teacher's appearance, or the decoder has not learned
the map.  This study separates them.  For every texel t and colour c it fits, by least
squares over training (pose, camera, env) samples, the teacher's texel radiance as a
linear function of the same texel's features of that colour (diffuse, phong16/32/64)
plus a constant, everything divided by the env scale s as the student's inputs are:

    C_t,c / s  ≈  Σ_k w_t,c,k · f_t,c,k / s  +  b_t,c            (ridge, λ relative)

and scores it exactly as the student is scored (held-out poses × held-out env maps,
composited through the capture's G-buffer, PSNR inside the hand mask against the
teacher's render).  The student checkpoint is scored on the same pairs.  If the
linear map beats the student, the features suffice and the decoder underfits; if it
stays far below the teacher, the features are the bottleneck.

    python benchmarks/study_student_features.py --capture CAP --teacher T.pt \
        --student S.pt --envs ENVS.json --out benchmarks/results/student_features

``ENVS.json`` holds ``{"train": [...], "eval": [...]}`` env specs (the split the
student was distilled with).  Writes ``student_features.{md,json}``; no timings inside.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--capture", required=True)
    ap.add_argument("--teacher", required=True)
    ap.add_argument("--student", required=True)
    ap.add_argument("--envs", required=True, help="JSON {train: [...], eval: [...]}")
    ap.add_argument("--train-items", type=int, default=48,
                    help="training (pose, camera) pairs sampled evenly")
    ap.add_argument("--envs-per-item", type=int, default=3)
    ap.add_argument("--eval-samples", type=int, default=16)
    ap.add_argument("--ridge", type=float, default=1e-4, help="λ relative to the mean diagonal")
    ap.add_argument("--out", required=True)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)

    import torch
    torch.set_num_threads(args.threads)
    from relight_cli.envmap import discretize_env
    from relight_cli.formats.checkpoint import read_checkpoint
    from relight_cli.inputs import load_envmap
    from relight_cli.neural import distill as D
    from relight_cli.neural.data import CaptureData
    from relight_cli.neural.teacher import composite
    from relight_cli.neural.checkpoints import load

    t0 = time.perf_counter()
    split = json.loads(Path(args.envs).read_text())
    specs = list(split["train"]) + list(split["eval"])
    train_idx = list(range(len(split["train"])))
    eval_idx = list(range(len(split["train"]), len(specs)))
    net, cfg, _ = load(read_checkpoint(args.student, kind="student"))
    tnet, tcfg, mean = load(read_checkpoint(args.teacher, kind="teacher"))
    data = CaptureData(args.capture, tcfg.tex_res, tcfg.aa, tcfg.visibility, tcfg.falloff,
                       tcfg.holdout, 256)
    envs = [discretize_env(load_envmap(s), *cfg.env_res) for s in specs]
    targets = D.TeacherTargets(tnet, tcfg, data, envs[0], None, 16000, "cpu", mean,
                               identity=Path(args.teacher).name)
    task = D.StudentTask(data, cfg, targets, envs, train_idx, eval_idx, specs)
    names = task.features.names                      # diffuse, phong16, ...
    k_feat = len(names)
    rng = np.random.default_rng(0)

    def sample(pose, cam, denv, held_out):
        hand = data.eval_hand if held_out else data.hand
        pf = task.features.pose(hand, pose, key=(held_out, pose))
        feats = task.features.maps(pf, denv, data._cameras[cam].center)    # [Hh, 3K, N, N]
        tex = targets.texture(pose, cam, denv, held_out)                   # Hh × [3, N, N]
        s = D.env_scale(denv)
        return feats / s, np.stack([t.numpy() for t in tex]) / s, s

    # ---- fit: per hand, texel and colour, least squares over the training samples
    items = task.items[::max(1, len(task.items) // args.train_items)][:args.train_items]
    xs, ys = [], []
    for i, (pose, cam) in enumerate(items):
        for e in rng.choice(train_idx, size=min(args.envs_per_item, len(train_idx)),
                            replace=False):
            denv = envs[int(e)]
            if cfg.rotations:
                denv = D.rotate_env(denv, int(rng.integers(denv.width - 1)))
            x, y, _ = sample(pose, cam, denv, False)
            xs.append(x)
            ys.append(y)
        print(f"  fit data {i + 1}/{len(items)}  {time.perf_counter() - t0:.0f} s", flush=True)
    X = np.stack(xs)                                   # [S, Hh, 3K, N, N]
    Y = np.stack(ys)                                   # [S, Hh, 3, N, N]
    s_, hh, _, n, _ = X.shape
    # feature k of colour c is channel 3k + c
    Xc = X.reshape(s_, hh, k_feat, 3, n, n)
    A = np.concatenate([Xc, np.ones((s_, hh, 1, 3, n, n), X.dtype)], axis=2)  # [S,Hh,K+1,3,N,N]
    A = np.moveaxis(A, 0, -1).astype(np.float64)       # [Hh, K+1, 3, N, N, S]
    Yc = np.moveaxis(Y, 0, -1).astype(np.float64)      # [Hh, 3, N, N, S]
    G = np.einsum("hkcxys,hjcxys->hcxykj", A, A)       # [Hh, 3, N, N, K+1, K+1]
    b = np.einsum("hkcxys,hcxys->hcxyk", A, Yc)
    lam = args.ridge * np.trace(G, axis1=-2, axis2=-1)[..., None, None] / (k_feat + 1) + 1e-12
    W = np.linalg.solve(G + lam * np.eye(k_feat + 1), b[..., None])[..., 0]   # [Hh,3,N,N,K+1]

    def linear_texture(x):
        xc = x.reshape(hh, k_feat, 3, n, n).astype(np.float64)
        xa = np.concatenate([xc, np.ones((hh, 1, 3, n, n))], axis=1)
        return np.einsum("hkcxy,hcxyk->hcxy", xa, W)

    fit_rows = []
    for x, y in zip(xs, ys):
        res = linear_texture(x) - y
        fit_rows.append(float(np.mean(res ** 2)))

    # ---- score: held-out poses × held-out envs, as evaluate_student picks them
    pairs = [(f.pose, c) for f in data.heldout_frames for c in f.images]
    combos = [(p, c, e) for p, c in pairs for e in eval_idx]
    pick = np.unique(np.linspace(0, len(combos) - 1, min(len(combos), args.eval_samples))
                     .round().astype(int))
    rows = []
    net.eval()
    with torch.no_grad():
        for j in pick:
            pose, cam, e = combos[j]
            denv = envs[e]
            x, y, s = sample(pose, cam, denv, False)       # held-out poses of the sequence
            gb = data.gbuffer(pose, data._cameras[cam])
            target = targets.image(pose, cam, denv).numpy()
            lin = composite([torch.from_numpy((t * s).astype(np.float32))
                             for t in linear_texture(x)], gb).numpy()
            stud = task.render(net, pose, cam, denv, "cpu").numpy()
            teach_tex = composite([torch.from_numpy((t * s).astype(np.float32)) for t in y],
                                  gb).numpy()
            mask = gb.mask
            rows.append({"pose": int(pose), "camera": cam, "env": specs[e],
                         "linear": D._metrics(lin, target, mask)["psnr"],
                         "student": D._metrics(stud, target, mask)["psnr"],
                         "teacher_texture": D._metrics(teach_tex, target, mask)["psnr"]})
            print(f"  {rows[-1]}", flush=True)
    lin_ps = [r["linear"] for r in rows]
    stu_ps = [r["student"] for r in rows]
    result = {
        "capture": args.capture, "teacher": args.teacher, "student": args.student,
        "features": names, "train_samples": int(s_), "ridge": args.ridge,
        "tex_res": int(n), "env_res": list(cfg.env_res),
        "fit_train_psnr_texture": float(-10 * np.log10(np.mean(fit_rows) /
                                                         max(float(np.mean(Y ** 2)), 1e-30))),
        "heldout": rows,
        "linear_mean": float(np.mean(lin_ps)), "student_mean": float(np.mean(stu_ps)),
        "linear_minus_student": [float(a - b) for a, b in zip(lin_ps, stu_ps)],
    }
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "student_features.json").write_text(json.dumps(result, indent=2) + "\n")
    d = np.array(result["linear_minus_student"])
    md = ["# The student's features against a per-texel linear map of them", "",
          f"Capture `{args.capture}`, teacher `{Path(args.teacher).name}`, student "
          f"`{Path(args.student).name}` ({n}² texture, env grid "
          f"{cfg.env_res[1]}x{cfg.env_res[0]}); {s_} training samples "
          f"({len(items)} (pose, camera) pairs × {args.envs_per_item} env maps), features "
          f"{', '.join(names)} per colour plus a constant, ridge λ = {args.ridge} (relative).",
          "", "PSNR (dB) inside the hand mask against the teacher's render, held-out poses "
          "× held-out env maps:", "",
          "| pose | camera | env | per-texel linear | student |", "|---|---|---|---|---|"]
    md += [f"| {r['pose']} | {r['camera']} | {Path(r['env']).name} | {r['linear']:.2f} | "
           f"{r['student']:.2f} |" for r in rows]
    md += ["", f"Mean: linear {result['linear_mean']:.2f}, student {result['student_mean']:.2f} "
           f"(linear − student {d.mean():+.2f} ± {d.std(ddof=1) / np.sqrt(len(d)):.2f} s.e.); "
           "the teacher's own texture composited scores "
           f"{np.mean([r['teacher_texture'] for r in rows]):.1f} (the compositing ceiling).",
           f"Linear fit on its training samples (texture space): "
           f"{result['fit_train_psnr_texture']:.2f} dB.", ""]
    (out / "student_features.md").write_text("\n".join(md))
    print("\n".join(md))
    return 0


if __name__ == "__main__":
    sys.exit(main())
