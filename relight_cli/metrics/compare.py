"""Compare a metrics record with a baseline: what moved, and did anything regress?

Every leaf of the baseline's ``metrics`` object (dotted keys, e.g.
``envmap_cube.psnr``) is checked against the same key in the new record:

* direction (``better``): ``higher`` (PSNR, SSIM, IoU, F), ``lower`` (errors) or
  ``either`` (any move beyond tolerance is a regression); known names get their
  direction from :data:`DEFAULT_BETTER` by the key's last component, others
  default to ``either``.
* tolerance: slack = atol + rtol·|baseline|.  A metric *regresses* when it moved
  in the bad direction by more than the slack; moves in the good direction are
  reported as ``improved`` and never fail.
* a metric in the baseline but missing from the new record is a regression
  (``missing``); a metric only in the new record is reported as ``new``.
* ``null`` (JSON's stand-in for +∞, e.g. PSNR of identical images) compares as +∞.
* NaN, or a ``NaN``/``Infinity`` literal (not valid JSON, read as NaN), in either
  record is a regression.

Options map a key to a value by, in order of precedence: the exact dotted key,
a shell-style pattern (``*.psnr``), the key's last component (``psnr``), and
finally a bare default given without a name.
"""

from __future__ import annotations

import fnmatch
import math
from dataclasses import dataclass

DEFAULT_RTOL = 1e-3
DEFAULT_ATOL = 1e-9
DEFAULT_BETTER = {
    "psnr": "higher", "ssim": "higher", "sm_iou": "higher", "boundary_f": "higher",
    "boundary_precision": "higher", "boundary_recall": "higher",
    "mse": "lower", "mae": "lower", "lpips": "lower", "sae": "lower",
    "paa_y": "lower", "apf_y": "lower", "ncm_ab": "lower",
    "paa_angle": "lower", "apf_rms": "lower", "ncm_ab_weighted": "lower",
    "gap_to_ceiling": "lower",
}
DIRECTIONS = ("higher", "lower", "either")


@dataclass
class Row:
    """One compared metric."""

    key: str
    baseline: float | None      # None: absent from the baseline
    new: float | None           # None: absent from the new record
    slack: float
    better: str
    status: str                 # ok | improved | REGRESSED | missing | new

    @property
    def regressed(self) -> bool:
        return self.status in ("REGRESSED", "missing")

    def to_json(self) -> dict:
        """The row of ``relight metrics compare -o`` (formats/metrics_json.md): +∞ is
        ``null`` as in metrics records, NaN the string ``"nan"``, an absent side left out,
        ``change`` only when both sides are finite."""
        out = {"metric": self.key}
        for name, value in (("baseline", self.baseline), ("new", self.new)):
            if value is not None:
                out[name] = "nan" if math.isnan(value) else (None if math.isinf(value)
                                                             else value)
        if (self.baseline is not None and self.new is not None
                and math.isfinite(self.baseline) and math.isfinite(self.new)):
            out["change"] = self.new - self.baseline
        out.update(slack=self.slack, better=self.better, status=self.status,
                   regressed=self.regressed)
        return out


def lookup(options: dict[str | None, object], key: str, default):
    """The option value for ``key`` (see the module docstring for precedence)."""
    if key in options:
        return options[key]
    for pattern, value in options.items():
        if pattern and any(c in pattern for c in "*?[") and fnmatch.fnmatchcase(key, pattern):
            return value
    leaf = key.rsplit(".", 1)[-1]
    if leaf in options:
        return options[leaf]
    return options.get(None, default)


def unknown_names(options: dict[str | None, object], keys: list[str]) -> list[str]:
    """Option names (exact key, pattern or leaf) that match none of ``keys``."""
    leaves = {k.rsplit(".", 1)[-1] for k in keys}
    unknown = []
    for name in options:
        if name is None or name in keys or name in leaves:
            continue
        if any(c in name for c in "*?[") and any(fnmatch.fnmatchcase(k, name) for k in keys):
            continue
        unknown.append(name)
    return unknown


def compare_metrics(new: list[tuple[str, float]], baseline: list[tuple[str, float]],
                    rtol: dict | None = None, atol: dict | None = None,
                    better: dict | None = None) -> list[Row]:
    """Compare flattened metrics (dotted key, value with +∞ for null) → rows in baseline order.

    Args:
        new, baseline: [(key, float)] leaves; use math.inf for stored nulls.
        rtol, atol: {key|pattern|leaf|None: float} tolerances.
        better: {key|pattern|leaf|None: "higher"|"lower"|"either"}.
    """
    rtol = rtol or {}
    atol = atol or {}
    better = better or {}
    new_map = dict(new)
    rows = []
    for key, base in baseline:
        leaf = key.rsplit(".", 1)[-1]
        direction = lookup(better, key, DEFAULT_BETTER.get(leaf, "either"))
        slack = (float(lookup(atol, key, DEFAULT_ATOL))
                 + float(lookup(rtol, key, DEFAULT_RTOL)) * (abs(base) if math.isfinite(base) else 0.0))
        if key not in new_map:
            rows.append(Row(key, base, None, slack, direction, "missing"))
            continue
        value = new_map[key]
        rows.append(Row(key, base, value, slack, direction, _status(value, base, slack, direction)))
    seen = {k for k, _ in baseline}
    for key, value in new:
        if key not in seen:
            leaf = key.rsplit(".", 1)[-1]
            rows.append(Row(key, None, value, 0.0,
                            lookup(better, key, DEFAULT_BETTER.get(leaf, "either")), "new"))
    return rows


def _status(value: float, base: float, slack: float, direction: str) -> str:
    if math.isnan(value) or math.isnan(base):
        return "REGRESSED"  # NaN (or a NaN/Infinity literal) is never an acceptable result
    if value == base:
        return "ok"
    if math.isinf(value) or math.isinf(base):
        # Only +∞ occurs (PSNR of identical images): a move to or from it is large.
        change = math.inf if value > base else -math.inf
    else:
        change = value - base
    if direction == "higher":
        if change < -slack:
            return "REGRESSED"
        return "improved" if change > slack else "ok"
    if direction == "lower":
        if change > slack:
            return "REGRESSED"
        return "improved" if change < -slack else "ok"
    return "REGRESSED" if abs(change) > slack else "ok"


def _fmt(value) -> str:
    if value is None:
        return "-"
    if math.isinf(value):
        return "inf"
    return f"{value:.6g}"


def format_table(rows: list[Row], only_changed: bool = False) -> str:
    """A fixed-width text table: metric, baseline, new, change, slack, better, status."""
    header = ("metric", "baseline", "new", "change", "slack", "better", "status")
    lines = []
    for r in rows:
        if only_changed and r.status == "ok":
            continue
        if r.baseline is None or r.new is None:
            change = "-"
        elif math.isinf(r.baseline) or math.isinf(r.new):
            change = "0" if r.baseline == r.new else ("+inf" if r.new > r.baseline else "-inf")
        else:
            change = f"{r.new - r.baseline:+.3g}"
        lines.append((r.key, _fmt(r.baseline), _fmt(r.new), change, f"{r.slack:.3g}", r.better,
                      r.status))
    widths = [max(len(h), *(len(line[i]) for line in lines)) if lines else len(h)
              for i, h in enumerate(header)]
    out = ["  ".join(h.ljust(w) for h, w in zip(header, widths)).rstrip()]
    out.append("  ".join("-" * w for w in widths))
    out += ["  ".join(c.ljust(w) for c, w in zip(line, widths)).rstrip() for line in lines]
    n_bad = sum(r.regressed for r in rows)
    n_up = sum(r.status == "improved" for r in rows)
    out.append(f"{len(rows)} metric(s): {n_bad} regressed, {n_up} improved")
    return "\n".join(out) + "\n"
