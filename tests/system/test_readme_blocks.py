"""Every README shell block runs as written after the blocks above it (issue 53, item 9):
each file a block reads is made by an earlier command (``-o``, ``--report``, ``--preview``,
``> file`` …), or is a ``builtin:``, a repository file or a ``../shared/data`` path.  The
blocks are parsed, never run (the heavy ones train models); options are checked against
each command's click definition, so a misspelt or removed option fails here too."""

from __future__ import annotations

import re
import shlex
import subprocess
from pathlib import Path

import click
import pytest

ROOT = Path(__file__).resolve().parents[2]

#: options whose value a command writes (a file, a pattern or a folder)
OUTPUTS = {"-o", "--output", "--report", "--preview", "--metrics-out", "--receivers-out",
           "--occluders-out", "--lights-out", "--video", "--per-vertex", "--features-out"}
#: what a path's name ends with when it is a file (else it is a folder)
FILE = re.compile(r"\.(npz|pt|json|jsonl|exr|hdr|ply|png|jpg|jpeg|webp|glb|gltf|txt|bvh)$")


def sh_blocks(text: str) -> list[tuple[str, str]]:
    """(heading, body) of every ```sh block, in order."""
    blocks, heading = [], ""
    for m in re.finditer(r"^(#+ [^\n]*)$|^```sh\n(.*?)^```", text, re.M | re.S):
        if m.group(1):
            heading = m.group(1)
        else:
            blocks.append((heading, m.group(2)))
    return blocks


def logical_lines(body: str) -> list[str]:
    """Continuations joined, ``$(which relight)`` as ``relight``, each ``for V in A B; do
    … done`` loop unrolled (the body once per value, ``$V`` substituted)."""
    lines = body.replace("\\\n", " ").replace("$(which relight)", "relight").splitlines()
    out, i = [], 0
    while i < len(lines):
        m = re.match(r"\s*for (\w+) in ([^;]+); do\s*$", lines[i])
        if not m:
            out.append(lines[i])
            i += 1
            continue
        end = next(j for j in range(i + 1, len(lines)) if lines[j].strip() == "done")
        for value in m.group(2).split():
            out += [line.replace("$" + m.group(1), value) for line in lines[i + 1:end]]
        i = end + 1
    return out


def segments(line: str) -> list[list[str]]:
    """The simple commands of one shell line: words split at ``| && || ; ( ) { }``,
    with a redirect's target kept as ``>`` + file."""
    lex = shlex.shlex(line, posix=True, punctuation_chars=True)
    lex.commenters = "#"
    lex.wordchars += "{}$:,@+%"
    words, out = list(lex), [[]]
    for w in words:
        if w in ("|", "&&", "||", ";", "(", ")", "&"):
            out.append([])
        else:
            out[-1].append(w)
    return [s for s in out if s]


def _command(name: str, rest: list[str]):
    """(click command, the words after its name) for ``relight NAME …`` (``metrics image``
    resolves to its subcommand)."""
    from relight_cli.cli import cli
    ctx = click.Context(cli)
    cmd = cli.get_command(ctx, name)
    assert cmd is not None, f"no command relight {name}"
    if isinstance(cmd, click.Group) and rest and not rest[0].startswith("-"):
        sub = cmd.get_command(click.Context(cmd, parent=ctx), rest[0])
        if sub is not None:
            return sub, rest[1:]
    return cmd, rest


def _options(cmd) -> dict:
    """option spelling → is a flag, for a click command; a mode dispatcher (``relight
    relight``) has its modes' options."""
    found, commands = {}, [cmd]
    if type(cmd).__name__ == "Dispatch":
        from relight_cli.commands.relight import _modules
        commands += [m.command for m in _modules()]
    for c in commands:
        for p in getattr(c, "params", []):
            if isinstance(p, click.Option):
                for o in p.opts + p.secondary_opts:
                    found[o] = p.is_flag or p.count
    return found


def _path_of(word: str) -> str | None:
    """The file or folder a word names, or None (``builtin:``, ``-``, numbers, sizes);
    a placement ``SOURCE:KEY=…`` names its SOURCE."""
    if word in ("-", "") or word.startswith("builtin:"):
        return None
    source = word.split(":")[0] if ":" in word and "=" in word else word
    if FILE.search(source) or source.endswith("/") or "/" in source:
        return source
    return None


class Made:
    """What the blocks above have made: files, patterns and folders (everything in a folder
    a command wrote counts as made; ``mkdir`` makes only the folder)."""

    def __init__(self):
        self.files, self.folders, self.dirs = set(), set(), set()

    def add(self, path: str):
        if FILE.search(path):
            self.files.add(_norm(path))
        else:
            self.folders.add(_norm(path))

    def has(self, path: str) -> bool:
        p = _norm(path)
        if p.startswith("../shared/"):
            return True
        if p in self.files or p in self.folders or p in self.dirs:
            return True
        if any(p.startswith(f + "/") for f in self.folders):
            return True
        if any(_pattern(f).fullmatch(p) for f in self.files if "{" in f or "*" in f):
            return True
        return (ROOT / p).exists() and _tracked(p)


def _norm(path: str) -> str:
    return path.rstrip("/").removeprefix("./")


def _pattern(path: str) -> re.Pattern:
    return re.compile(re.sub(r"\\\{[^}]*\\\}|\\\*", ".+", re.escape(path)))


def _tracked(path: str) -> bool:
    r = subprocess.run(["git", "ls-files", "--error-unmatch", path], cwd=ROOT,
                       capture_output=True)
    return r.returncode == 0


def check_blocks(text: str) -> list[str]:
    """The problems of the README's sh blocks, in order: '<heading>: <what>'."""
    problems, made = [], Made()
    for heading, body in sh_blocks(text):
        for line in logical_lines(body):
            for words in segments(line):
                while words and re.match(r"\w+=", words[0]):      # VAR=value prefixes
                    words = words[1:]
                if not words:
                    continue
                reads, writes = [], []
                # redirects: > FILE writes it, < FILE reads it
                rest = []
                it = iter(words)
                for w in it:
                    if w in (">", ">>"):
                        writes.append(next(it))
                    elif w == "<":
                        reads.append(next(it))
                    else:
                        rest.append(w)
                words = rest
                if words[0] == "mkdir":
                    made.dirs.update(_norm(w) for w in words[1:] if not w.startswith("-"))
                elif "relight" in words:
                    at = words.index("relight") + 1
                    while at < len(words) and words[at] in ("-q", "--quiet", "--debug"):
                        at += 1
                    cmd, args = _command(words[at], words[at + 1:])
                    flags = _options(cmd)
                    i = 0
                    while i < len(args):
                        w = args[i]
                        if w.startswith("-") and len(w) > 1 and not re.match(r"-[\d.]", w):
                            name, eq, value = w.partition("=")
                            if name not in flags:
                                problems.append(f"{heading}: relight {words[at]} has no "
                                                f"option {name}")
                                i += 1
                                continue
                            if not flags[name] and not eq:
                                i += 1
                                value = args[i] if i < len(args) else ""
                            path = _path_of(value) if not flags[name] else None
                            if path:
                                (writes if name in OUTPUTS else reads).append(path)
                        else:
                            path = _path_of(w)
                            if path:
                                reads.append(path)
                        i += 1
                for path in reads:
                    if not made.has(path):
                        problems.append(f"{heading}: {path} is made by no block above "
                                        f"({' '.join(words)[:80]})")
                for path in writes:
                    made.add(path)
    return problems


def test_a_block_reading_what_nothing_made_is_found():
    """The checker fails on the README of issue 53 (its Sequences block read hand.npz,
    linear.pt and cam.json) and on a misspelt option; it passes inputs made above."""
    text = ("# A\n```sh\nrelight camera --eye 0,0,1 --target 0,0,0 -o cam.json\n"
            "relight relight hand.npz builtin:studio --model linear --checkpoint linear.pt \\\n"
            "    --camera cam.json --frames all -o 'frames/f_{frame:04d}.exr'\n```\n"
            "# B\n```sh\nrelight envmap 'frames/f_0001.exr' --info -o - --colour x\n```\n")
    problems = check_blocks(text)
    assert any("hand.npz" in p for p in problems), problems
    assert any("linear.pt" in p for p in problems), problems
    assert not any("cam.json" in p for p in problems), problems
    assert not any("frames/f_0001.exr" in p for p in problems), problems   # the pattern
    assert any("has no option --colour" in p for p in problems), problems
    # a placement names its source; mkdir makes a folder, not its contents
    text = ("# C\n```sh\nmkdir -p out\nrelight relight 'out/a.ply:fit=0.3;on-floor' "
            "--probe p.json -o out/b.ply\n```\n")
    problems = check_blocks(text)
    assert any("out/a.ply" in p for p in problems) and any("p.json" in p for p in problems)


def test_readme_blocks_read_only_what_is_made_above():
    problems = check_blocks((ROOT / "README.md").read_text())
    assert not problems, "\n".join(problems)


@pytest.mark.parametrize("name", ["Sequences", "Presets", "Streams"])
def test_the_blocks_of_issue_53_are_sh_blocks(name):
    """The examples the issue named are blocks the checker reads (not prose)."""
    assert any(name in heading or name in body
               for heading, body in sh_blocks((ROOT / "README.md").read_text())), name
