"""Helpers of the learned models' tests (tests/neural/, tests/commands/test_train_teacher.py):
a flat UV plane, the DDP runner, the linear model's smallest configuration."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

# The smallest teacher: 16² texture, 4-wide U-Net (resume/DDP/CLI tests need seconds only).
TEACHER_SMALL = {"tex_res": 16, "encoder": [4, 4, 4], "decoder": [8, 8, 8], "pose_channels": [4, 4],
                 "val_samples": 2}
# The smallest linear model: 16² maps, 4-wide F_G, 8-wide light path with 2 levels (16 → 4²).
LINEAR_SMALL = {"tex_res": 16, "encoder": [4, 4, 4], "decoder": [4, 4, 4], "pose_channels": [4, 4],
                "light_decoder": [8, 8, 8, 8, 8, 8, 8, 4], "light_levels": 2, "val_samples": 2,
                "aa": 1}


def _plane(n=4, flip=False):
    """A unit square in the z = 0 plane, UV = (x, y) (or mirrored x for ``flip``)."""
    from relight_cli.hand.scene import PosedMesh
    xs, ys = np.meshgrid(np.linspace(0, 1, n + 1), np.linspace(0, 1, n + 1))
    v = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], 1)
    uv = v[:, :2].copy()
    faces = []
    for r in range(n):
        for c in range(n):
            a = r * (n + 1) + c
            faces += [[a, a + 1, a + n + 2], [a, a + n + 2, a + n + 1]]
    faces = np.asarray(faces)
    if flip:
        v = v * [-1, 1, 1]
        faces = faces[:, ::-1]
    normals = np.tile([0.0, 0.0, 1.0], (len(v), 1))
    return PosedMesh(v, faces, uv, faces.copy(), normals, "plane")


def _torchrun():
    exe = Path(sys.executable).with_name("torchrun")
    if not exe.exists():
        pytest.skip("torchrun is not installed next to this interpreter")
    return str(exe)


def _ddp_pair(script_text: str, capture_dir, tmp_path):
    """Run ``script_text`` (it saves OUT/rank{RANK}.pt) under torchrun with 2 CPU processes;
    the two ranks' saved weights."""
    script = tmp_path / "ddp.py"
    script.write_text(script_text)
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONWARNINGS="ignore")
    # --standalone: a local rendezvous on a free port
    r = subprocess.run([_torchrun(), "--standalone", "--nproc_per_node=2", str(script),
                        str(capture_dir), str(tmp_path)], capture_output=True, text=True,
                       timeout=300, env=env)
    assert r.returncode == 0, r.stderr[-2000:]
    import torch
    return (torch.load(tmp_path / "rank0.pt", weights_only=True),
            torch.load(tmp_path / "rank1.pt", weights_only=True))
