"""The input loaders moved to :mod:`relight_cli.inputs` (the engine), so that no
command imports another.  This re-export only keeps a study process started before
the move (benchmarks/study_hands.py imports it lazily) running; nothing in the tree
imports it, and it goes once no such process is left."""

from __future__ import annotations

from relight_cli.inputs import load_envmap  # noqa: F401
