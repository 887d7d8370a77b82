"""One-line error checks shared by test files of one command (tests/commands/test_fit_geometry.py,
tests/formats/test_leap.py)."""

from __future__ import annotations


def _one_error(result, code, needle=None, command="fit-geometry"):
    """One line on stderr, the exit code, no traceback."""
    text = result.stderr if hasattr(result, "stderr") and not hasattr(result, "exit_code") \
        else result.output
    got = result.exit_code if hasattr(result, "exit_code") else result.returncode
    assert got == code, text
    lines = [line for line in text.strip().splitlines() if line.strip()]
    assert len(lines) == 1, text
    assert lines[0].startswith(f"relight {command}: error:"), text
    assert "Traceback" not in text
    if needle:
        assert needle in lines[0], text
