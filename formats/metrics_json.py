"""Metrics JSON: format ``relight/metrics`` version 2 (spec: ``formats/metrics_json.md``).

One JSON object per file, keys always in the same order so diffs stay readable::

    format, version, kind, metrics, [per_channel], [aggregate], [pairs], [frames],
    [details], inputs, settings, provenance

``metrics`` is a (possibly nested) object of numbers; ``relight metrics compare``
compares its leaves.  A metric whose value is +∞ (PSNR of identical images) is
stored as ``null`` because JSON has no infinity; see :func:`decode_value`.
"""

from __future__ import annotations

import json
import math

from relight_cli.errors import DataError

from ._common import check_format_version

FORMAT = "relight/metrics"
VERSION = 2
# Version 1 lighting records named this toolkit's variants paa_y, apf_y, ncm_ab;
# version 2 gives those names to the paper's definitions (Sec. 4.1).
V1_LIGHTING_NAMES = {"paa_y": "paa_angle", "apf_y": "apf_rms", "ncm_ab": "ncm_ab_weighted"}
KINDS = ("image", "shadow", "lighting", "gate", "validation")
# The order keys are written in; anything else follows in insertion order.
KEY_ORDER = ("format", "version", "kind", "metrics", "per_channel", "aggregate", "pairs",
             "frames", "details", "inputs", "settings", "provenance")


def encode_value(value):
    """A JSON-safe number: floats rounded-trip exactly, ±∞ → None (null), NaN refused."""
    if value is None:
        return None
    if isinstance(value, bool):
        return value
    if isinstance(value, int):
        return value
    value = float(value)
    if math.isnan(value):
        raise ValueError("NaN metric value")
    if math.isinf(value):
        return None
    return value


def decode_value(value):
    """Inverse of :func:`encode_value` for comparison: null → +∞."""
    return math.inf if value is None else float(value)


def _encode_tree(obj):
    if isinstance(obj, dict):
        return {str(k): _encode_tree(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_encode_tree(v) for v in obj]
    if isinstance(obj, str) or obj is None:
        return obj
    if hasattr(obj, "item") and not isinstance(obj, (int, float)):  # numpy scalars
        obj = obj.item()
    return encode_value(obj)


def make_record(kind: str, metrics: dict, inputs: dict, settings: dict, provenance: dict,
                **extra) -> dict:
    """Build a record with keys in :data:`KEY_ORDER` (``extra``: per_channel, aggregate, ...)."""
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    fields = {"format": FORMAT, "version": VERSION, "kind": kind, "metrics": metrics,
              "inputs": inputs, "settings": settings, "provenance": provenance, **extra}
    ordered = {k: fields[k] for k in KEY_ORDER if k in fields and fields[k] is not None}
    for k, v in fields.items():
        if k not in ordered and v is not None:
            ordered[k] = v
    return {k: (v if k in ("format", "version", "kind") else _encode_tree(v))
            for k, v in ordered.items()}


def dumps(record: dict) -> str:
    """Serialize with stable key order and round-trippable floats (repr)."""
    return json.dumps(record, indent=2, allow_nan=False, ensure_ascii=False) + "\n"


def write_metrics(path: str, record: dict) -> None:
    """Write atomically (``-`` = stdout)."""
    from relight_cli.fileio import write_text_atomic
    write_text_atomic(path, dumps(record))


def loads(text: str, path: str = "<string>") -> dict:
    """Parse and validate a metrics record.  Raises DataError naming ``path``."""
    from ._common import parse_json
    record = parse_json(text, path, non_finite="nan")
    if not isinstance(record, dict):
        raise DataError("metrics JSON must hold an object", path)
    version = check_format_version(record.get("format"), record.get("version"), FORMAT, VERSION,
                                   path)
    metrics = record.get("metrics")
    if not isinstance(metrics, dict):
        raise DataError("missing 'metrics' object", path)
    if version == 1 and record.get("kind") == "lighting":
        record["metrics"] = metrics = _upgrade_v1_lighting(metrics)
    for key, value in flatten(metrics):
        if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float))):
            raise DataError(f"metric {key!r} is not a number", path)
    return record


def _upgrade_v1_lighting(tree):
    """Rename version 1's lighting leaves to their version 2 names (they are the variants)."""
    if not isinstance(tree, dict):
        return tree
    return {V1_LIGHTING_NAMES.get(k, k) if not isinstance(v, dict) else k: _upgrade_v1_lighting(v)
            for k, v in tree.items()}


def read_metrics(path: str) -> dict:
    """Read and validate a metrics record (``-``: stdin)."""
    from ._common import read_text
    path = str(path)
    return loads(read_text(path, "a metrics JSON file"), path)


def flatten(metrics: dict, prefix: str = "") -> list[tuple[str, object]]:
    """Leaves of a nested metrics object as (dotted.key, value), in file order."""
    out = []
    for key, value in metrics.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            out.extend(flatten(value, name + "."))
        else:
            out.append((name, value))
    return out


# ----------------------------------------------------------------------------- comparisons

COMPARISON_FORMAT = "relight/metrics-comparison"
COMPARISON_VERSION = 1
COMPARISON_KEYS = ("format", "version", "kind", "regressed", "exit_code", "counts", "rows",
                   "inputs", "settings", "provenance")


def make_comparison(kind: str, rows: list[dict], exit_code: int, inputs: dict, settings: dict,
                    provenance: dict) -> dict:
    """The record of ``relight metrics compare -o`` (keys in :data:`COMPARISON_KEYS`).

    ``rows``: one object per compared metric (``Row.to_json`` of
    relight_cli.metrics.compare): metric, [baseline], [new], [change], slack, better,
    status (ok | improved | REGRESSED | missing | new), regressed.
    """
    statuses = [r["status"] for r in rows]
    counts = {"metrics": len(rows), "regressed": sum(bool(r["regressed"]) for r in rows),
              "improved": statuses.count("improved"), "missing": statuses.count("missing"),
              "new": statuses.count("new")}
    return {"format": COMPARISON_FORMAT, "version": COMPARISON_VERSION, "kind": kind,
            "regressed": counts["regressed"] > 0, "exit_code": int(exit_code), "counts": counts,
            "rows": rows, "inputs": inputs, "settings": settings, "provenance": provenance}


def loads_comparison(text: str, path: str = "<string>") -> dict:
    """Parse and check a comparison record (DataError naming ``path``)."""
    from ._common import parse_json
    record = parse_json(text, path)
    if not isinstance(record, dict):
        raise DataError("a metrics comparison JSON holds an object", path)
    check_format_version(record.get("format"), record.get("version"), COMPARISON_FORMAT,
                         COMPARISON_VERSION, path)
    if not isinstance(record.get("rows"), list) or not isinstance(record.get("regressed"), bool):
        raise DataError("missing 'rows' list or 'regressed' flag", path)
    return record
