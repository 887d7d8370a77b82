"""relight_cli.jobs.bake_features called without click: its arrays equal what ``relight
bake-features`` writes, and env maps are checked before any frame."""

from __future__ import annotations

import json

import numpy as np
import pytest

from relight_cli.cli import inputs as I
from relight_cli.errors import DataError


def _cli(run_cli, *args):
    r = run_cli(*args)
    assert r.exit_code == 0, r.output
    return r


# ---------------------------------------------------------------- bake-features


def test_bake_job_equals_the_cli(run_cli, tmp_path):
    """Two env maps, per-vertex features, GGX and Phong: the job's texel maps, per-vertex
    arrays and provenance settings are what bake-features writes."""
    from relight_cli.features import FeatureSettings
    from relight_cli.formats.features_exr import read_features, read_vertex_features
    from relight_cli.jobs import bake_features as J

    _cli(run_cli, "bake-features", "builtin:right", "builtin:sky", "builtin:studio",
         "-o", tmp_path / "f_{env}.exr", "--per-vertex", tmp_path / "f_{env}.npz",
         "--res", "24x16", "--env-res", "8x4", "--specular", "both", "--shininess", "16",
         "--roughness", "0.4", "-q")
    envs = [I.load_envmap("builtin:sky"), I.load_envmap("builtin:studio")]
    options = J.BakeOptions(FeatureSettings(shininess=(16,), specular="both", roughness=0.4),
                            env_res=(4, 8), tex_res=(16, 24))
    [frame] = list(J.bake(I.load_hand("builtin:right"), [0], envs, options))
    assert frame.frame == 0 and frame.hands == ["right"] and frame.rays_traced > 0
    for k, name in enumerate(("sky", "studio")):
        written = read_features(str(tmp_path / f"f_{name}.exr"))
        assert set(written.layers) == set(frame.maps[k]) >= {"diffuse", "phong16", "ggx",
                                                              "visibility", "mask"}
        for layer, value in frame.maps[k].items():
            np.testing.assert_array_equal(written.layers[layer], value, err_msg=layer)
        vertex = read_vertex_features(str(tmp_path / f"f_{name}.npz"))
        for key, value in frame.vertex[k].items():     # written as float32 / int32
            np.testing.assert_array_equal(vertex[key], np.asarray(value).astype(vertex[key].dtype),
                                          err_msg=key)
        record = json.loads(str(vertex["provenance"]))
        assert record["settings"] == {**frame.settings, "roughness": "0.4"}
    # the two env maps light the hand differently: the comparison above can tell them apart
    assert not np.allclose(frame.maps[0]["diffuse"], frame.maps[1]["diffuse"])


def test_bake_job_checks_env_maps_before_any_frame():
    """A map whose features would overflow float32 is refused when the job is called
    (before a frame is baked), naming the map; a viewer and a roughness map are used."""
    from relight_cli.features import FeatureSettings
    from relight_cli.jobs import bake_features as J

    bright = I.load_envmap("builtin:uniform")
    bright.radiance = np.full_like(bright.radiance, 3e36)
    options = J.BakeOptions(FeatureSettings(shininess=(), specular="ggx"), env_res=(4, 8),
                            tex_res=(8, 8))
    with pytest.raises(DataError, match="too bright") as err:
        J.bake(I.load_hand("builtin:right"), [0], [bright], options, names=["sun.exr"])
    assert "sun.exr" in str(err.value)
    # a constant roughness map equals the scalar; the viewer is the one given
    env = [I.load_envmap("builtin:studio")]
    eye = np.array([0.1, 0.3, 0.5])
    scalar = J.BakeOptions(FeatureSettings(shininess=(), specular="ggx", roughness=0.25),
                           env_res=(4, 8), tex_res=(8, 8), viewer=eye)
    mapped = J.BakeOptions(FeatureSettings(shininess=(), specular="ggx"), env_res=(4, 8),
                           tex_res=(8, 8), viewer=eye, roughness_map=np.full((4, 4), 0.25))
    hand = I.load_hand("builtin:right")
    [a], [b] = J.bake(hand, [0], env, scalar), J.bake(hand, [0], env, mapped)
    np.testing.assert_array_equal(a.viewer, eye)
    assert a.settings["view"] == [0.1, 0.3, 0.5] and b.settings["roughness"] == "map"
    np.testing.assert_allclose(a.vertex[0]["ggx"], b.vertex[0]["ggx"], rtol=1e-12)
    assert a.vertex[0]["ggx"].max() > 0
