"""relight_cli.jobs.relight_hand called without click: a frame equals the CLI's image."""

from __future__ import annotations

import numpy as np


def _same_as_written(array, written):
    """Equal at the file's precision (PLY float32 read back as float64; EXR half/float)."""
    written = np.asarray(written)
    dtype = np.float32 if written.dtype == np.float64 else written.dtype
    np.testing.assert_array_equal(written.astype(dtype), np.asarray(array).astype(dtype))


def test_hand_job_frame_is_the_cli_image(run_cli, tmp_path):
    """relight_hand.physical on a built-in hand, a tiny view: the EXR's channels."""
    from relight_cli.builtin_envs import builtin_envmap
    from relight_cli.formats.exr import read_exr
    from relight_cli.hand.model import builtin_hand
    from relight_cli.hand.scene import preview_camera
    from relight_cli.jobs import relight_hand as J
    from relight_cli.render import appearance as A
    from relight_cli.render.shading import RenderSettings
    data = builtin_hand("right", "relaxed")
    settings = RenderSettings(tex_res=16, aa=1, shadows=True, specular=True, sss=False,
                              sss_scale=1.0, env_res=(4, 8), bounce=False)
    materials = A.hand_materials(data, "fine", 256, 0, None, None)
    [frame] = J.physical(data, [0], lambda f, meshes: preview_camera(meshes, 12, 10), materials,
                         settings, None, builtin_envmap("builtin:sky"), (0.0, 0.0, 0.0),
                         "fine", ("depth",))
    r = run_cli("relight", "builtin:right", "builtin:sky", "--size", "12x10", "--tex-res", "16",
                "--aa", "1", "--no-sss", "--env-res", "8x4", "--aov", "depth", "-q",
                "-o", tmp_path / "hand.exr")
    assert r.exit_code == 0, r.output
    image = read_exr(str(tmp_path / "hand.exr"))
    assert set(image.channels) == set(frame.channels) == {"R", "G", "B", "A", "depth.Z"}
    for name, values in frame.channels.items():
        _same_as_written(values, image.channels[name])
    assert frame.channels["A"].max() > 0.5       # the hand is in view
