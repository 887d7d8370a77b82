"""Extract and run the README's example pipeline, exactly as written.

The lines between ``<!-- example:begin -->`` and ``<!-- example:end -->`` in
README.md (inside a ```sh fence) are the pipeline a newcomer copies; ``make
example`` runs them with this script, and tests/system/test_readme_example.py runs it
in a scratch copy so the README cannot drift from what works.

    python tools/readme_example.py [--print] [--cwd DIR] [README.md]

Lines ending in a backslash are joined; comment-only lines are kept (bash ignores
them).  They run in one ``bash -euo pipefail`` with the venv's ``relight`` first
on PATH, from the repository root (or ``--cwd``), so ``../shared/data`` is the
shared data folder next to the clone.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

BEGIN, END = "<!-- example:begin -->", "<!-- example:end -->"


def example_script(readme: str) -> str:
    """The shell text of the README's example block (fences removed)."""
    text = Path(readme).read_text(encoding="utf-8")
    if BEGIN not in text or END not in text:
        raise SystemExit(f"{readme}: no {BEGIN} … {END} block")
    block = text.split(BEGIN, 1)[1].split(END, 1)[0]
    lines = [line for line in block.strip().splitlines() if not line.startswith("```")]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("readme", nargs="?", default=str(Path(__file__).parents[1] / "README.md"))
    parser.add_argument("--print", action="store_true", help="print the script, run nothing")
    parser.add_argument("--cwd", default=None, help="run there (default: the repository root)")
    args = parser.parse_args(argv)
    script = example_script(args.readme)
    if args.print:
        sys.stdout.write(script)
        return 0
    root = Path(__file__).resolve().parents[1]
    env = dict(os.environ)
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    return subprocess.run(["bash", "-euo", "pipefail", "-c", script],
                          cwd=args.cwd or root, env=env).returncode


if __name__ == "__main__":
    sys.exit(main())
