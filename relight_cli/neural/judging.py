"""How a learned model is judged: the rules DESIGN.md makes normative, as one library.

DESIGN.md, "How a learned model is judged", asks three things of every table row and of
every claim read from one, and this module is the one implementation of each (the
benchmarks and ``make study`` call it; tests/neural/test_judging.py holds it to the rules):

- **converged** (:func:`tail_gain`, :func:`converged`): "a table row from a model whose
  validation curve still rises says nothing about the paper; state convergence per row".
  A curve has stopped rising when it gained less than :data:`CONVERGED_DB` over the last
  :data:`CONVERGED_TAIL` of its iterations; a row over several seeds is converged when
  every seed's curve is, not converged as soon as one seed's curve still rises, and
  unknown otherwise (a curve with no point in the window, or one that never reached its
  last iteration).
- **verdict** (:func:`verdict`): "a verdict needs an effect larger than the seed spread and
  a minimum size (a 0.01 dB difference is a tie)".  Paired by seed, the mean difference in
  dB must exceed both :data:`SIGMAS` standard deviations over seeds and
  :data:`MIN_EFFECT_DB`; anything smaller is a tie, and so is one seed alone (no spread to
  exceed).
- **gate** (:func:`gate`, :func:`passes`): "a sabotaged model fails every gate check that
  guards it".  A check's threshold lies halfway between the worst value any measured seed
  gave and the value of the sabotaged (or untrained, or no-effect) model, so no measured
  seed fails it and the sabotage always does; a check whose seeds do not all lie on the
  good side of the sabotage is not robust and is not gated.  And against the **ceiling**
  ("every validation record and table shows model, ceiling and the gap"): a ``--preset``
  meets its goal when its gap to the ceiling is at most :data:`GOAL_DB` (:func:`within_goal`).

Numbers only (floats, lists, small records): no torch, no click, no file I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

#: a curve has stopped rising when it gained less than this (dB) over its tail
CONVERGED_DB = 0.2
#: the tail: the last fraction of a run's iterations the gain is read over
CONVERGED_TAIL = 0.2
#: the smallest effect (dB) a verdict may rest on: a smaller difference is a tie
MIN_EFFECT_DB = 0.2
#: how many standard deviations over seeds an effect must exceed to be a verdict
SIGMAS = 2.0
#: a ``--preset``'s goal: a gap to the ceiling of at most this (dB)
GOAL_DB = 1.0
#: metrics whose differences are read as dB through 10·log10 of their ratio (lower is
#: better; MSE is a power, MAE is scored the same way); PSNR is in dB already
RATIO_METRICS = ("mse", "mae")


def _finite(v) -> bool:
    try:
        return v is not None and math.isfinite(float(v))
    except (TypeError, ValueError):
        return False


def mean_std(values) -> dict:
    """``{"mean", "std", "n", "values"}`` of the finite values (None, NaN and ±inf are left
    out: a diverged or missing run is no measurement); ``std`` is the sample standard
    deviation over seeds (n − 1), 0 for one value; mean and std are None for none."""
    vals = [float(v) for v in values if _finite(v)]
    if not vals:
        return {"mean": None, "std": None, "n": 0, "values": []}
    m = sum(vals) / len(vals)
    s = math.sqrt(sum((v - m) ** 2 for v in vals) / (len(vals) - 1)) if len(vals) > 1 else 0.0
    return {"mean": m, "std": s, "n": len(vals), "values": vals}


def gain_db(before, after, metric: str = "psnr") -> float | None:
    """How much better ``after`` is than ``before``, in dB: a PSNR difference, or 10·log10
    of the ratio for a lower-is-better metric of :data:`RATIO_METRICS` (both positive);
    None for a metric with no dB reading (SSIM) or a value that is missing or not finite."""
    if not (_finite(before) and _finite(after)):
        return None
    before, after = float(before), float(after)
    if metric == "psnr":
        return after - before
    if metric in RATIO_METRICS:
        return 10 * math.log10(before / after) if before > 0 and after > 0 else None
    return None


def tail_gain(curve, iters=None, *, metric: str = "psnr", tail: float = CONVERGED_TAIL,
              last_interval: bool = False) -> tuple:
    """``(gain in dB, step it is read from)`` of one validation curve over its tail.

    ``curve`` is ``[[step, value], ...]`` in step order; ``iters`` the run's last
    iteration (default: the curve's last step).  The gain is the final value against the
    first point at or after ``(1 − tail)·iters`` (and before ``iters``), through
    :func:`gain_db`.  ``(None, None)`` when it cannot be read: the curve does not reach
    ``iters`` with a finite value, or no point lies in the window — unless
    ``last_interval``, where validations sparser than the tail are read over the last
    validation interval instead (from the last point before the end)."""
    curve = [(s, v) for s, v in curve]
    if not curve:
        return None, None
    end = curve[-1][0] if iters is None else iters
    points = [(s, v) for s, v in curve if _finite(v)]
    if end is None or not points or points[-1][0] != end:
        return None, None
    window = [(s, v) for s, v in points if (1 - tail) * end <= s < end]
    if not window and last_interval:
        window = [(s, v) for s, v in points if s < end][-1:]
    if not window:
        return None, None
    step, first = window[0]
    gain = gain_db(first, points[-1][1], metric)
    return (gain, step) if gain is not None else (None, None)


def converged(gains, limit: float = CONVERGED_DB) -> bool | None:
    """Whether a row's curves (one tail gain in dB per seed, :func:`tail_gain`) have
    stopped rising: False as soon as one seed gained ``limit`` or more (that curve still
    rises), True when every seed's gain is known and below it, None otherwise (no seed, or
    a seed whose gain is unknown and none that rises).  A falling curve has stopped rising."""
    gains = list(gains)
    known = [float(g) for g in gains if _finite(g)]
    if any(g >= limit for g in known):
        return False
    if not gains or len(known) != len(gains):
        return None
    return True


@dataclass(frozen=True)
class Verdict:
    """One comparison's verdict: ``word`` is ``better`` (the effect is positive and larger
    than ``margin``), ``worse`` (as clearly negative), ``tie`` or ``not measured`` (no
    finite difference); ``mean``/``std``/``n`` describe the paired differences and
    ``margin`` = max(minimum effect, SIGMAS·std) the size an effect had to exceed."""

    word: str
    mean: float | None
    std: float | None
    n: int
    margin: float | None

    @property
    def decided(self) -> bool:
        return self.word in ("better", "worse")


def verdict(diffs, *, min_effect: float = MIN_EFFECT_DB, sigmas: float = SIGMAS) -> Verdict:
    """The verdict on paired (same-seed) differences ``diffs`` (dB; positive: the claimed
    direction): ``better`` when their mean exceeds max(``min_effect``, ``sigmas``·std over
    seeds), ``worse`` when it is below minus that, else ``tie``; one seed is a tie whatever
    its size (its spread is unknown, and an effect must exceed it); non-finite differences
    are left out (:func:`mean_std`), and none left is ``not measured``.  ``min_effect=0``
    reads a metric with no dB (SSIM) on the seed spread alone."""
    stats = mean_std(diffs)
    if not stats["n"]:
        return Verdict("not measured", None, None, 0, None)
    mean, std, n = stats["mean"], stats["std"], stats["n"]
    margin = max(float(min_effect), sigmas * std)
    if n < 2:
        word = "tie"
    elif mean > margin:
        word = "better"
    elif mean < -margin:
        word = "worse"
    else:
        word = "tie"
    return Verdict(word, mean, std, n, margin)


@dataclass(frozen=True)
class Gate:
    """A gate check's margin: ``threshold`` (None: not gated), ``robust`` (every measured
    seed on the good side of the sabotage), ``worst`` (the worst measured seed),
    ``sabotaged`` (the sabotaged, untrained or no-effect value) and ``better``
    (``higher`` or ``lower``)."""

    threshold: float | None
    robust: bool
    worst: float | None
    sabotaged: float
    better: str


def gate(values, sabotaged: float, better: str = "higher") -> Gate:
    """A gate check from its measured seeds and the value a sabotaged model gives: robust
    when every seed is finite and strictly better than the sabotage; its threshold then
    halfway between the worst seed and the sabotage (so no measured seed fails and the
    sabotage always does), else None (reported, never gated).  A ratio of the paper's
    worse row to its better row is gated against 1 (no effect), a gap to the ceiling
    against the same model never trained."""
    if better not in ("higher", "lower"):
        raise ValueError(f"better must be 'higher' or 'lower', not {better!r}")
    values = list(values)
    sabotaged = float(sabotaged)
    if not values or not all(_finite(v) for v in values) or not _finite(sabotaged):
        return Gate(None, False, None, sabotaged, better)
    worst = min(map(float, values)) if better == "higher" else max(map(float, values))
    robust = worst > sabotaged if better == "higher" else worst < sabotaged
    threshold = sabotaged + (worst - sabotaged) / 2 if robust else None
    return Gate(threshold, robust, worst, sabotaged, better)


def passes(value, check: Gate) -> bool | None:
    """Whether ``value`` is on the good side of ``check``'s threshold (strictly); None for a
    check that is not gated; a missing or non-finite value fails."""
    if check.threshold is None:
        return None
    if not _finite(value):
        return False
    return float(value) > check.threshold if check.better == "higher" \
        else float(value) < check.threshold


def within_goal(gap_db, goal_db: float = GOAL_DB) -> bool | None:
    """Whether a model's gap to its ceiling (dB) meets a preset's goal (≤ ``goal_db``);
    None when the gap is unknown."""
    if not _finite(gap_db):
        return None
    return float(gap_db) <= goal_db
