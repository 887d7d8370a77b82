"""hand.npz: round trips, two hands, and the reader's validation of every field."""

from __future__ import annotations

import json

import numpy as np
import pytest

from relight_cli.errors import DataError
from relight_cli.formats.hand_npz import FORMAT, VERSION, read_hand, read_provenance, to_arrays, write_hand
from relight_cli.hand.model import builtin_hand
from relight_cli.hand.scene import posed_meshes, two_hands


@pytest.fixture(scope="module")
def pair():
    return two_hands(builtin_hand())


def _write_arrays(path, arrays):
    with open(path, "wb") as f:
        np.savez(f, **arrays)


def test_round_trip_two_hands_exact(tmp_path, pair):
    path = tmp_path / "hand.npz"
    write_hand(str(path), pair, {"format": FORMAT, "note": "test"})
    back = read_hand(str(path))
    assert back.joint_names == pair.joint_names
    assert [h.name for h in back.hands] == ["right", "left"]
    assert [h.mirror for h in back.hands] == [False, True]
    for a, b in zip(posed_meshes(back, 0, "fine"), posed_meshes(pair, 0, "fine")):
        np.testing.assert_array_equal(a.vertices, b.vertices)
        np.testing.assert_array_equal(a.faces_uv, b.faces_uv)
    np.testing.assert_array_equal(back.coarse.labels, pair.coarse.labels)
    assert back.label_names == pair.label_names
    assert read_provenance(str(path))["note"] == "test"
    with np.load(path, allow_pickle=False) as z:
        assert str(z["format"]) == "relight/hand" and int(z["version"]) == 1
        assert z["poses"].shape == (1, 25, 3) and z["other_poses"].shape == (1, 1, 25, 3)
        assert z["coarse_weights"].shape == (len(pair.coarse.vertices), 25)


def test_single_hand_minimal_file_reads_with_defaults(tmp_path):
    """Only the issue's required keys: optional two-hand fields default sensibly."""
    h = builtin_hand()
    arrays = to_arrays(h)
    for key in ("hand_names", "hand_mirror", "hand_roots", "side", "bone_scales", "label_names",
                "coarse_labels", "fine_labels", "provenance"):
        arrays.pop(key)
    path = tmp_path / "min.npz"
    _write_arrays(path, arrays)
    back = read_hand(str(path))
    assert len(back.hands) == 1 and back.side == "right"
    np.testing.assert_array_equal(back.hands[0].root, np.eye(4))


def test_write_is_atomic_on_invalid_data(tmp_path):
    h = builtin_hand()
    h.coarse.weights = h.coarse.weights * 2
    path = tmp_path / "bad.npz"
    with pytest.raises(DataError, match="sums to"):
        write_hand(str(path), h)
    assert not path.exists() and not list(tmp_path.iterdir())


def _corrupt(key, value):
    arrays = to_arrays(builtin_hand())
    if value is None:
        arrays.pop(key)
    else:
        arrays[key] = value(arrays[key]) if callable(value) else value
    return arrays


BAD = [
    ("format", np.array("something/else"), "not a relight/hand file"),
    ("version", np.array(2), "unsupported relight/hand version 2"),
    ("poses", None, "missing array 'poses'"),
    ("rest_joints", lambda a: a[:20], "'rest_joints' has shape"),
    ("poses", lambda a: np.where(np.arange(3) == 1, np.nan, a), "'poses' holds NaN"),
    ("coarse_faces", lambda a: a + 10**6, "indexes vertices out of range"),
    ("coarse_faces", lambda a: a.astype(np.float64), "must be an integer array"),
    ("coarse_faces_uv", lambda a: a[:-1], "'coarse_faces_uv' has shape"),
    ("fine_uv", lambda a: a + 1.5, "outside [0, 1]"),
    ("coarse_weights", lambda a: -a, "negative"),
    ("coarse_weights", lambda a: a * 0.5, "sums to 0.5"),
    ("parents", lambda a: np.where(np.arange(25) == 3, 7, a), "after its parent"),
    ("parents", lambda a: np.where(np.arange(25) == 0, 0, a), "must be -1"),
    ("translations", lambda a: np.zeros((3, 3)), "'translations' has shape"),
    ("hand_roots", lambda a: a * 2, "not a rigid transform"),
    ("joint_names", lambda a: a.astype(bytes), "must be a string array"),
    ("coarse_labels", lambda a: a + 50, "exceeds"),
    ("bone_scales", lambda a: -a, "positive"),
]


@pytest.mark.parametrize("key,value,message", BAD, ids=[f"{k}-{m[:20]}" for k, _, m in BAD])
def test_reader_rejects_bad_fields(tmp_path, key, value, message):
    path = tmp_path / "bad.npz"
    _write_arrays(path, _corrupt(key, value))
    with pytest.raises(DataError) as exc:
        read_hand(str(path))
    assert message in str(exc.value)
    assert str(path) in str(exc.value)  # names the file


def test_reader_rejects_non_npz_and_pickles(tmp_path):
    text = tmp_path / "text.npz"
    text.write_text("hello")
    with pytest.raises(DataError, match="not a readable npz"):
        read_hand(str(text))
    with pytest.raises(DataError, match="no such file"):
        read_hand(str(tmp_path / "missing.npz"))
    arrays = to_arrays(builtin_hand())
    arrays["joint_names"] = np.array(list(arrays["joint_names"]), dtype=object)
    path = tmp_path / "pickle.npz"
    with open(path, "wb") as f:
        np.savez(f, **arrays)
    with pytest.raises(DataError, match="pickled"):
        read_hand(str(path))


def test_other_hands_need_same_frame_count(tmp_path, pair):
    import copy

    bad = copy.deepcopy(pair)
    bad.hands[1].poses = np.zeros((3, 25, 3))
    bad.hands[1].translations = np.zeros((3, 3))
    with pytest.raises(DataError, match="same number of frames"):
        write_hand(str(tmp_path / "x.npz"), bad)


def test_provenance_is_json(tmp_path):
    from relight_cli.provenance import provenance

    h = builtin_hand()
    write_hand(str(tmp_path / "h.npz"), h, provenance(FORMAT, VERSION, {}, {"pose": "relaxed"}))
    with np.load(tmp_path / "h.npz") as z:
        record = json.loads(str(z["provenance"]))
    assert record["format"] == FORMAT and record["settings"]["pose"] == "relaxed"


def test_mean_texture_round_trips_and_bad_ones_are_refused(tmp_path):
    """The optional subject texture (relight personalize): exact round trip; a file without
    it reads as None; a non-square, non-power-of-two, negative or NaN one is refused."""
    hand = builtin_hand()
    assert to_arrays(hand).get("mean_texture") is None
    t = np.random.default_rng(0).uniform(0, 0.3, (3, 16, 16)).astype(np.float32)
    hand.mean_texture = t
    write_hand(str(tmp_path / "h.npz"), hand)
    np.testing.assert_array_equal(read_hand(str(tmp_path / "h.npz")).mean_texture, t)
    for bad, message in ((np.zeros((3, 16, 8)), "power of two"),
                         (np.zeros((3, 12, 12)), "power of two"),
                         (-t, "negative|\\[0, 1e6\\]"), (t * np.nan, "NaN")):
        arrays = dict(to_arrays(builtin_hand()))
        arrays["mean_texture"] = bad.astype(np.float32)
        np.savez(tmp_path / "bad.npz", **arrays)
        with pytest.raises(DataError, match=message):
            read_hand(str(tmp_path / "bad.npz"))
