"""Fit an SH light probe: ``relight sh-probe`` as a job.

:func:`fit` samples the radiance of a loaded environment map, or of a Gaussian scene
seen from a point (its six cube faces splatted on the CPU, paper Sec. 3.4), and fits
the real SH coefficients by solid-angle-weighted ridge least squares
(:mod:`relight_cli.gaussians.probe`), at a fixed degree or the smallest one the
``auto`` search accepts, optionally through a deringing window
(:func:`relight_cli.sh.window_factors`); it returns them with the settings their
provenance records.  When no degree up to ``max_degree`` keeps the ``auto``
promise (irradiance within ``tolerance`` and ringing within ``max_negativity``),
:func:`fit` raises :class:`ProbePromiseBroken` (exit 1) instead of returning a probe
that breaks it.

    from relight_cli.builtin_envs import builtin_envmap
    from relight_cli.jobs.sh_probe import ProbeOptions, fit
    probe = fit(builtin_envmap("sky"), ProbeOptions(degree=2))
    probe.coefficients                      # [9, 3]
"""

from __future__ import annotations

from dataclasses import dataclass, field

from relight_cli.errors import DataError


@dataclass
class ProbeOptions:
    """``relight sh-probe``'s options, parsed: ``degree`` (None: the ``auto`` search with
    ``tolerance``, ``max_negativity``, ``max_degree``), ``ridge``; for a scene, the probe
    position ``at`` (X, Y, Z), the cube-face size and the cube cameras' near plane;
    ``window``: the deringing window (``relight_cli.sh.WINDOWS``) applied to the fit."""

    degree: int | None = None
    ridge: float = 0.0
    tolerance: float = 0.03
    max_negativity: float = 2.0
    max_degree: int = 8
    at: tuple | None = None
    face_size: int = 64
    near: float = 0.01
    window: str = "none"


class ProbePromiseBroken(DataError):
    """``--degree auto`` found no degree up to ``--max-degree`` whose irradiance error is
    within ``--tolerance`` and whose ringing is within ``--max-negativity``.  Exit 1."""


@dataclass
class Probe:
    """What :func:`fit` made: the radiance ``samples`` fitted, the ``degree`` and its
    ``coefficients``, the probe's ``extra`` record fields and the ``settings`` its
    provenance records (those of the sampling, then those of the degree search)."""

    samples: object
    degree: int
    coefficients: object
    extra: dict = field(default_factory=dict)
    settings: dict = field(default_factory=dict)


def fit(source, options: ProbeOptions, progress=None, log=None) -> Probe:
    """The probe of ``source``: an EnvMap, or a Gaussian scene seen from ``options.at``
    (``progress``: a wrapper of the cube faces' iterable, or None); ``log``
    (callable(str)) reports the ``auto`` degree search, or a fixed degree's ringing.

    Raises:
        ProbePromiseBroken: ``auto`` and no degree keeps the promise (nothing to write).
    """
    from relight_cli.gaussians import probe as PR
    from relight_cli.sh import apply_window

    settings, extra = {}, {}
    if options.at is not None:
        samples = PR.scene_samples(source, options.at, options.face_size, options.near,
                                   progress=progress)
        settings.update(at=list(options.at), face_size=options.face_size, near=options.near)
    else:
        samples = PR.env_samples(source)
    if options.degree is None:
        choice = PR.choose_degree(samples, options.tolerance, options.ridge, options.max_degree,
                                  options.max_negativity, window=options.window)
        degree, coefficients = choice.degree, choice.coefficients
        extra["degree_search"] = PR.degree_search_record(choice)
        settings.update(tolerance=options.tolerance, max_negativity=options.max_negativity,
                        max_degree=options.max_degree)
        for line in PR.degree_search_log(choice):
            if log is not None:
                log(line)
        if not choice.tolerance_met:
            raise ProbePromiseBroken(broken_promise(choice), hint=_hint(options))
    else:
        degree = options.degree
        coefficients = apply_window(PR.fit_probe(samples, degree, options.ridge), options.window)
        if log is not None:
            negativity, negative = PR.radiance_negativity(coefficients)
            log(f"degree {degree}: radiance negativity {negativity:.2f} (deepest dip / mean "
                f"radiance), negative over {negative:.0%} of the sphere, window {options.window}")
    if options.window != "none":
        extra["window"] = options.window
        settings.update(window=options.window)
    if options.at is not None:
        extra["face_size"] = options.face_size
    return Probe(samples, degree, coefficients, extra, settings)


def _hint(options) -> str:
    """The ways out of a broken ``auto`` promise, the window first unless it was tried."""
    ways = []
    if options.window == "none" or options.max_degree < 16:
        ways.append("a deringing window may keep both (--window hanning --max-degree 16)")
    ways.append("accept more error (--tolerance) or ringing (--max-negativity)")
    ways.append("take a fixed --degree N")
    return ", or ".join(ways)


def broken_promise(choice) -> str:
    """The one error line of an ``auto`` search whose best candidate misses the tolerance."""
    text = (f"--degree auto: no degree up to --max-degree {choice.max_degree} (window "
            f"{choice.window}) has irradiance error within --tolerance {choice.tolerance:g} and "
            f"radiance negativity within --max-negativity {choice.max_negativity:g}; closest: "
            f"degree {choice.degree}, error {choice.error:.2e}, negativity {choice.negativity:.2f}")
    better = [d for d in choice.errors if choice.errors[d] <= choice.tolerance]
    if better:
        d = min(better)
        text += (f"; degree {d} would reach error {choice.errors[d]:.2e} but rings to "
                 f"{choice.negativities[d]:.2f}")
    return text
