"""Generate man pages from the click metadata: ``python -m relight_cli.cli.manpage man/``.

One page per subcommand (``relight-<cmd>.1``) plus ``relight.1``.  No dates or
versions that change between runs, so a test can detect a stale ``man/``.
"""

from __future__ import annotations

import inspect
import sys
from pathlib import Path

import click


def _escape(text: str) -> str:
    text = text.replace("\\", "\\\\").replace("-", "\\-")
    lines = []
    for line in text.splitlines():
        if line.startswith((".", "'")):
            line = "\\&" + line
        lines.append(line)
    return "\n".join(lines)


def _paragraphs(help_text: str) -> str:
    """click help text → roff, keeping \\b (no-rewrap) blocks verbatim."""
    out = []
    blocks = inspect.cleandoc(help_text or "").split("\n\n")
    for block in blocks:
        if block.startswith("\b\n"):
            out.append(".nf\n" + _escape(block[2:]) + "\n.fi")
        else:
            out.append(".PP\n" + _escape(" ".join(block.split())))
    return "\n".join(out)


def _option_lines(command: click.Command, ctx: click.Context) -> list[str]:
    lines = []
    for param in command.get_params(ctx):
        if isinstance(param, click.Argument):
            continue
        record = param.get_help_record(ctx)
        if record is None:
            continue
        names, help_text = record
        lines.append(".TP\n\\fB" + _escape(names) + "\\fR\n" + _escape(help_text or ""))
    return lines


def render_page(words: list[str], command: click.Command, ctx: click.Context) -> str:
    """One man page for the command whose full name is ``" ".join(words)``."""
    full = " ".join(words)
    usage = " ".join(command.collect_usage_pieces(ctx))
    page = [f'.TH "{"-".join(words).upper()}" 1 "" "relight" "relight manual"',
            ".SH NAME", f"{_escape(full)} \\- {_escape(command.get_short_help_str(200))}",
            ".SH SYNOPSIS", f"\\fB{_escape(full)}\\fR {_escape(usage)}",
            ".SH DESCRIPTION", _paragraphs(command.help or "")]
    options = _option_lines(command, ctx)
    if options:
        page += [".SH OPTIONS", *options]
    for description, mode in getattr(command, "mode_commands", lambda: [])():
        # a dispatcher (relight relight): each mode's own synopsis, description, options
        mode_ctx = click.Context(mode, info_name=words[-1], parent=ctx.parent)
        page += [f".SH MODE: {_escape(description.upper())}",
                 f"\\fB{_escape(full)}\\fR {_escape(' '.join(mode.collect_usage_pieces(mode_ctx)))}",
                 _paragraphs(mode.help or ""), *_option_lines(mode, mode_ctx)]
    if isinstance(command, click.Group):
        page.append(".SH COMMANDS")
        for sub in command.list_commands(ctx):
            cmd = command.get_command(ctx, sub)
            page.append(f".TP\n\\fB{_escape(full)} {_escape(sub)}\\fR\n"
                        f"{_escape(cmd.get_short_help_str(200))}\n"
                        f"See \\fB{_escape('-'.join(words + [sub]))}\\fR(1).")
    page += [".SH EXIT STATUS",
             "0 success; 1 bad input data; 2 usage error"
             + ("; 3 a metrics regression found by \\fBrelight metrics compare\\fR."
                if len(words) == 1 or "metrics" in words else ".")]
    if len(words) == 1:
        page += [".SH FILES", "File formats are specified in the formats/ folder of the source tree."]
    else:
        page += [".SH SEE ALSO", f"\\fB{_escape('-'.join(words[:-1]))}\\fR(1)"]
    return "\n".join(page) + "\n"


def _walk(command: click.Command, ctx: click.Context, words: list[str]):
    yield words, command, ctx
    if isinstance(command, click.Group):
        for sub in command.list_commands(ctx):
            cmd = command.get_command(ctx, sub)
            yield from _walk(cmd, click.Context(cmd, info_name=sub, parent=ctx), words + [sub])


def generate() -> dict[str, str]:
    """{file name: page text} for relight and every registered (sub)command."""
    from relight_cli.cli import cli
    root = click.Context(cli, info_name="relight", **cli.context_settings)
    return {"-".join(words) + ".1": render_page(words, command, ctx)
            for words, command, ctx in _walk(cli, root, ["relight"])}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    folder = Path(argv[0] if argv else "man")
    folder.mkdir(parents=True, exist_ok=True)
    pages = generate()
    for stale in folder.glob("relight*.1"):
        if stale.name not in pages:
            stale.unlink()
    for name, text in pages.items():
        (folder / name).write_text(text, encoding="utf-8")
    print(f"wrote {len(pages)} man pages to {folder}/", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
