"""The learned half of relight: data from a capture folder, models, losses, training.

Modules:
    config      model/training configurations, the ``tiny`` and ``paper`` presets
    geometry    texel G-buffers of posed meshes: tangent frames from UV derivatives,
                per-light local light/view directions (RelightableHands Eq. 3–4),
                falloff and ray-traced visibility
    data        a relight/capture folder as training samples (frame × camera), splits,
                per-pose caches, the capture's mean texture
    models      the pose encoder J(θ), the teacher U-Net (App. A.1, Eq. 10) and the GGX
                baseline (App. B, Eq. 12)
    losses      masked MSE, the optional VGG perceptual loss (local weights only), L_neg (Eq. 6)
    train       the training loop: Adam, seeded and deterministic on CPU, DDP under torchrun,
                periodic validation, exact resume
    teacher     rendering with a trained teacher: point lights (near or far) and env maps
                as sums over their directions (linearity of light transport)
    shading_features  URHand's physically based features in torch (supp. 8.2, Eq. 10–15):
                refined normals from a displacement map, diffuse and GGX specular with
                visibility for point lights and env-map directions
    linear      URHand's model (Sec. 4): physical branch F_G, non-linear branch F_nl,
                bias-free light path F_l (Eq. 5–6), ``LinearConfig`` and its presets
    linear_train  its training loop (Eq. 7, 9, 17) and one-pass rendering
    adversarial   the lighting-aware patch discriminator and hinge losses (Eq. 8)

Our hands are meshes with one UV layout, not MVP primitives, so the teacher follows
URHand's mesh-based re-implementation of RelightableHands (URHand supp. 10.1, Eq. 16):
S = 1 (one texel per primitive voxel) and the per-primitive rotation R_k of Eq. 3–4 is
each texel's tangent frame.
"""
