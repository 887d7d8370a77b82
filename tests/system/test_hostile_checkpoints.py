"""Hostile checkpoints and distill caches (issue 23: nothing trusted that a file declares).

One tiny teacher (olat and ggx), linear model and student are trained once; each row
damages a copy the way a hostile or broken file would — sizes that would make us allocate
terabytes (stride-0 views, huge declared shapes, pose_dim 10¹²), resume state of the wrong
shape or type, fields of the wrong type, damaged ``--cache`` entries — and runs the real
entry point on it: ``relight HAND --checkpoint``, ``relight CAPTURE/``, ``train-teacher
--resume``, ``distill TEACHER``, ``distill --resume``, ``distill --cache``.  A damaged
checkpoint must end in one line ``relight <cmd>: error: <what> (<file>)``, exit 1, nothing
written, inputs untouched; a damaged cache entry is a miss (recomputed, rewritten, named
once on stderr).  What is checked is listed in formats/README.md ("What is checked when a
checkpoint and a distill cache are read").
"""

from __future__ import annotations

import hashlib
import json
import zipfile

import numpy as np
import pytest

torch = pytest.importorskip("torch")

CAPTURE_ARGS = ["--cameras", "2", "--leds", "6", "--group", "2", "--n-frames", "4", "--size",
                "16", "--tex-res", "32", "--aa", "1", "--eval-poses", "1", "--eval-cameras",
                "1", "--eval-envs", "builtin:sky", "--eval-env-res", "16x8", "-q"]
TEACHER = {"tex_res": 16, "encoder": [4, 4, 4], "decoder": [8, 8, 8], "pose_channels": [4, 4],
           "val_samples": 1, "aa": 1}
LINEAR = {"tex_res": 16, "encoder": [4, 4, 4], "decoder": [4, 4, 4], "pose_channels": [4, 4],
          "light_decoder": [8, 8, 8, 8, 8, 8, 8, 4], "light_levels": 2, "val_samples": 1,
          "aa": 1}
STUDENT = {"tex_res": 16, "decoder": [8, 8, 8, 8, 8, 8, 8], "pose_channels": [4, 8],
           "val_samples": 1, "env_holdout": 0.34, "env_res": [4, 8], "cache_mb": 0}
ENVS = ["--envs", "builtin:sky", "--envs", "builtin:studio", "--envs", "builtin:uniform"]
HUGE = 10 ** 6


def _cli(*args):
    from click.testing import CliRunner

    from relight_cli.cli import cli
    return CliRunner().invoke(cli, [str(a) for a in args])


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """A capture and one real checkpoint of each kind (2 iterations each: seconds)."""
    root = tmp_path_factory.mktemp("hostile")
    for name, cfg in (("teacher", TEACHER), ("linear", LINEAR), ("student", STUDENT)):
        (root / f"{name}.json").write_text(json.dumps(cfg))
    runs = [["synth-capture", "-o", root / "cap", *CAPTURE_ARGS],
            ["train-teacher", root / "cap", "--config", root / "teacher.json", "--iters", "2",
             "-q", "-o", root / "teacher.pt"],
            ["train-teacher", root / "cap", "--config", root / "teacher.json", "--iters", "2",
             "--model", "ggx", "-q", "-o", root / "ggx.pt"],
            ["train-teacher", root / "cap", "--config", root / "linear.json", "--iters", "2",
             "--model", "linear", "-q", "-o", root / "linear.pt"],
            ["distill", root / "teacher.pt", root / "cap", *ENVS, "--config",
             root / "student.json", "--iters", "1", "-q", "-o", root / "student.pt",
             "--cache", root / "cache"]]
    for args in runs:
        r = _cli(*args)
        assert r.exit_code == 0, r.output
    return root


def _load(path):
    return torch.load(path, weights_only=True)


def _other_layout():
    """The UV layout digest of another hand model (the coarse mesh's chart)."""
    from relight_cli.hand.model import builtin_hand
    from relight_cli.neural.geometry import uv_layout_digest
    return uv_layout_digest(builtin_hand().mesh("coarse"))


def _first(state):
    return next(iter(state))


def _set(obj, dotted, value):
    """obj with the entry at a dotted path (``weights.NAME``, ``extra.mean_texture``) set."""
    keys = dotted.split(".", 1)
    if len(keys) == 1:
        obj[dotted] = value
    elif keys[0] == "weights":
        obj["weights"][keys[1]] = value
    else:
        obj[keys[0]][keys[1]] = value
    return obj


def _weight(ck, value):
    ck["weights"][_first(ck["weights"])] = value
    return ck


def _moment(ck, value):
    ck["optimizer"]["state"][0]["exp_avg"] = value
    return ck


def _shared_views(ck, big):
    """Ten entries on one stored 4 MB tensor: the file holds 4 MB, they declare 40."""
    for i in range(10):
        ck["weights"][f"evil{i}"] = big
    return ck


def _rng(ck, name, value):
    ck["rng"][name] = value
    return ck


def _deflated(src, dst):
    """The same archive with a zero-filled data member deflated: it declares far more bytes
    than the file holds (what a zip bomb looks like to the loader)."""
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as zout:
        big = False
        for info in zin.infolist():
            data = zin.read(info)
            if not big and "/data/" in info.filename:
                data, big = bytes(len(data) + (1 << 22)), True
                zout.writestr(info.filename, data, compress_type=zipfile.ZIP_DEFLATED)
            else:
                zout.writestr(info, data)


def _py_state(bad_pos):
    import random
    v, internal, g = random.getstate()
    return json.dumps([v, list(internal[:-1]) + [bad_pos], g])


def _np_state(pos):
    s = np.random.get_state()
    return json.dumps([s[0], s[1].tolist(), pos, 0, 0.0])


# (id, checkpoint, damage, entry point, what the one line must say)
ROWS = [
    # --- sizes declared inside a checkpoint are bounded before anything is computed
    ("weight-stride0-huge", "teacher", lambda c: _weight(c, torch.zeros(1).expand(HUGE, HUGE)),
     "relight", "strided view"),
    ("extra-weight-stride0", "teacher",
     lambda c: _set(c, "weights.evil", torch.zeros(1).expand(HUGE, HUGE)), "relight",
     "strided view"),
    ("ggx-mean-texture-huge", "ggx",
     lambda c: _set(c, "extra.mean_texture", torch.zeros(1).expand(10 ** 5, 3, 10 ** 4, 10 ** 4)),
     "relight", "strided view"),
    ("pose-dim-1e12", "teacher", lambda c: _set(c, "pose_dim", 10 ** 12), "relight", "pose_dim"),
    ("student-pose-dim-1e12", "student", lambda c: _set(c, "pose_dim", 10 ** 12),
     "relight-student", "pose_dim"),
    ("ggx-mean-texture-wrong-res", "ggx",
     lambda c: _set(c, "extra.mean_texture", torch.zeros(1, 3, 8, 8)), "relight",
     "mean_texture"),
    ("linear-mean-texture-stride0", "linear",
     lambda c: _set(c, "extra.mean_texture", torch.zeros(1).expand(4, 3, 10 ** 5, 10 ** 5)),
     "relight-linear", "strided view"),
    ("capture-eval-stride0", "teacher", lambda c: _weight(c, torch.zeros(1).expand(HUGE, HUGE)),
     "capture", "strided view"),
    ("config-huge-model", "teacher",
     lambda c: _set(c, "config", json.dumps({**json.loads(c["config"]), "tex_res": 4096,
                                             "encoder": [4096] * 3, "decoder": [4096] * 3,
                                             "untied_bias": True})), "relight", "tensor"),
    # issue 52 cause 12: sizes that would run out of memory, refused before anything is built
    ("config-feature-maps-too-large", "teacher",
     lambda c: _set(c, "config", json.dumps({**json.loads(c["config"]), "tex_res": 4096,
                                             "encoder": [1024] * 3, "decoder": [1024] * 3})),
     "relight", "feature tensor"),
    ("student-config-feature-maps-too-large", "student",
     lambda c: _set(c, "config", json.dumps({**json.loads(c["config"]), "tex_res": 4096,
                                             "decoder": [512] * 7})),
     "relight-student", "feature tensor"),
    ("linear-config-too-many-parameters", "linear",
     lambda c: _set(c, "config", json.dumps({**json.loads(c["config"]), "encoder": [4096] * 3,
                                             "decoder": [4096] * 3})),
     "relight-linear", "parameters"),
    ("distill-teacher-stride0", "teacher",
     lambda c: _weight(c, torch.zeros(1).expand(HUGE, HUGE)), "distill-teacher", "strided view"),
    ("rng-torch-stride0", "teacher",
     lambda c: _rng(c, "torch", torch.zeros(1, dtype=torch.uint8).expand(10 ** 9)), "resume",
     "strided view"),
    ("optimizer-moment-stride0", "teacher",
     lambda c: _moment(c, torch.zeros(1).expand(HUGE, HUGE)), "resume", "strided view"),
    ("tensor-bytes-beyond-file", "teacher", lambda c: _shared_views(c, torch.zeros(HUGE)),
     "relight", "more data than the file"),
    ("zip-member-deflated", "teacher", None, "relight", "declares more bytes"),
    # --- --resume: the whole state checked against this run's model and optimizer
    ("resume-weight-shape", "teacher", lambda c: _weight(c, torch.zeros(1, 2, 3)), "resume",
     "shape"),
    ("resume-optimizer-int-state", "teacher", lambda c: _set(c, "optimizer", {"state": 5}),
     "resume", "optimizer"),
    ("resume-optimizer-state-5", "teacher",
     lambda c: _set(c, "optimizer", {"state": 5, "param_groups": c["optimizer"]["param_groups"]}),
     "resume", "optimizer"),
    ("resume-moment-shape", "teacher", lambda c: _moment(c, torch.zeros(2, 2)), "resume",
     "exp_avg"),
    ("resume-moment-nan", "teacher",
     lambda c: _moment(c, c["optimizer"]["state"][0]["exp_avg"] * float("nan")), "resume",
     "NaN"),
    ("resume-optimizer-other-params", "teacher",
     lambda c: c["optimizer"]["param_groups"][0].update(params=[0, 1]) or c, "resume",
     "optimizer"),
    ("resume-optimizer-capturable", "teacher",
     lambda c: c["optimizer"]["param_groups"][0].update(capturable=True) or c, "resume",
     "capturable"),
    ("resume-step-negative", "teacher", lambda c: _set(c, "step", -1), "resume", "step"),
    ("resume-step-string", "teacher", lambda c: _set(c, "step", "2"), "resume", "step"),
    ("resume-step-huge", "teacher", lambda c: _set(c, "step", 10 ** 30), "resume", "step"),
    ("resume-rng-torch-size", "teacher",
     lambda c: _rng(c, "torch", torch.zeros(10, dtype=torch.uint8)), "resume", "rng.torch"),
    ("resume-rng-torch-invalid", "teacher",
     lambda c: _rng(c, "torch", torch.zeros_like(c["rng"]["torch"])), "resume", "rng.torch"),
    ("resume-rng-numpy-pos", "teacher", lambda c: _rng(c, "numpy", _np_state(999)), "resume",
     "rng.numpy"),
    ("resume-rng-python", "teacher", lambda c: _rng(c, "python", _py_state(10 ** 6)), "resume",
     "rng.python"),
    ("resume-linear-weight-shape", "linear", lambda c: _weight(c, torch.zeros(3)), "resume",
     "shape"),
    ("distill-resume-weight-shape", "student", lambda c: _weight(c, torch.zeros(1, 2, 3)),
     "distill-resume", "shape"),
    ("distill-resume-optimizer", "student", lambda c: _set(c, "optimizer", {"state": 5}),
     "distill-resume", "optimizer"),
    ("distill-resume-rng", "student", lambda c: _rng(c, "numpy", "[1, 2"), "distill-resume",
     "rng.numpy"),
    # --- fields of the wrong type or value
    ("config-json-list", "teacher", lambda c: _set(c, "config", "[1, 2]"), "relight",
     "config must be a JSON object"),
    ("extra-int", "teacher", lambda c: _set(c, "extra", 5), "relight", "extra"),
    ("model-unet9", "teacher", lambda c: _set(c, "model", "unet9"), "relight", "unet9"),
    ("uv-layout-not-hex", "teacher", lambda c: _set(c, "extra.uv_layout", ["x"]), "relight",
     "uv_layout"),
    ("uv-layout-other-hand", "teacher", lambda c: _set(c, "extra.uv_layout", _other_layout()),
     "relight", "uv_layout is not the UV layout"),
    ("uv-layout-other-hand-linear", "linear",
     lambda c: _set(c, "extra.uv_layout", _other_layout()), "relight-linear", "uv_layout is not the UV layout"),
    ("uv-layout-other-hand-capture", "teacher",
     lambda c: _set(c, "extra.uv_layout", _other_layout()), "capture",
     "uv_layout is not the UV layout"),
    ("ggx-mean-texture-nan", "ggx",
     lambda c: _set(c, "extra.mean_texture", c["extra"]["mean_texture"] * float("nan")),
     "relight", "NaN"),
    ("config-field-type", "teacher",
     lambda c: _set(c, "config", json.dumps({**json.loads(c["config"]), "encoder": 5})),
     "relight", "encoder"),
    ("hands-not-a-list", "linear", lambda c: _set(c, "extra.hands", 7), "relight-linear",
     "hands"),
    ("kind-not-a-string", "teacher", lambda c: _set(c, "kind", 5), "resume", "kind"),
    ("student-envs-list", "student", lambda c: _set(c, "extra.envs", "[1]"), "distill-resume",
     "envs"),
]


def _command(made, entry, ckpt, out):
    root = made
    hand = root / "cap" / "hand.npz"
    if entry.startswith("relight"):
        model = {"relight": "teacher", "relight-student": "student",
                 "relight-linear": "linear"}[entry]
        return ["relight", hand, "builtin:sky", "--model", model, "--checkpoint", ckpt,
                "--size", "16x16", "-o", out / "o.exr"]
    if entry == "capture":
        return ["relight", root / "cap", "--model", "teacher", "--checkpoint", ckpt,
                "--eval-samples", "1", "-o", out / "m.json"]
    if entry == "resume":
        return ["train-teacher", root / "cap", "--resume", ckpt, "--iters", "3",
                "-o", out / "t.pt"]
    if entry == "distill-teacher":
        return ["distill", ckpt, root / "cap", *ENVS, "--config", root / "student.json",
                "--iters", "1", "-o", out / "s.pt"]
    assert entry == "distill-resume"
    return ["distill", root / "teacher.pt", root / "cap", *ENVS, "--resume", ckpt,
            "--iters", "3", "-o", out / "s.pt"]


def _digest(folder):
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("case, base, damage, entry, says", ROWS, ids=[r[0] for r in ROWS])
def test_hostile_checkpoint_is_one_line(made, tmp_path, case, base, damage, entry, says):
    bad = tmp_path / "in" / "bad.pt"
    bad.parent.mkdir()
    if damage is None:
        _deflated(made / f"{base}.pt", bad)
    else:
        torch.save(damage(_load(made / f"{base}.pt")), bad)
    out = tmp_path / "out"
    out.mkdir()
    before_ckpt, before_cap = bad.read_bytes(), _digest(made / "cap")
    r = _cli(*_command(made, entry, bad, out), "-q")
    lines = [ln for ln in r.output.strip().splitlines() if ln.strip()]
    assert r.exit_code == 1, r.output
    assert len(lines) == 1 and "Traceback" not in r.output, r.output
    assert lines[0].startswith(f"relight {_command(made, entry, bad, out)[0]}: error: "), lines
    assert lines[0].endswith(f"({bad})") and says in lines[0], lines[0]
    assert list(out.iterdir()) == []
    assert bad.read_bytes() == before_ckpt and _digest(made / "cap") == before_cap


def test_real_checkpoints_still_load_and_resume(made, tmp_path):
    """The validators accept what relight writes (every kind, resumed one step further)."""
    from relight_cli.neural.checkpoints import read_checkpoint
    for name in ("teacher", "ggx", "linear", "student"):
        ck = read_checkpoint(str(made / f"{name}.pt"))
        assert ck["path"] == str(made / f"{name}.pt")
    r = _cli("train-teacher", made / "cap", "--resume", made / "ggx.pt", "--iters", "3", "-q",
             "-o", tmp_path / "g.pt")
    assert r.exit_code == 0, r.output


# ---------------------------------------------------------------- distill --cache

def _cache_entries(made):
    return sorted((made / "cache").glob("*.npy"))


def _damage_cache(path, how):
    arr = np.load(path)
    if how == "truncated":
        path.write_bytes(path.read_bytes()[:-100])
    elif how == "mis-shaped":
        np.save(path, arr[:, :1])
    elif how == "pickled":
        np.save(path, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    elif how == "nan":
        np.save(path, np.full_like(arr, np.nan))
    elif how == "float64":
        np.save(path, arr.astype(np.float64))


@pytest.mark.parametrize("how", ["truncated", "mis-shaped", "pickled", "nan", "float64"])
def test_damaged_cache_entry_is_recomputed(made, tmp_path, how):
    """A bad --cache entry is a miss: recomputed, rewritten valid, named once on stderr;
    the student comes out as from a good cache (never from the bad values)."""
    import shutil
    cache = tmp_path / "cache"
    shutil.copytree(made / "cache", cache)
    entries = sorted(cache.glob("*.npy"))
    assert entries
    good = {p.name: np.load(p) for p in entries}
    for p in entries:
        _damage_cache(p, how)
    out = tmp_path / "s.pt"
    r = _cli("distill", made / "teacher.pt", made / "cap", *ENVS, "--config",
             made / "student.json", "--iters", "1", "-o", out, "--cache", cache)
    assert r.exit_code == 0, r.output
    notes = [ln for ln in r.output.splitlines() if "--cache entry" in ln]
    assert len(notes) == 1 and str(cache) in notes[0], r.output
    for p in entries:
        np.testing.assert_array_equal(np.load(p, allow_pickle=False), good[p.name])
    assert sorted(q.name for q in cache.iterdir()) == sorted(good)      # no temp files
    reference = _load(made / "student.pt")["weights"]
    for k, v in _load(out)["weights"].items():
        torch.testing.assert_close(v, reference[k], rtol=0, atol=0)


def test_cache_write_interrupted_leaves_nothing(made, tmp_path, monkeypatch):
    """SIGTERM (the CLI raises it as an exception) while an entry is written: no temp
    file, no entry."""
    from relight_cli.neural import distill as D
    targets = D.TeacherTargets.__new__(D.TeacherTargets)
    targets.cache_dir = str(tmp_path / "c")
    targets._verified = {}

    def dying_save(f, value, allow_pickle=False):
        f.write(b"\x93NUMPY partial")
        raise KeyboardInterrupt
    monkeypatch.setattr(D.np, "save", dying_save)
    with pytest.raises(KeyboardInterrupt):
        targets._write_cached(str(tmp_path / "c" / "k.npy"), np.zeros((1, 2), np.float32))
    assert list((tmp_path / "c").iterdir()) == []
