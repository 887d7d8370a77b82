"""Quality metrics: images, shadow mattes, lighting consistency of Gaussian avatars,
and the comparison of metric records for regression gates.

Modules (plain arrays in, plain dicts out; no paths, no click):

* :mod:`.image` — MSE, PSNR, SSIM (scikit-image), MAE, per channel and overall, masked.
* :mod:`.shadow` — the DGSM paper's SAE, SM-IoU and boundary F-measure.
* :mod:`.lighting` — PAA-Y, APF-Y and NCM-ab for a Gaussian avatar in a Gaussian scene.
* :mod:`.batch` — pairing many files and aggregating rows.
* :mod:`.compare` — regression check of a metrics record against a baseline.
* :mod:`.lpips` — optional LPIPS with user-supplied weights.
"""
