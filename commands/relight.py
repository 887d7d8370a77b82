"""``relight relight IN …``: relight IN under new lighting — one command per kind of IN.

IN decides the mode, and each mode is its own command module with exactly its own options
(as COLMAP's variants are separate commands and nerfstudio's exporters one dataclass
each); this module only dispatches:

    IN                                       mode                             module
    CAPTURE/ (a relight/capture folder)      score learned models on it       score_capture
    AVATAR.ply [ENV], a mesh, builtin:hand|  Gaussians relit by an SH probe   relight_gaussians
      room|sphere (a hand .npz with --probe, (--probe, or fitted from ENV)
      --dgsm, --receivers, --object or       (+ DGSM shadows)
      --shadow-matte: its posed hand)
    HAND.npz, builtin:right|left|two[:POSE]  a hand rendered (physical or     relight_hand
                                             a learned model)

``relight relight IN --help`` shows the options of IN's mode.  An option of another mode
is a usage error naming the mode it belongs to, found from the modes' own click
parameters (no table of which option goes where).
"""

from __future__ import annotations

import importlib

import click

#: The modes, in the order IN is tried: module (under relight_cli.commands).
MODES = ("score_capture", "relight_gaussians", "relight_hand")


def _modules():
    return [importlib.import_module(f"relight_cli.commands.{name}") for name in MODES]


class Dispatch(click.Command):
    """``relight relight``: finds IN among the arguments, picks the mode that accepts it,
    refuses other modes' options, and runs the mode's command in this context's place."""

    def parse_args(self, ctx, args):
        ctx.meta["relight.relight.args"] = list(args)
        return []

    def invoke(self, ctx):
        from relight_cli.errors import UsageProblem
        args = ctx.meta.pop("relight.relight.args", [])
        modules = _modules()
        options = {m: _options(m.command) for m in modules}
        positionals, given = _scan(args, options)
        if not positionals:
            if any(a in ("-h", "--help") for a in args):
                click.echo(ctx.get_help(), color=ctx.color)
                ctx.exit()
            raise click.UsageError("Missing argument 'IN'.", ctx)
        source = positionals[0]
        names = {options_name for m in modules for flag, (options_name, _) in options[m].items()
                 if flag in given}
        mode = next((m for m in modules if m.accepts(source, names)), None)
        if mode is None:
            raise UsageProblem("IN must be a Gaussians .ply (or a mesh, builtin:hand|room|"
                               "sphere) or a hand .npz (or builtin:right|left|two); cannot "
                               "tell what this is", source)
        _refuse_foreign(mode, modules, options, given, positionals)
        sub = mode.command.make_context(ctx.info_name, list(args), parent=ctx.parent)
        with sub:
            return mode.command.invoke(sub)

    def mode_commands(self) -> list:
        """[(what IN is, the mode's command)] in dispatch order (the man page's modes)."""
        return [(m.DESCRIPTION, m.command) for m in _modules()]

    def format_help_text(self, ctx, formatter):
        super().format_help_text(ctx, formatter)
        with formatter.section("Modes (relight relight IN --help shows a mode's options)"):
            formatter.write_dl([(m.DESCRIPTION, m.command.get_short_help_str(80))
                                for m in _modules()])

    def format_options(self, ctx, formatter):
        pass

    def collect_usage_pieces(self, ctx):
        return ["IN", "[ARGS]..."]


def _options(command) -> dict:
    """A mode command's option flags: flag → (parameter name, takes a value)."""
    flags = {}
    for param in command.params:
        if isinstance(param, click.Option):
            for flag in param.opts + param.secondary_opts:
                flags[flag] = (param.name, not (param.is_flag or param.count))
    return flags


def _scan(args, options) -> tuple:
    """(positional arguments, option flags given) of ``args``, options that take a value
    skipping it (as any mode's parser would)."""
    takes = {}
    for flags in options.values():
        for flag, (_, value) in flags.items():
            takes[flag] = takes.get(flag, False) or value
    positionals, given, skip, rest = [], [], False, False
    for arg in args:
        if skip:
            skip = False
        elif rest or arg == "-" or not arg.startswith("-"):
            positionals.append(arg)
        elif arg == "--":
            rest = True
        else:
            flag = arg.split("=", 1)[0]
            given.append(flag)
            skip = "=" not in arg and takes.get(flag, False)
    return positionals, given


def _refuse_foreign(mode, modules, options, given, positionals) -> None:
    """A usage error naming the options (and ENV) given that ``mode`` does not take but
    another mode does: what they apply to, or (the capture) what it is instead."""
    from relight_cli.errors import UsageProblem

    def arguments(m):
        return sum(isinstance(p, click.Argument) for p in m.command.params)

    def owners(flag):
        if flag == "ENV":       # a second positional argument: the hand's env map
            return tuple(m for m in modules if arguments(m) >= len(positionals))
        return tuple(m for m in modules if flag in options[m])
    foreign = [flag for flag in dict.fromkeys(given) if flag not in options[mode] and owners(flag)]
    if len(positionals) > arguments(mode) and owners("ENV"):
        foreign.insert(0, "ENV")
    if not foreign:
        return
    if hasattr(mode, "REFUSAL"):
        raise UsageProblem(mode.REFUSAL.format(", ".join(foreign)))
    first = owners(foreign[0])
    named = [flag for flag in foreign if owners(flag) == first]
    raise UsageProblem(f"{', '.join(named)} only apply to "
                       + " or ".join(m.DESCRIPTION for m in first))


@click.command("relight", cls=Dispatch, add_help_option=False,
               context_settings={"ignore_unknown_options": True, "allow_extra_args": True},
               short_help="Relight Gaussians or render a hand under new light, or score a capture.")
def command():
    """Relight IN under new lighting: IN decides what is done.

    \b
      IN = AVATAR.ply (or a mesh, builtin:hand|room|sphere) [ENV]: Gaussians
        relit by an SH probe (--probe, or fitted from an env map ENV), turned
        into IN's frame by --up, shadowed by a DGSM (--dgsm, --receivers); a
        relit PLY in IN's own frame, or with --camera an EXR view.
      IN = HAND.npz (or builtin:right|left|two[:POSE]) [ENV]: the posed hands
        rendered under an env map and/or --lights, by the physical renderer
        or a learned --model with --checkpoint; one EXR, or --frames.
      IN = CAPTURE/: a capture's images scored against learned models' renders
        (a relight/metrics JSON).

    \b
    Examples:
      relight relight avatar.ply --probe probe.json -o avatar-relit.ply
      relight relight statue.ply sky.hdr --up -y -o statue-relit.ply
      relight relight hand.npz builtin:sky --model physical -o img.exr
      relight relight capture/ --model teacher --checkpoint teacher.pt -o scores.json
      relight relight hand.npz --help      (the hand mode's options)
    """
