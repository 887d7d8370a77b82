"""Model checkpoints: format ``relight/checkpoint`` version 1 (spec: ``formats/checkpoint.md``).

A checkpoint is one ``torch.save`` archive of a dict of plain values and tensors, read
back only with ``torch.load(weights_only=True)``: loading never runs code from the
file.  Text fields (config, RNG states, provenance) are JSON strings so the archive
holds nothing but str/int/float/bool, lists, dicts and tensors.

torch is imported inside the functions (this module is imported by ``--help`` paths).
"""

from __future__ import annotations

import json
import os

from relight_cli.errors import DataError

from ._common import check_format_version

FORMAT = "relight/checkpoint"
VERSION = 1
KINDS = ("teacher", "student", "linear")
REQUIRED = ("format", "version", "kind", "model", "config", "step", "weights", "optimizer",
            "rng", "capture_key", "pose_dim", "provenance")


def make_checkpoint(kind: str, model_name: str, config: dict, step: int, weights: dict,
                    optimizer: dict, rng: dict, capture_key: str, pose_dim: int,
                    provenance: dict, extra: dict | None = None) -> dict:
    """The checkpoint dict (see the spec for each field)."""
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    return {"format": FORMAT, "version": VERSION, "kind": kind, "model": model_name,
            "config": json.dumps(config, sort_keys=True), "step": int(step),
            "weights": weights, "optimizer": optimizer,
            "rng": {k: (v if not isinstance(v, (dict, list)) else json.dumps(v))
                    for k, v in rng.items()},
            "capture_key": str(capture_key), "pose_dim": int(pose_dim),
            "provenance": json.dumps(provenance, sort_keys=True),
            "extra": dict(extra or {})}


def write_checkpoint(path: str, checkpoint: dict) -> None:
    """Write atomically (temp file in the same folder, then rename).

    A write that fails inside ``torch.save`` (a full disk, an I/O error) reaches here as
    the RuntimeError of torch's zip writer (``[enforce fail at inline_container.cc…]``),
    the file's OSError at most its context; it is raised as that OSError (ENOSPC when
    the writer gave none and the disk is full, else EIO), which the atomic write reports
    as every output's write error, ``cannot write: REASON (PATH)``, leaving nothing."""
    import torch

    from relight_cli.fileio import atomic_path
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            try:
                torch.save(checkpoint, f)
            except RuntimeError as exc:
                error = _write_error(exc, tmp)
                if error is None:
                    raise
                raise error from None


def _write_error(exc: RuntimeError, tmp: str) -> OSError | None:
    """The OSError behind a RuntimeError of torch's zip writer, or None when ``exc`` is
    not a write failure (a bug: raised as it is)."""
    import errno
    seen, cause = set(), exc
    while cause is not None and id(cause) not in seen:
        seen.add(id(cause))
        if isinstance(cause, OSError):
            return cause
        cause = cause.__cause__ or cause.__context__
    text = str(exc)
    if "inline_container" not in text and "PytorchStreamWriter" not in text:
        return None
    try:
        vfs = os.statvfs(os.path.dirname(tmp) or ".")
        full = vfs.f_blocks and (vfs.f_bfree if os.geteuid() == 0 else vfs.f_bavail) == 0
    except OSError:
        full = False
    if full:
        return OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    return OSError(errno.EIO, os.strerror(errno.EIO))


#: The variants of each kind, and the configuration field that names the variant.
MODELS = {"teacher": (("olat", "ggx"), "model"), "student": (("student", "dram"), "student"),
          "linear": (("linear",), "model")}
#: Bounds of what a file may declare (checked before anything is computed on it).
MAX_POSE_DIM = 300           # (joints − 1) × 3: a hand of up to 101 joints
MAX_HANDS = 4                # per-hand records and mean textures
MAX_SUBJECTS = 1024          # subjects of a linear model (extra.subjects, URHand Sec. 4)
MAX_TENSORS = 100_000        # tensors anywhere in the archive
MAX_DEPTH = 16               # nesting of the plain-data tree
MAX_STEP = 10 ** 9           # the configurations' largest ``iters``
ADAM_STATE = ("step", "exp_avg", "exp_avg_sq")
_DTYPES = ("float32", "float64", "float16", "bfloat16", "uint8", "int8", "int16", "int32",
           "int64", "bool")


def read_checkpoint(path: str, kind: str | None = None, model: str | None = None, *,
                    config_class) -> dict:
    """Read and check a checkpoint: the one validator of the format, used by every command
    that reads one.  Returns its dict with ``config`` and ``provenance`` decoded from JSON
    and ``path`` (the file read, so later checks against a model can name it).

    Everything the file declares is checked before anything is computed on it (see
    "What is checked" in ``formats/README.md``): a zip archive of plain data; every tensor
    dense (no stride-0 or overlapping views), of a plain dtype, all of them together no
    larger than the file; the fields' types; the configuration (that of its kind,
    validated); the model named by kind and configuration; ``step`` and ``pose_dim`` in
    range; the optimizer's structure; each RNG state loadable; ``extra``'s fields; every
    float tensor finite.  ``config_class``: kind → the class whose ``from_dict`` validates
    that kind's configuration (its fields' JSON types and ranges, raising UsageProblem);
    the schemas are the engine's, next to their presets, so the format is read through
    :func:`relight_cli.neural.checkpoints.read_checkpoint`, which passes the model
    registry's.  What needs the model itself (each weight's and optimizer
    moment's shape against the module the configuration builds) is checked by
    :func:`relight_cli.neural.train.load_weights` and ``restore_state`` before use.
    Raises DataError naming the file.
    """
    import pickle
    import warnings
    import zipfile

    import torch

    if not os.path.isfile(path):
        raise DataError("no such checkpoint file", path)
    size = os.path.getsize(path)
    # torch.save writes a zip of stored (uncompressed) members; a legacy tar/pickle
    # stream or a compressed member could make the loader allocate what it declares
    try:
        with zipfile.ZipFile(path) as archive:
            members = archive.infolist()
    except (zipfile.BadZipFile, OSError, ValueError, EOFError):
        raise DataError("not a relight checkpoint (not a torch zip archive)", path) from None
    if any(m.file_size > size for m in members):
        raise DataError("not a relight checkpoint (a zip member declares more bytes than the "
                        "file holds)", path)
    try:
        with warnings.catch_warnings():
            # torch warns about foreign pickle protocols before refusing them: one line only
            warnings.simplefilter("ignore")
            obj = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        first = (str(exc).splitlines() or ["?"])[0][:120]
        raise DataError(f"refused: not a plain-data checkpoint (weights_only load failed: "
                        f"{first})", path) from None
    except Exception as exc:  # zip/pickle/EOF errors of damaged or foreign files
        first = (str(exc).splitlines() or [type(exc).__name__])[0][:120]
        raise DataError(f"not a relight checkpoint ({first})", path) from None
    if not isinstance(obj, dict) or obj.get("format") != FORMAT:
        raise DataError(f"not a {FORMAT} file", path)
    check_format_version(obj.get("format"), obj.get("version"), FORMAT, VERSION, path)
    missing = [k for k in REQUIRED if k not in obj]
    if missing:
        raise DataError(f"checkpoint lacks field(s) {', '.join(missing)}", path)
    tensors = _tensors(obj, path)                       # sizes bounded before any use
    for key in ("kind", "model", "config", "capture_key", "provenance"):
        if not isinstance(obj[key], str):
            raise DataError(f"checkpoint field {key} must be a string, got "
                            f"{type(obj[key]).__name__}", path)
    if obj["kind"] not in KINDS:
        raise DataError(f"checkpoint kind must be one of {', '.join(KINDS)}, got "
                        f"{_short(obj['kind'])}", path)
    if kind is not None and obj["kind"] != kind:
        raise DataError(f"checkpoint holds a {obj['kind']!r} model, expected {kind!r}", path)
    names, field = MODELS[obj["kind"]]
    if obj["model"] not in names:
        raise DataError(f"checkpoint model must be {' or '.join(names)} for kind "
                        f"{obj['kind']!r}, got {_short(obj['model'])}", path)
    if model is not None and obj["model"] != model:
        raise DataError(f"checkpoint holds model {obj['model']!r}, expected {model!r}", path)
    obj["config"] = _json_field(obj["config"], "config", dict, path)
    obj["provenance"] = _json_field(obj["provenance"], "provenance", dict, path)
    config = _config(obj, path, config_class(obj["kind"]))
    if getattr(config, field) != obj["model"]:
        raise DataError(f"checkpoint model {obj['model']!r} differs from its configuration's "
                        f"{field} {getattr(config, field)!r}", path)
    step = obj["step"]
    if not _is_int(step) or not 0 <= step <= config.iters:
        raise DataError(f"checkpoint step must be an integer in [0, iters = {config.iters}], "
                        f"got {_short(step)}", path)
    pose_dim = obj["pose_dim"]
    if not _is_int(pose_dim) or not 3 <= pose_dim <= MAX_POSE_DIM or pose_dim % 3:
        raise DataError(f"checkpoint pose_dim must be (joints − 1) × 3 in [3, {MAX_POSE_DIM}], "
                        f"got {_short(pose_dim)}", path)
    if not 1 <= len(obj["capture_key"]) <= 256:
        raise DataError("checkpoint capture_key must be a short string", path)
    _check_state_dict(obj["weights"], "weights", path)
    check_optimizer(obj["optimizer"], "optimizer", path)
    decode_rng(obj["rng"], path)
    obj["extra"] = _check_extra(obj.get("extra", {}), obj["kind"], obj["model"], config, path,
                                obj["capture_key"])
    for where, value in tensors:
        if value.is_floating_point() and not bool(torch.isfinite(value).all()):
            label = where[len("weights."):] if where.startswith("weights.") else where
            raise DataError(f"checkpoint {'weight ' if label != where else ''}{label} holds "
                            f"NaN/Inf", path)
    obj["path"] = path
    return obj


def _short(value) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _is_int(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value) -> bool:
    import math
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _dense(tensor) -> bool:
    """Every element its own memory: strides a permutation of a contiguous layout's (no
    stride-0 broadcast, no overlap), so numel × itemsize is what the tensor occupies."""
    dims = sorted((st, sz) for st, sz in zip(tensor.stride(), tensor.shape) if sz > 1)
    expected = 1
    for st, sz in dims:
        if st != expected:
            return False
        expected *= sz
    return True


def _tensors(obj, path: str) -> list:
    """[(where, tensor)] of every tensor in the archive's tree, after bounding them: each
    a dense strided CPU tensor of a plain dtype, all together no more bytes than the file
    (a file holds each tensor's data once: a view cannot declare more than it stores)."""
    import torch
    out, total, size = [], 0, os.path.getsize(path)
    stack = [("", obj, 0)]
    while stack:
        where, value, depth = stack.pop()
        if depth > MAX_DEPTH:
            raise DataError(f"checkpoint entry {where} is nested more than {MAX_DEPTH} levels "
                            f"deep", path)
        if isinstance(value, dict):
            stack.extend((f"{where}.{k}" if where else str(k), v, depth + 1)
                         for k, v in value.items())
        elif isinstance(value, (list, tuple)):
            stack.extend((f"{where}[{i}]", v, depth + 1) for i, v in enumerate(value))
        elif isinstance(value, torch.Tensor):
            name = where[:80]
            if value.layout != torch.strided or value.device.type != "cpu" or \
                    str(value.dtype).replace("torch.", "") not in _DTYPES:
                raise DataError(f"checkpoint tensor {name} is not a plain dense tensor "
                                f"({value.layout}, {value.dtype})", path)
            if value.ndim > 8 or not _dense(value):
                raise DataError(f"checkpoint tensor {name} of shape {_short(tuple(value.shape))} "
                                f"is a strided view, not the data it declares", path)
            total += value.numel() * value.element_size()
            if total > size:
                raise DataError(f"checkpoint tensors declare more data than the file holds "
                                f"(at {name}, shape {_short(tuple(value.shape))})", path)
            out.append((where, value))
            if len(out) > MAX_TENSORS:
                raise DataError(f"checkpoint holds more than {MAX_TENSORS} tensors", path)
    return out


def _json_field(text: str, name: str, kind: type, path: str):
    from ._common import parse_json
    try:
        value = parse_json(text, path)
    except DataError as exc:
        raise DataError(f"checkpoint {name}: {exc.message}", path) from None
    if not isinstance(value, kind):
        raise DataError(f"checkpoint {name} must be a JSON {'object' if kind is dict else 'array'}"
                        f", got {type(value).__name__}", path)
    return value


def _config(obj: dict, path: str, cls):
    """The checkpoint's configuration, validated by its kind's class ``cls`` (DataError)."""
    from relight_cli.errors import UsageProblem
    try:
        return cls.from_dict(obj["config"], "checkpoint config")
    except UsageProblem as exc:
        raise DataError(exc.message, path) from None
    except (TypeError, ValueError) as exc:
        raise DataError(f"checkpoint config: {str(exc).splitlines()[0][:120]}", path) from None


def _check_state_dict(state, name: str, path: str) -> None:
    """A state dict: str → tensor (shapes are checked against the model by load_weights)."""
    import torch
    if not isinstance(state, dict) or not all(
            isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in state.items()):
        raise DataError(f"checkpoint {name} must map names to tensors", path)


def check_optimizer(state, name: str, path: str) -> None:
    """The structure of an Adam ``state_dict()``: ``state`` {int: {step, exp_avg,
    exp_avg_sq[, max_exp_avg_sq]}} and ``param_groups`` [{params: [int], hyperparameters}]
    (their shapes against the parameters: ``relight_cli.neural.train.check_optimizer_state``)."""
    import torch
    if not isinstance(state, dict) or set(state) != {"state", "param_groups"}:
        raise DataError(f"checkpoint {name} must be an optimizer state dict (state, "
                        f"param_groups)", path)
    groups, per_param = state["param_groups"], state["state"]
    if not isinstance(groups, list) or not groups or not all(isinstance(g, dict) for g in groups):
        raise DataError(f"checkpoint {name}.param_groups must be a list of groups", path)
    seen = set()
    for g in groups:
        params = g.get("params")
        if not isinstance(params, list) or not all(_is_int(i) and 0 <= i < MAX_TENSORS
                                                   for i in params):
            raise DataError(f"checkpoint {name}.param_groups: params must list parameter "
                            f"indices", path)
        seen.update(params)
        for key, value in g.items():
            if key == "params":
                continue
            if not isinstance(key, str) or not (value is None or isinstance(value, bool)
                                                or _is_number(value) or (
                    isinstance(value, (tuple, list)) and len(value) <= 4
                    and all(_is_number(v) for v in value))):
                raise DataError(f"checkpoint {name}.param_groups: {_short(key)} must be a "
                                f"number, a flag or a pair of numbers", path)
    if not isinstance(per_param, dict):
        raise DataError(f"checkpoint {name}.state must map parameter indices to moments", path)
    for index, entry in per_param.items():
        if not _is_int(index) or index not in seen:
            raise DataError(f"checkpoint {name}.state has an entry for {_short(index)}, which "
                            f"is no parameter of its groups", path)
        if not isinstance(entry, dict) or not set(ADAM_STATE) <= set(entry) or \
                not set(entry) <= {*ADAM_STATE, "max_exp_avg_sq"}:
            raise DataError(f"checkpoint {name}.state[{index}] must hold Adam's "
                            f"{', '.join(ADAM_STATE)}", path)
        step = entry["step"]
        if isinstance(step, torch.Tensor):
            step = float(step) if step.numel() == 1 and step.ndim == 0 and \
                step.is_floating_point() else None
        if not _is_number(step) or not 0 <= step <= MAX_STEP:
            raise DataError(f"checkpoint {name}.state[{index}].step must be a count in "
                            f"[0, {MAX_STEP}]", path)
        for key in set(entry) - {"step"}:
            if not isinstance(entry[key], torch.Tensor) or not entry[key].is_floating_point():
                raise DataError(f"checkpoint {name}.state[{index}].{key} must be a float "
                                f"tensor", path)


def decode_rng(rng, path: str | None) -> tuple:
    """(torch ByteTensor, numpy state tuple, python state tuple) of a checkpoint's ``rng``
    field, each checked by loading it into a scratch generator (the process's own are
    untouched); DataError naming the file otherwise."""
    import random

    import numpy as np
    import torch
    if not isinstance(rng, dict) or not {"torch", "numpy", "python"} <= set(rng):
        raise DataError("checkpoint rng must hold torch, numpy and python states", path)
    state = rng["torch"]
    reference = torch.get_rng_state()
    if not isinstance(state, torch.Tensor) or state.dtype != torch.uint8 or \
            tuple(state.shape) != tuple(reference.shape):
        raise DataError(f"checkpoint rng.torch must be a ByteTensor of {reference.numel()} "
                        f"bytes (torch.get_rng_state())", path)
    try:
        torch.Generator().set_state(state)
    except (RuntimeError, TypeError, ValueError):
        raise DataError("checkpoint rng.torch is not a valid generator state", path) from None

    def decoded(name):
        value = rng[name]
        if isinstance(value, str):
            value = _json_field(value, f"rng.{name}", list, path)
        if not isinstance(value, (list, tuple)) or len(value) != (5 if name == "numpy" else 3):
            source = "np.random.get_state()" if name == "numpy" else "random.getstate()"
            raise DataError(f"checkpoint rng.{name} must be the list of {source}", path)
        return value

    def words(value, count):
        return isinstance(value, (list, tuple)) and len(value) == count and all(
            _is_int(w) and 0 <= w < 2 ** 32 for w in value)

    np_state = decoded("numpy")
    if np_state[0] != "MT19937" or not words(np_state[1], 624) or not _is_int(np_state[2]) \
            or not 0 <= np_state[2] <= 624 or np_state[3] not in (0, 1) \
            or isinstance(np_state[3], bool) or not _is_number(np_state[4]):
        raise DataError("checkpoint rng.numpy is not a valid MT19937 state", path)
    np_tuple = ("MT19937", np.asarray(np_state[1], np.uint32), int(np_state[2]),
                int(np_state[3]), float(np_state[4]))
    py = decoded("python")
    if not _is_int(py[0]) or not words(py[1], 625) or not (py[2] is None or _is_number(py[2])):
        raise DataError("checkpoint rng.python is not a valid random.getstate()", path)
    py_tuple = (py[0], tuple(py[1]), py[2])
    for name, load, value in (("numpy", np.random.RandomState().set_state, np_tuple),
                              ("python", random.Random().setstate, py_tuple)):
        try:
            load(value)
        except (ValueError, TypeError, OverflowError):
            raise DataError(f"checkpoint rng.{name} is not a valid generator state",
                            path) from None
    return state, np_tuple, py_tuple


def _hex(value, digits: int) -> bool:
    return isinstance(value, str) and len(value) == digits and all(
        c in "0123456789abcdef" for c in value)


def _check_extra(extra, kind: str, model: str, config, path: str,
                 capture_key: str | None = None) -> dict:
    """``extra``'s known fields typed (see the spec); unknown fields are kept as read."""
    import torch
    if not isinstance(extra, dict) or not all(isinstance(k, str) for k in extra):
        raise DataError(f"checkpoint extra must be a dict, got {type(extra).__name__}", path)
    extra = dict(extra)
    if "uv_layout" in extra and not _hex(extra["uv_layout"], 16):
        raise DataError("checkpoint extra.uv_layout must be 16 hex digits", path)
    if "hands" in extra:
        hands = extra["hands"]
        if isinstance(hands, str):
            hands = _json_field(hands, "extra.hands", list, path)
        if not isinstance(hands, list) or not 1 <= len(hands) <= MAX_HANDS or not all(
                isinstance(h, dict) and h.get("side") in ("right", "left")
                and _hex(h.get("uv_chart"), 16) for h in hands):
            raise DataError(f"checkpoint extra.hands must list 1 to {MAX_HANDS} "
                            f"{{side: right|left, uv_chart: 16 hex digits}}", path)
        extra["hands"] = hands
    mean = extra.get("mean_texture")
    if mean is None and model in ("ggx", "linear"):
        raise DataError(f"a {model} checkpoint needs its mean texture (extra.mean_texture)", path)
    if mean is not None:
        n = config.tex_res
        if not isinstance(mean, torch.Tensor) or mean.dtype != torch.float32 or mean.ndim != 4 \
                or not 1 <= mean.shape[0] <= MAX_HANDS or tuple(mean.shape[1:]) != (3, n, n):
            shape = _short(tuple(mean.shape)) if isinstance(mean, torch.Tensor) else \
                type(mean).__name__
            raise DataError(f"checkpoint extra.mean_texture must be float32 [1..{MAX_HANDS}, 3, "
                            f"{n}, {n}] (tex_res {n}), got {shape}", path)
    if "subjects" in extra or "mean_textures" in extra:
        _check_subjects(extra, kind, config, path, capture_key)
    if kind == "linear" and getattr(config, "lambda_gan", 0) > 0:
        for key in ("discriminator", "optimizer_discriminator"):
            if key not in extra:
                raise DataError(f"checkpoint extra lacks {key} (lambda_gan > 0)", path)
    if "discriminator" in extra:
        _check_state_dict(extra["discriminator"], "extra.discriminator", path)
    if "optimizer_discriminator" in extra:
        check_optimizer(extra["optimizer_discriminator"], "extra.optimizer_discriminator", path)
    if "teacher_sha256" in extra and not (extra["teacher_sha256"] == ""
                                          or _hex(extra["teacher_sha256"], 64)):
        raise DataError("checkpoint extra.teacher_sha256 must be 64 hex digits", path)
    if "envs" in extra:
        envs = _json_field(extra["envs"], "extra.envs", dict, path) \
            if isinstance(extra["envs"], str) else None
        if not isinstance(envs, dict) or not all(
                isinstance(envs.get(k), list) and all(isinstance(n, str) for n in envs[k])
                for k in ("train", "eval")):
            raise DataError("checkpoint extra.envs must be the JSON of {train: [names], "
                            "eval: [names]}", path)
    return extra


def _check_subjects(extra: dict, kind: str, config, path: str, capture_key) -> None:
    """``extra.subjects`` and ``extra.mean_textures`` of a linear model trained on several
    subjects (URHand Sec. 4.3, Table 2): together or not at all; one record {capture_key:
    a short string, unique, the first the checkpoint's ``capture_key``; skin_seed: an
    integer or null; mean_texture: a row of mean_textures} per subject; mean_textures
    float32 [S, 1..4, 3, N, N] (N = tex_res), finite, its first subject's row equal to
    ``extra.mean_texture``."""
    import torch
    if kind != "linear":
        raise DataError(f"checkpoint extra.subjects belongs to a linear checkpoint, not a "
                        f"{kind} one", path)
    if "subjects" not in extra or "mean_textures" not in extra:
        raise DataError("checkpoint extra.subjects and extra.mean_textures come together "
                        "(one without the other)", path)
    subjects, means = extra["subjects"], extra["mean_textures"]
    n = config.tex_res
    if not isinstance(means, torch.Tensor) or means.dtype != torch.float32 or means.ndim != 5 \
            or not 1 <= means.shape[0] <= MAX_SUBJECTS or not 1 <= means.shape[1] <= MAX_HANDS \
            or tuple(means.shape[2:]) != (3, n, n):
        shape = _short(tuple(means.shape)) if isinstance(means, torch.Tensor) else \
            type(means).__name__
        raise DataError(f"checkpoint extra.mean_textures must be float32 [1..{MAX_SUBJECTS}, "
                        f"1..{MAX_HANDS}, 3, {n}, {n}] (tex_res {n}), got {shape}", path)
    if not bool(torch.isfinite(means).all()):
        raise DataError("checkpoint extra.mean_textures holds NaN/Inf", path)

    def record(r):
        return isinstance(r, dict) and isinstance(r.get("capture_key"), str) \
            and 1 <= len(r["capture_key"]) <= 256 and "skin_seed" in r \
            and (r["skin_seed"] is None or _is_int(r["skin_seed"])) \
            and _is_int(r.get("mean_texture")) and 0 <= r["mean_texture"] < means.shape[0]
    if not isinstance(subjects, list) or not 1 <= len(subjects) <= MAX_SUBJECTS or \
            not all(record(r) for r in subjects):
        raise DataError(f"checkpoint extra.subjects must list 1 to {MAX_SUBJECTS} {{capture_key: "
                        f"a short string, skin_seed: an integer or null, mean_texture: a row "
                        f"of extra.mean_textures (0..{means.shape[0] - 1})}}", path)
    keys = [r["capture_key"] for r in subjects]
    if len(set(keys)) != len(keys):
        raise DataError("checkpoint extra.subjects lists a capture_key twice", path)
    if capture_key is not None and keys[0] != capture_key:
        raise DataError(f"checkpoint extra.subjects[0].capture_key {_short(keys[0])} is not "
                        f"its capture_key {_short(capture_key)}", path)
    mean = extra.get("mean_texture")
    first = means[subjects[0]["mean_texture"]]
    if isinstance(mean, torch.Tensor) and mean.is_floating_point() and \
            not bool(torch.isfinite(mean).all()):
        return                          # read_checkpoint's finite check names it
    if not isinstance(mean, torch.Tensor) or tuple(mean.shape) != tuple(first.shape) or \
            mean.dtype != first.dtype or not torch.equal(mean, first):
        raise DataError("checkpoint extra.mean_texture is not its first subject's row of "
                        "extra.mean_textures", path)


def read_state_dict(path: str, what: str = "weights") -> dict:
    """A plain torch state dict file (e.g. local VGG or LPIPS weights), loaded with
    ``weights_only=True``; DataError naming the file when it is anything else."""
    import warnings

    import torch
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for non-checkpoint files
        msg = (str(exc).splitlines() or [type(exc).__name__])[0][:160]
        raise DataError(f"not a loadable torch state dict: {msg}", path) from None
    if not isinstance(state, dict):
        raise DataError(f"{what} must be a state dict (key → tensor)", path)
    return state
