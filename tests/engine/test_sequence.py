"""relight_cli.sequence: the one frame grammar (--frame/--frames, {frame}/{env} patterns)."""

from __future__ import annotations

import pytest

from relight_cli.errors import UsageProblem
from relight_cli.sequence import (OutputPattern, check_frame, parse_frames, plan_outputs,
                                  select, sequence_pattern, write_sequence)


def test_frames_select_as_a_python_slice():
    assert parse_frames("all").resolve(4) == [0, 1, 2, 3]
    assert parse_frames("1:3").resolve(4) == [1, 2]
    assert parse_frames("0:10:3").resolve(8) == [0, 3, 6]
    assert parse_frames(":2").resolve(5) == [0, 1] and parse_frames("3:").resolve(5) == [3, 4]
    assert parse_frames("0:300:10").as_slice() == slice(0, 300, 10)
    assert parse_frames("all").as_slice() == slice(None)
    # every grammar error is a usage error (exit 2) naming the option
    for bad, message in (("a:b", "takes integers"), ("1", "takes all, A:B"),
                         ("1:2:0", "step must be ≥ 1"), ("-1:2", "≥ 0"), ("", "takes all"),
                         ("1:2:3:4", "takes all")):
        with pytest.raises(UsageProblem, match=message):
            parse_frames(bad)
    with pytest.raises(UsageProblem, match="selects no frame of a recording of 5"):
        parse_frames("5:9").resolve(5)


def test_a_count_where_a_selection_goes_names_the_count_option():
    with pytest.raises(UsageProblem, match="a number of frames is --n-frames 10"):
        parse_frames("10", count_option="--n-frames")


def test_one_frame_or_a_sequence():
    assert select(None, None, 3, "h.npz") == [0]
    assert select(2, None, 3, "h.npz") == [2]
    assert select(None, "all", 3, "h.npz") == [0, 1, 2]
    with pytest.raises(UsageProblem, match="--frame 3 is out of range: h.npz has 3"):
        select(3, None, 3, "h.npz")
    with pytest.raises(UsageProblem, match="give one of them"):
        check_frame(1, "0:2")
    with pytest.raises(UsageProblem, match="--frame must be ≥ 0"):
        check_frame(-1, None)


@pytest.mark.parametrize("pattern", ["{frame[0]}.exr", "{frame.real}.exr", "{frame!r}.exr",
                                     "{frame:c}.exr", "{frame:x}.exr", "{frame:s}.exr",
                                     "{other}.exr", "{}.exr", "{0}.exr", "{frame:{env}}.exr",
                                     "{frame", "frame}}{"])
def test_patterns_hold_only_the_fields_as_names(pattern):
    """No indexing, attributes, conversions, control bytes (``{frame:c}`` of 0 is NUL) or
    other fields: a pattern names files, it does not run code on its values."""
    with pytest.raises(UsageProblem, match="may only use"):
        OutputPattern(pattern, fields=("frame", "env"))


def test_patterns_format_frames_and_envs():
    p = OutputPattern("out/{env}_{frame:04d}.exr")
    assert p.format(7, "sky") == "out/sky_0007.exr"
    assert OutputPattern("{frame:5}.exr").format(3) == "    3.exr"
    assert OutputPattern("{frame:d}-{env:8s}").format(1, "a") == "1-a       "
    with pytest.raises(UsageProblem, match=r"may only use \{frame\}"):
        OutputPattern("{env}.exr", fields=("frame",))


def test_sequence_patterns_name_each_frame():
    assert sequence_pattern(None, "--preview") is None
    with pytest.raises(UsageProblem, match="not stdout"):
        sequence_pattern("-", "-o")
    with pytest.raises(UsageProblem, match="must hold {frame}"):
        sequence_pattern("out.exr", "-o")
    assert sequence_pattern("out/{frame:03d}.png", "--preview").format(5) == "out/005.png"


def test_plan_outputs_refuses_two_targets_on_one_file():
    plan = plan_outputs({"-o": OutputPattern("f{frame}_{env}.exr"), "--preview": None},
                        [0, 2], ("sky", "studio"))
    assert list(plan) == [(0, "sky"), (0, "studio"), (2, "sky"), (2, "studio")]
    assert plan[2, "studio"] == {"-o": "f2_studio.exr", "--preview": None}
    with pytest.raises(UsageProblem, match="two env maps the same file"):
        plan_outputs({"-o": OutputPattern("f{frame}.exr")}, [0], ("sky", "studio"))
    with pytest.raises(UsageProblem, match="two frames the same file"):
        plan_outputs({"-o": OutputPattern("f{frame:1d}{env}.exr")}, [1, 11],
                     ("1", ""))


def test_write_sequence_writes_in_order_as_frames_come():
    seen = []

    def frames():
        for k in range(3):
            seen.append(("made", k))
            yield k

    def write(k):
        seen.append(("written", k))
        return k * 10
    assert write_sequence(frames(), write, 3, "test", quiet=True) == [0, 10, 20]
    # a frame is written before the next is made (a sequence never holds every frame)
    assert seen == [("made", 0), ("written", 0), ("made", 1), ("written", 1), ("made", 2),
                    ("written", 2)]
