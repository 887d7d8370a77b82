"""The one shadow of scene receivers: what ``relight`` delivers and ``dgsm-build --preview`` shows.

A receiver's colour c becomes c · [(1 − s) + s · Σ_l w_l T_l / Σ_l w_l] per channel
(:func:`relight_cli.gaussians.transfer.shadow_factor`), T_l the DGSM transmittance of
light l at the receiver, w_l the light weights and s the shadow strength
(``--shadow-strength``):

* a number in [0, 1]: the same s everywhere (1, the paper's, makes a full shadow black);
* ``auto`` (``relight``'s default): per receiver and channel the direct share
  s = E_d / (E_d + E_probe) of the lights' irradiance against the SH probe's
  (:func:`relight_cli.gaussians.transfer.direct_share`), normals the receivers'
  shortest axes turned towards the lights.  It needs the probe that lights the
  scene: without one no preview can show it.

The default weights follow the strength as in ``relight``: ``irradiance`` with auto,
``intensity`` otherwise (:func:`default_light_weights`).  Both ``relight relight``
(relight_cli.jobs.relight_gaussians) and the preview sheet of ``dgsm-build``
(relight_cli.preview.dgsm_sheet) call :func:`receiver_shadow`, so the preview shows
the shadow the render will have for the same strength, probe and weights.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class ReceiverShadow:
    """What :func:`receiver_shadow` returns.

    Attributes:
        factor: [M, 3] the multiplier of each receiver's colour (1: unshadowed).
        strength: the s used: a float, or [M, 3] per receiver and channel (auto).
        light_weights: the weights mode used (``intensity``, ``irradiance``, ``equal``).
    """

    factor: np.ndarray
    strength: object
    light_weights: str

    def describe(self) -> str:
        """``1``, ``0.7`` or ``auto (median 0.71)``: the strength for labels and logs."""
        if np.ndim(self.strength) == 0:
            return f"{float(self.strength):g}"
        return f"auto (median {float(np.median(self.strength)):.2f})"


def default_light_weights(strength) -> str:
    """``relight``'s default weights for this strength: irradiance for auto, else intensity."""
    return "irradiance" if strength == "auto" else "intensity"


def receiver_shadow(shadow_map, receivers, transmittance, strength="auto",
                    light_weights: str | None = None,
                    probe_coefficients=None) -> ReceiverShadow:
    """The shadow factor of ``receivers`` (module doc).

    Args:
        shadow_map: the DGSM (its lights, intensities and colours weigh the lights).
        receivers: the scene Gaussians, M of them.
        transmittance: [L, M] each light's T at the receivers (dgsm.sample_transmittance).
        strength: a number in [0, 1] or ``"auto"``.
        light_weights: ``intensity``, ``irradiance`` or ``equal``, as it can run with
            this map (relight_cli.gaussians.transfer.effective_light_weights); None: the
            default for the strength.
        probe_coefficients: [(d+1)², 3] SH radiance of the scene's probe (auto only).
    Raises:
        ValueError: auto without a probe, or a strength outside [0, 1].
    """
    from relight_cli.gaussians import transfer as TF
    mode = light_weights or TF.effective_light_weights(default_light_weights(strength),
                                                       shadow_map.intensities)
    normals = None
    if strength == "auto":
        if probe_coefficients is None:
            raise ValueError("shadow strength auto weighs the lights against the scene's "
                             "probe: give the probe")
        normals = TF.facing_lights(receivers.means, TF.estimate_normals(receivers, "axis"),
                                   shadow_map.lights)
        e_direct = TF.direct_irradiance(shadow_map.intensities, shadow_map.colors,
                                        shadow_map.lights, receivers.means,
                                        normals).sum(axis=0)
        strength = TF.direct_share(e_direct, probe_coefficients, normals)
    elif not 0.0 <= float(strength) <= 1.0:
        raise ValueError(f"shadow strength must be in [0, 1] or auto, got {strength}")
    else:
        strength = float(strength)
    weights = TF.dgsm_light_weights(mode, shadow_map, receivers, normals)
    factor = TF.shadow_factor(transmittance, weights, strength)
    if factor.ndim == 1:
        factor = np.repeat(factor[:, None], 3, axis=1)
    return ReceiverShadow(factor, strength, mode)
