"""The hand mode's shared usage checks (commands/relight_hand.py: the physical and the
learned renderers): the view and env grid, the outputs one frame or a sequence writes,
and the input files."""

from __future__ import annotations

from relight_cli.cli.tools import check_input, check_output


def view_options(a) -> tuple:
    """The hand mode's shared usage checks: (width, height, env H, env W, the outputs:
    plain names for one frame, ``{frame}`` patterns with --frames, not with --frame)."""
    from relight_cli.cli.inputs import env_grid
    from relight_cli.cli.tools import check_extension, parse_size
    from relight_cli.envmap import DEFAULT_GRID
    from relight_cli.errors import UsageProblem
    from relight_cli.sequence import Outputs, check_frame
    if a.env is None and a.hand_lights is None:
        raise UsageProblem("give an env map ENV and/or --lights LIGHTS.json to light the hand")
    if a.preview_exposure is not None and a.preview is None:
        raise UsageProblem("--preview-exposure sets --preview's tone mapping: give --preview PNG")
    check_extension(a.output, "exr")
    if a.camera is not None and a.hand_size is not None:
        raise UsageProblem("--size sets the default camera's image; the size of --camera is its own")
    width, height = 256, 256
    if a.hand_size is not None:
        width, height = parse_size(a.hand_size, "--size", maximum=8192)
    env_h, env_w = env_grid(a.env_res) if a.env_res is not None else DEFAULT_GRID
    check_frame(a.hand_frame, a.hand_frames)
    outputs = Outputs(a.hand_frames, {"-o": (a.output, "exr"), "--preview": (a.preview, "png")})
    return width, height, env_h, env_w, outputs


def check_files(a, outputs, *more) -> None:
    """-o and --preview (one frame; a sequence's once its frames are known), then the
    input files: --camera, --lights and ``more`` (path, stdin role)."""
    if not outputs.sequence:
        outputs.check([a.hand_frame or 0], lambda path, kind, what: check_output(
            path, a.no_clobber, kind=kind, what=what))
    for path, role in ((a.camera, "--camera"), (a.hand_lights, "--lights"), *more):
        if path is not None:
            check_input(path, stdin=role)
