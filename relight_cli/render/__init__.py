"""Physically based hand rendering and the synthetic light stage.

Modules:
    gbuffer     embree primary rays from OpenCV cameras → per-sample hand/face/barycentrics/UV/
                position/normal/depth, stratified sub-pixel antialiasing
    appearance  UV-space materials: procedural skin albedo (variation, creases, nails) and
                roughness for the built-in hand, or user image maps
    brdf        the Disney/UE4 GGX lobe as elementwise terms (numpy and torch), the same lobe
                as :func:`relight_cli.features.ggx_weights`
    shading     Lambert + GGX; point lights (inverse square, grouped), env maps through
                bake-features' exact texel discretization, embree shadows, texture-space
                subsurface scattering, optional one-bounce interreflection; the
                differentiable torch path texture → image
    capture     the synthetic light stage (dome of cameras and LEDs, hand motion,
                time-multiplexed fully lit / grouped frames, resumable)
"""
