"""``relight synth-capture``: a synthetic light-stage capture with known ground truth."""

from __future__ import annotations

import click

from relight_cli.cli.tools import (SEED_MAX, SquareSize, check_output, log, no_clobber_option,
                                   preview_option, quiet_option, renamed_option, seed_option)


@click.command("synth-capture",
               short_help="Render a synthetic light-stage capture (dome of cameras and LEDs).")
@click.argument("hand", metavar="[HAND]", required=False, default="builtin:right")
@click.option("-o", "--output", required=True, metavar="FOLDER",
              help="Capture folder (created; an existing capture of the same settings is resumed).")
@click.option("--cameras", type=int, default=20, show_default=True, help="Cameras on the dome.")
@click.option("--leds", type=int, default=64, show_default=True,
              help="Number of LED point lights on the dome (formerly --lights).")
@renamed_option("--lights", "--leds N",
                why="--lights is a lights JSON file in dgsm-build and relight")
@click.option("--group", type=int, default=5, show_default=True,
              help="Lights on in a grouped (partially lit) frame.")
@click.option("--n-frames", "frames", type=int, default=12, show_default=True,
              help="Number of frames of hand motion (formerly --frames).")
@renamed_option("--frames", "--n-frames N",
                why="--frames selects frames (all|A:B[:S]) in every command; a count is --n-frames")
@click.option("--full-every", type=int, default=3, show_default=True,
              help="Every N-th frame is fully lit (1: all frames fully lit).")
@click.option("--size", "res", type=SquareSize(), default=128, show_default=True,
              help="Image size N or NxN (the stage's cameras are square; formerly --res).")
@renamed_option("--res", "--size N", why="sizes are --size WxH or N everywhere")
@click.option("--motion", type=click.Choice(["random", "file"]), default="random",
              show_default=True,
              help="random: slerp between random key poses; file: HAND's own frames.")
@click.option("--keyframe-every", type=int, default=10, show_default=True,
              help="Frames between random key poses.")
@click.option("--tex-res", type=SquareSize(), default=256, show_default=True,
              help="Renderer's texture-space lighting map size.")
@click.option("--aa", type=int, default=2, show_default=True,
              help="Stratified sub-pixel samples per axis: the images integrate each pixel's "
                   "area as a sensor does (recorded in capture.json; learned models sample "
                   "pixels the same way).")
@click.option("--no-sss", is_flag=True, help="Ablation: no subsurface scattering.")
@click.option("--bounce", is_flag=True, help="Add one bounce of interreflection (slower).")
@click.option("--eval-poses", type=int, default=2, show_default=True,
              help="Held-out poses rendered under --eval-envs for evaluation (0: none).")
@click.option("--eval-envs", default="builtin:sky,builtin:studio", show_default=True,
              help="Comma-separated env maps (files or builtin:NAME) of the evaluation renders.")
@click.option("--eval-cameras", type=int, default=4, show_default=True,
              help="Cameras (the first N of the dome) of the evaluation renders.")
@click.option("--eval-env-res", default="64x32", show_default=True, metavar="WxH",
              help="Lat-long grid the ground-truth env renders integrate over; the env maps "
                   "are stored in eval/envs/ resampled to it.")
@click.option("--eval-env-space", type=click.Choice(["texels", "vertices"]), default="texels",
              show_default=True,
              help="Where the ground-truth env renders integrate light transport: at the "
                   "texel centres where the LEDs are shaded (an env render is then the sum of "
                   "the stage's own transport over the map's directions, as on a real stage) "
                   "or at mesh vertices, interpolated (captures made before this option).")
@click.option("--ggx-shadowing", type=click.Choice(["smith", "schlick"]), default="smith",
              show_default=True,
              help="The skin's GGX shadowing term: the exact Smith G a standard renderer "
                   "(Mitsuba 3) uses, or URHand Eq. 15's Schlick remap k = (rho+1)^2/8 "
                   "(captures made before this option).")
@click.option("--skin-seed", type=click.IntRange(0, SEED_MAX), default=0, show_default=True,
              help="Seed of the procedural skin: the subject (keep it across the right, left "
                   "and two-hand captures of one study; --seed changes their motion).")
@click.option("--phone-scan", "phone_scan", default=None, metavar="ENV",
              help="Instead of a capture, a phone scan of the subject (HAND's shape, "
                   "--skin-seed's skin) under ENV for relight personalize: --views photos "
                   "(view_NN.exr, RGBA, A = mask) from around the still hand, cameras.json "
                   "and keypoints.json (the joints projected, with pixel noise; "
                   "formats/keypoints2d.md).")
@click.option("--views", type=click.IntRange(2, 256), default=8, show_default=True,
              help="--phone-scan: number of photos.")
@preview_option("Also write a labelled PNG contact sheet: a few cameras (rows) × fully lit, "
                "grouped and held-out env-map frames (columns).")
@seed_option
@no_clobber_option
@quiet_option
def command(hand, output, cameras, leds, group, frames, full_every, res, motion,
            keyframe_every, tex_res, aa, no_sss, bounce, eval_poses, eval_envs, eval_cameras,
            eval_env_res, eval_env_space, ggx_shadowing, skin_seed, phone_scan, views, preview,
            seed, no_clobber, quiet):
    """Render a light-stage capture of HAND (a hand.npz, or
    builtin:right|left|two[:POSE]; default builtin:right) into FOLDER in the
    relight/capture format (formats/capture.md): capture.json, the ground-truth
    hand.npz, images/{frame:06d}/{camera}.exr (R, G, B, A = mask; with two hands
    also hand0.A, hand1.A: each hand's coverage) and held-out evaluation renders
    under env maps in eval/.

    Frames are time-multiplexed: every --full-every-th frame has all --leds on,
    the others a group of --group neighbouring LEDs.  Rerunning the same
    command resumes: frames whose images exist and are valid are skipped
    (--no-clobber refuses an existing FOLDER instead).

    Two hands (builtin:two, or a hand.npz with two hands): both move through
    their own random poses and interact: the second hand faces the first one's
    palm and slides in until the hands are 6-25 mm apart, so they shadow,
    occlude and light (--bounce) each other but never touch.

    \b
    Examples:
      relight synth-capture -o capture/ --cameras 20 --leds 64 --n-frames 30
      relight synth-capture builtin:two -o both/ --seed 3
      relight synth-capture hand.npz -o capture/ --motion file --size 256
      relight synth-capture -o capture/ --cameras 8 --n-frames 6 --preview capture.png
      relight synth-capture hand.npz --skin-seed 7 --phone-scan builtin:sky -o scan/
    """
    import os
    import time

    from relight_cli.errors import UsageProblem
    from relight_cli.formats import capture as C
    from relight_cli.cli.inputs import load_envmap, load_hand
    from relight_cli.jobs.synth_capture import StageSettings, light_stage, write_capture_folder

    if phone_scan is not None:
        return _phone_scan(hand, output, phone_scan, views, res, tex_res, aa, no_sss, skin_seed,
                           seed, preview, no_clobber, quiet)
    # ---- usage checks before any work
    env_specs, env_res, existing = _check_usage(
        hand, output, cameras, leds, group, frames, full_every, res, motion, keyframe_every,
        tex_res, aa, eval_poses, eval_envs, eval_cameras, eval_env_res, preview, no_clobber)

    # ---- inputs (data errors), the plan
    data = load_hand(hand)
    settings = StageSettings(cameras=cameras, lights=leds, group=group, frames=frames,
                             full_every=full_every, res=res, keyframe_every=keyframe_every,
                             seed=seed, tex_res=tex_res, aa=aa, sss=not no_sss, bounce=bounce,
                             skin_seed=skin_seed, eval_env_res=tuple(env_res),
                             eval_env_space=eval_env_space, ggx_shadowing=ggx_shadowing)
    stage = light_stage(data, [load_envmap(spec) for spec in env_specs], settings, motion,
                        eval_poses)
    plan, settings = stage.plan, stage.settings
    if existing is not None and existing.key != plan.key:
        raise UsageProblem("output folder holds a different capture (other settings or hand); "
                           "give a new folder to start another", output)
    log(f"{'resuming' if existing else 'writing'} {output}: {settings.cameras} cameras, "
        f"{settings.lights} LEDs, {len(plan.frames)} frames ({res}x{res})", quiet)

    # ---- write: every finished file lands at once (resumable), see C.immediate_writes
    start = time.perf_counter()
    capture, rendered, skipped = write_capture_folder(output, stage, hand, env_specs,
                                                      eval_cameras, quiet)
    log(f"wrote {output}: {rendered} image(s) rendered, {skipped} already there "
        f"({time.perf_counter() - start:.1f} s)", quiet)
    if preview is not None:
        from relight_cli.formats.image import write_png
        from relight_cli.preview import capture_sheet
        title = (f"synth-capture {hand} -> {output}: {settings.cameras} cameras, "
                 f"{settings.lights} LEDs, {len(plan.frames)} frames ({res}x{res})")
        write_png(preview, capture_sheet(
            capture, lambda rel: C.read_image(os.path.join(output, rel)), title))
        log(f"wrote {preview}", quiet)


def _check_usage(hand, output, cameras, leds, group, frames, full_every, res, motion,
                 keyframe_every, tex_res, aa, eval_poses, eval_envs, eval_cameras,
                 eval_env_res, preview, no_clobber):
    """The options' usage errors (exit 2), before any work: (env map specs, the eval env
    grid, the capture already in the folder or None)."""
    import os

    from relight_cli.errors import UsageProblem
    from relight_cli.formats import capture as C
    from relight_cli.cli.inputs import env_grid
    from relight_cli.jobs.synth_capture import env_name

    for name, value, lo, hi in (("--cameras", cameras, 1, 1000), ("--leds", leds, 1, 10000),
                                ("--group", group, 1, 10000), ("--n-frames", frames, 1, 100000),
                                ("--full-every", full_every, 1, 100000), ("--size", res, 8, 4096),
                                ("--keyframe-every", keyframe_every, 1, 100000),
                                ("--tex-res", tex_res, 8, 4096), ("--aa", aa, 1, 8),
                                ("--eval-poses", eval_poses, 0, 1000),
                                ("--eval-cameras", eval_cameras, 0, 1000)):
        if not lo <= value <= hi:
            raise UsageProblem(f"{name} must be in [{lo}, {hi}], got {value}")
    if group > leds:
        raise UsageProblem(f"--group {group} exceeds --leds {leds}")
    if eval_poses and eval_cameras > cameras:
        raise UsageProblem(f"--eval-cameras {eval_cameras} exceeds --cameras {cameras}")
    if motion == "file" and hand.startswith("builtin:"):
        raise UsageProblem("--motion file needs a HAND.npz with frames")
    env_specs = [e.strip() for e in eval_envs.split(",") if e.strip()] if eval_poses else []
    if eval_poses and not env_specs:
        raise UsageProblem("--eval-poses needs at least one --eval-envs map")
    env_names = [env_name(e) for e in env_specs]
    if len(set(env_names)) != len(env_names):
        raise UsageProblem("two --eval-envs maps have the same name")
    env_res = env_grid(eval_env_res, "--eval-env-res")
    if output in ("", "-"):
        raise UsageProblem("-o is the capture FOLDER; give a folder name", repr(output))
    if no_clobber and os.path.lexists(output):
        raise UsageProblem("output exists and --no-clobber was given", output)
    check_output(preview, no_clobber, kind="png", what="--preview")
    if os.path.exists(output) and not os.path.isdir(output):
        raise UsageProblem("output exists and is not a folder", output)
    parent = os.path.dirname(os.path.abspath(output))
    if not os.path.isdir(parent):
        raise UsageProblem("output's parent folder does not exist", parent)
    existing = None
    if os.path.isdir(output) and os.listdir(output):
        if not os.path.exists(os.path.join(output, C.INDEX)):
            raise UsageProblem("output folder is not empty and holds no capture.json; "
                               "give a new or empty folder", output)
        existing = C.read_capture(os.path.join(output, C.INDEX))
    return env_specs, env_res, existing


def _phone_scan(hand, output, env, views, res, tex_res, aa, no_sss, skin_seed, seed, preview,
                no_clobber, quiet):
    """``--phone-scan``: the subject's scan (relight_cli.jobs.phone_scan) into ``output``."""
    import os

    from relight_cli.cli.inputs import load_envmap, load_hand
    from relight_cli.cli.tools import check_input
    from relight_cli.errors import UsageProblem
    from relight_cli.jobs import phone_scan as job
    from relight_cli.jobs.synth_capture import StageSettings
    from relight_cli.provenance import provenance

    if preview is not None:
        raise UsageProblem("--preview makes a capture's contact sheet; a --phone-scan has none")
    if os.path.lexists(output):
        if not os.path.isdir(output):
            raise UsageProblem("--phone-scan writes a folder; this is a file", output)
        if no_clobber:
            raise UsageProblem("output exists and --no-clobber was given", output)
        if os.path.exists(os.path.join(output, "capture.json")):
            raise UsageProblem("the folder holds a capture; give another folder for a scan",
                               output)
    check_input(env)
    data = load_hand(hand)
    if len(data.hands) != 1:
        raise UsageProblem("--phone-scan scans one hand; give a one-hand HAND", hand)
    lighting = load_envmap(env)
    settings = StageSettings(res=res, tex_res=tex_res, aa=aa, sss=not no_sss,
                             skin_seed=skin_seed, seed=seed)
    scan = job.phone_scan(data, settings, lighting, views=views, res=res, seed=seed)
    inputs = {k: v for k, v in (("hand", hand), ("env", env)) if not v.startswith("builtin:")}
    record = {"views": views, "size": res, "tex_res": tex_res, "aa": aa, "sss": not no_sss,
              "skin_seed": skin_seed, "seed": seed, "env": env, "hand": hand}
    if os.path.exists(os.path.join(output, "keypoints.json")):    # an earlier scan's photos
        import glob
        for stale in glob.glob(os.path.join(output, "view_*.exr")):
            if os.path.basename(stale) not in scan.keypoints.images:
                os.remove(stale)
    written = job.write_scan(output, scan, lambda fmt, version: provenance(fmt, version, inputs,
                                                                           record))
    log(f"wrote {output}: {len(written) - 2} photo(s) of the {data.side} hand under {env}, "
        f"cameras.json, keypoints.json", quiet)
