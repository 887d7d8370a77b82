"""``make test``'s scheduling: the slow files conftest hands out first exist, and the
Makefile keeps xdist from reordering them."""

from __future__ import annotations

from conftest import ROOT, SLOW_FILES


def test_the_slow_files_exist_and_run_first():
    tests = ROOT / "tests"
    assert [name for name in SLOW_FILES if not (tests / name).is_file()] == []
    make = (ROOT / "Makefile").read_text()
    assert "--dist loadfile --no-loadscope-reorder" in make
