"""The relight/gaussian-sequence index (formats/gaussian_sequence.py) and the sequence
sources built on it (relight_cli/gaussians/sequence.py): fields checked, units and up
axis applied, '{frame}' patterns found on disk, the real PlayCanvas flipbook read."""

from __future__ import annotations

import json

import numpy as np
import pytest

from relight_cli.errors import DataError, UsageProblem
from relight_cli.formats.gaussian_sequence import read_sequence_index
from relight_cli.formats.gaussians_ply import Gaussians, rgb_to_sh_dc, write_gaussians
from relight_cli.gaussians.sequence import GaussianSource, pattern_frames


def _splats(centre, n=20):
    return Gaussians(np.tile(np.asarray(centre, float), (n, 1)) + np.arange(n)[:, None] * 0.01,
                     np.full((n, 3), 0.01), np.tile([1.0, 0, 0, 0], (n, 1)), np.full(n, 0.9),
                     rgb_to_sh_dc(np.full((n, 3), 0.5))[:, None, :], 0)


def _index(tmp_path, **fields):
    obj = {"format": "relight/gaussian-sequence", "version": 1,
           "frames": "f/{frame:02d}.ply", "count": 2}
    obj.update(fields)
    path = tmp_path / "seq.json"
    path.write_text(json.dumps(obj))
    return path


@pytest.fixture
def frames(tmp_path):
    (tmp_path / "f").mkdir()
    for k in range(2):
        write_gaussians(str(tmp_path / "f" / f"{k:02d}.ply"), _splats([0.0, 0.0, 1.0 + k]))
    return tmp_path


def test_index_reads_and_its_units_and_up_axis_apply(frames):
    index = read_sequence_index(str(_index(frames, fps=30, units="cm", up="+z")))
    assert index.frames == [0, 1] and index.fps == 30.0 and index.pattern.endswith("f/{frame:02d}.ply")
    source = GaussianSource(str(frames / "seq.json"))
    g = source.frame(1)
    # +Z up, centimetres: the file's (0, 0, 2) is 2 cm up (+Y) in the world
    np.testing.assert_allclose(g.means[0], [0.0, 0.02, 0.0], atol=1e-12)
    assert source.fps == 30.0 and source.moves


@pytest.mark.parametrize("fields,words", [
    ({"count": 0}, "'count'"),
    ({"count": 2.5}, "'count'"),
    ({"first": -1}, "'first'"),
    ({"frames": "f/00.ply"}, "{frame}"),
    ({"frames": "f/{frame!r}.ply"}, "{frame"),
    ({"frames": "f/{frame}.exr"}, "PLY"),
    ({"fps": 0}, "'fps'"),
    ({"fps": "24"}, "'fps'"),
    ({"units": "inch"}, "'units'"),
    ({"up": "y"}, "'up'"),
    ({"colour_space": "acescg"}, "'colour_space'"),
    ({"same_topology": "yes"}, "'same_topology'"),
    ({"format": "relight/lights"}, "not a relight/gaussian-sequence"),
    ({"version": 2}, "newer"),
])
def test_index_refusals_name_the_file(frames, fields, words):
    path = _index(frames, **fields)
    with pytest.raises(DataError) as info:
        read_sequence_index(str(path))
    assert words in info.value.message and info.value.path == str(path)


def test_a_frame_the_index_declares_but_the_folder_lacks_is_named(frames):
    source = GaussianSource(str(_index(frames, count=3)))
    with pytest.raises(DataError) as info:
        source.frame(2)
    assert info.value.path.endswith("f/02.ply")


def test_pattern_frames_found_on_disk_and_gaps_named(tmp_path):
    for k in (3, 4, 5):
        write_gaussians(str(tmp_path / f"a_{k:04d}.ply"), _splats([0, 0, 0]))
    (tmp_path / "a_12345.ply").write_text("not a frame of a 4-digit pattern? it is: 12345")
    (tmp_path / "b_0003.ply").write_text("another pattern")
    with pytest.raises(DataError) as info:   # 12345 fits {frame:04d}: a gap from 6 on
        pattern_frames(str(tmp_path / "a_{frame:04d}.ply"), "spec")
    assert info.value.path.endswith("a_0006.ply")
    (tmp_path / "a_12345.ply").unlink()
    assert pattern_frames(str(tmp_path / "a_{frame:04d}.ply"), "spec") == [3, 4, 5]
    # unpadded: a_3.ply … matches {frame}, not a_0003.ply (its name for 3 is a_3.ply)
    with pytest.raises(DataError, match="no file matches"):
        pattern_frames(str(tmp_path / "a_{frame}.ply"), "spec")
    with pytest.raises(UsageProblem):
        pattern_frames(str(tmp_path / "a_{frame:x}.ply"), "spec")


def test_real_flipbook_sequence_reads_as_one_avatar(shared):
    """PlayCanvas' flipbook monkey (5 per-frame PLYs written by another tool) is one moving
    avatar: 5 frames, the same count per frame, one placement for all of them (it grows
    ~2.3x across the clip, so fitting per frame would hide that)."""
    folder = shared("gaussians", "sequences", "flipbook-monkey")
    from relight_cli.gaussians.placement import robust_bounds
    source = GaussianSource(str(folder / "frame_{frame:04d}.ply") + ":fit=0.3", same_topology=True)
    assert source.frames == [0, 1, 2, 3, 4]
    sizes = []
    for k in source.frames:
        lo, hi = robust_bounds(source.frame(k))
        sizes.append(float((hi - lo).max()))
    assert sizes[0] == pytest.approx(0.3, rel=1e-9)
    assert sizes[-1] / sizes[0] > 1.8
