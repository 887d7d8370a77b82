"""Writing rendered frames: the relight/render EXR (+ PNG preview) of each frame of a run.

What every command that renders images frame by frame shares (``relight relight`` for a
hand today): each :class:`relight_cli.jobs.relight_hand.FrameRender` written as it comes
to its frame's names (:class:`relight_cli.sequence.Outputs`), its provenance recording
its frame, a progress bar over a sequence, and the closing log line with what it cost.
"""

from __future__ import annotations


def write_renders(outputs, renders, n_frames: int, inputs: dict, settings: dict, start: float,
                  output: str, quiet: bool = False, passes: bool = False,
                  exposure: float | None = None) -> list:
    """Write each FrameRender of ``renders`` (EXR: its channels and camera, provenance with
    its ``frame``; the ``--preview`` PNG), then log what the run cost (``passes``: its
    network passes too).  ``inputs``' None roles are left out.  Returns the renders, their
    pixels dropped (their timings kept)."""
    import time

    from relight_cli.cli.tools import log
    from relight_cli.formats.exr import write_exr
    from relight_cli.jobs.relight_hand import timing_summary
    from relight_cli.provenance import provenance
    from relight_cli.sequence import write_sequence
    inputs = {role: path for role, path in inputs.items() if path is not None}

    def write(r):
        paths = outputs.paths(r.frame)
        record = provenance("relight/render", 1, inputs, {**settings, "frame": r.frame})
        write_exr(paths["-o"], r.channels, attributes={
            "relight.model": settings["model"], "relight.camera": r.view.to_json()},
            provenance=record, camera=r.view)
        if paths.get("--preview") is not None:
            from relight_cli.preview import write_preview
            write_preview(paths["--preview"], r.rgb, exposure=exposure)
        r.rgb = r.channels = None          # the pixels are written; keep the timings
        return r
    done = write_sequence(renders, write, n_frames, "relight (frames)", quiet,
                          bar=outputs.sequence)
    wall = time.perf_counter() - start
    log(f"wrote {timing_summary(done, output, outputs.sequence, wall, passes)}", quiet)
    return done


def select_frames(outputs, frame, frames, n_frames: int, source: str, no_clobber: bool) -> list:
    """The frames of a run (``--frames`` or the one ``--frame``) of a recording of
    ``n_frames``; with --frames every frame's outputs checked before any work."""
    from relight_cli.cli.tools import check_output
    from relight_cli.sequence import select
    selected = select(frame, frames, n_frames, source)
    if outputs.sequence:
        outputs.check(selected, lambda path, kind, what: check_output(
            path, no_clobber, kind=kind, what=what))
    return selected


def frames_text(frames) -> str:
    """``frame 3`` or ``12 frames (0…11)`` for a log line."""
    if len(frames) == 1:
        return f"frame {frames[0]}"
    return f"{len(frames)} frames ({frames[0]}…{frames[-1]})"


def view_of(camera_path: str | None, width: int, height: int):
    """(frame, posed meshes) → Camera: ``--camera`` read once, or each frame framed by the
    default camera of ``width`` × ``height`` (:func:`relight_cli.jobs.relight_hand.framing`)."""
    from relight_cli.jobs.relight_hand import framing
    camera = None
    if camera_path is not None:
        from relight_cli.formats.camera import read_camera
        camera = read_camera(camera_path)
    return framing(width, height, camera)
