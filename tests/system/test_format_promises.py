"""Every promise of formats/README.md, checked (issue 16).

Each sentence of that page is a promise to users.  The ones no other test
checked are checked here, one test each, named after the promise; the others
are checked where they were already (the map below names the file).  Inputs
are tiny (the data folder of test_outputs_and_bad_inputs.py, and one run of
every command writing every kind of output), so the module takes about a
minute of CPU.  Each test here was seen to fail with the code it guards broken.

Promise (formats/README.md) → test
==================================
Header and table
  data files name format and version ...... test_every_output_records_its_format_and_provenance
  newer versions refused, naming the file . test_table_readers_read_the_format (a version-99 file
                                            through every reader the table names),
                                            test_python_readers_refuse_a_newer_version
  untagged files of other tools read ...... test_untagged_files_of_other_tools_are_read
  a module and a spec per format; versions  test_table_versions_and_specs_match_the_code
  "written by" ............................ test_table_writers_write_the_format
  camera imports (COLMAP, nerfstudio) ..... formats/test_camera_imports.py::test_colmap_round_trip_and_half_pixel_shift,
                                            formats/test_camera_imports.py::
                                            test_nerfstudio_round_trip_and_projection
  Leap Motion recordings .................. formats/test_leap.py::test_mapping_units_axes_and_missing_joints
  "read by" ............................... test_table_read_by_names_the_readers_tested,
                                            test_table_readers_read_the_format,
                                            test_render_files_are_read_as_images
Provenance
  the record, its fields, its format ...... test_every_output_records_its_format_and_provenance
  EXR / JSON / npz / PLY / checkpoint ..... test_exr_provenance_is_three_header_attributes,
                                            test_json_provenance_is_top_level_fields,
                                            test_npz_provenance_is_three_keys,
                                            test_ply_provenance_is_obj_info_lines,
                                            test_checkpoint_provenance_is_plain_entries
  no timestamps / timings, identical bytes  test_outputs_and_bad_inputs.py::
                                            test_identical_inputs_give_identical_bytes
  fixed zip member dates .................. test_npz_members_have_fixed_zip_dates
  command line without -q/--debug/... ..... test_command_line_leaves_out_presentation_flags
  builtin inputs hashed by name ........... test_builtin_inputs_are_hashed_by_name
  a JSON FIFO is not opened to be hashed .. engine/test_fileio.py::
                                            test_declaring_a_fifo_input_does_not_open_it
Atomic writes
  temp file name and folder ............... test_temporary_file_is_named_and_placed_as_documented
  fsync, not empty ........................ test_finished_output_is_fsynced_before_the_rename,
                                            test_empty_output_is_refused
  EXR/PNG read back on a full disk ........ test_full_disk_reads_exr_and_png_back (os.statvfs
                                            reports 0 free blocks, the file is cut short before
                                            the read-back); the real thing (an 8 KiB tmpfs in a
                                            user namespace): test_outputs_and_bad_inputs.py::
                                            test_full_file_system_never_leaves_an_empty_output
  renamed into place ...................... test_output_is_renamed_into_place
  several outputs: all or nothing ......... test_failed_second_output_leaves_the_first_unwritten,
                                            engine/test_fileio.py::
                                            test_output_transaction_is_all_or_nothing
  Ctrl-C, SIGTERM, SIGHUP leave nothing;
  SIGKILL's temp removed by the next run .. test_outputs_and_bad_inputs.py::
                                            test_killed_run_leaves_no_temp_files_after_the_next_run
                                            (SIGINT, SIGTERM, SIGHUP, SIGKILL),
                                            test_stale_temp_files_of_live_processes_are_kept
What an output may be (in test_outputs_and_bad_inputs.py unless written here)
  symlink written through ................. test_symlink_output_is_written_through,
                                            test_temporary_file_is_named_and_placed_as_documented
  character device in place, /dev/null .... test_character_device_is_written_in_place (root: a
                                            node of /dev/null's device, so a bug cannot replace
                                            /dev/null), test_full_device_is_a_write_error
  FIFO in place / without a reader ........ test_fifo_with_reader_gets_the_bytes,
                                            test_fifo_without_reader_is_refused_and_kept
  folder, block device, socket refused .... test_bad_output_target[*-directory],
                                            test_block_device_and_socket_are_refused (root),
                                            test_socket_output_is_refused
  output = input, two outputs on one file . test_bad_output_target[*-input],
                                            test_two_outputs_on_one_file_are_refused
  ... before anything is computed ......... test_output_that_is_an_input_is_refused_before_any_work
  hard links and ./ aliases ............... test_hard_link_to_an_input_is_refused,
                                            test_two_outputs_on_one_file_are_refused[envmap-alias]
  permissions ............................. test_read_only_folder (root, without its override)
  /proc, name too long .................... test_bad_output_target[*-proc], [*-name-too-long]
  read-only file system ................... test_read_only_file_system_is_one_line
  full disk ............................... see "read back on a full disk" above
What is checked when a checkpoint, a distill cache and a capture are read
  checkpoints ............................. test_hostile_checkpoints.py::
                                            test_hostile_checkpoint_is_one_line,
                                            test_real_checkpoints_still_load_and_resume
  distill cache ........................... test_hostile_checkpoints.py::
                                            test_damaged_cache_entry_is_recomputed,
                                            test_cache_write_interrupted_leaves_nothing
  captures ................................ test_hostile_files.py::
                                            test_a_hostile_file_is_one_line_and_writes_nothing
Names say what is written (test_outputs_and_bad_inputs.py unless written here)
  extension matches the format, any case .. test_output_extension_must_say_what_is_written,
                                            test_extensions_are_checked_in_any_case
  devices and FIFOs exempt ................ test_character_device_is_written_in_place,
                                            test_fifo_with_reader_gets_the_bytes
One line for a failure, also without -q
  log lines held until progress or success  cli/test_cli.py::
                                            test_log_lines_are_held_until_progress_shows_or_the_command_ends,
                                            commands/test_relight_gaussians.py::
                                            test_cli_info_lines_of_a_failing_run_are_not_said
Streams (test_outputs_and_bad_inputs.py unless written here)
  `-` reads JSON from stdin, provenance `-` test_json_inputs_read_stdin
  one input on stdin; not a terminal ...... test_only_one_input_reads_stdin,
                                            test_stdin_left_at_a_terminal_is_a_usage_error
  binary inputs never read stdin .......... test_binary_inputs_do_not_read_stdin
  `-o -` JSON; binary outputs need a name . test_json_outputs_go_to_stdout,
                                            test_binary_outputs_cannot_go_to_stdout
  broken stdout pipe: 141, quiet .......... test_broken_stdout_pipe_exits_quietly,
                                            test_broken_pipe_through_a_shell_pipeline
Sizes
  WxH, width first; N for N×N ............. commands/test_dgsm_build.py::
                                            test_size_is_width_by_height,
                                            commands/test_relight_hand.py::
                                            test_default_camera_and_size
  square-only sizes refuse WxH ............ commands/test_synth_capture.py::
                                            test_size_is_square,
                                            commands/test_relight_hand.py::
                                            test_bad_input[*not square*]
  --env-res taller than wide refused ...... commands/test_bake_features.py::
                                            test_usage_errors
  stored files keep [H, W] ................ commands/test_bake_features.py::
                                            test_bake_reads_back_and_matches_engine
Reading JSON
  NaN/Infinity, 1e400, depth, long ints ... test_every_json_reader_refuses_what_json_cannot_hold,
                                            test_json_nesting_limit_is_64_levels
  ... metrics files read them as NaN ...... test_metrics_files_read_non_finite_numbers_as_nan,
                                            test_outputs_and_bad_inputs.py::
                                            test_metrics_compare_fails_on_nan_and_inf (exit 3)
  true/false are not numbers .............. test_json_booleans_are_not_numbers
  one line naming the file, exit 1 ........ test_json_refusals_are_one_line_exit_1,
                                            test_outputs_and_bad_inputs.py::test_bad_input[*json*]
Images
  linear EXR, half or float ............... test_exr_outputs_are_half_or_float
  channel names ........................... test_exr_channels_are_named_by_layer,
                                            test_capture_images_of_two_hands_name_each_hands_coverage
  PNG previews: contact sheets ............ engine/test_preview.py (formats/preview.md's promises), e.g.
                                            test_preview_must_be_a_png,
                                            test_png_is_byte_identical_and_has_no_time_stamp
  rendered images: Reinhard + sRGB ....... test_png_preview_is_reinhard_then_srgb
Conventions
  world right-handed, +Y up, metres ....... test_world_is_right_handed_y_up_in_metres
  cameras OpenCV, world→camera, pixel
  centres at integer coordinates .......... formats/test_camera.py::
                                            test_camera_look_at_projects_target_to_principal_point,
                                            formats/test_camera.py::
                                            test_look_at_projects_hand_computed_pixels
  rendered EXRs carry worldToCamera/NDC ... formats/test_camera.py::
                                            test_hand_render_header_is_its_camera,
                                            formats/test_camera.py::
                                            test_splat_renderer_puts_a_gaussian_where_the_header_says
  UV v = 0 at the bottom row .............. engine/test_uvraster.py::test_texel_centres_v_up,
                                            engine/test_uvraster.py::
                                            test_bottom_triangle_lands_in_bottom_rows
  SH real, orthonormal, CS phase, index ... engine/test_sh.py::
                                            test_sh_basis_matches_scipy_complex_harmonics,
                                            test_sh_degree1_is_the_3dgs_convention
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
import shutil
import stat
import subprocess
import zipfile
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from conftest import ROOT, relight_executable
from relight_cli.cli import COMMANDS as REGISTRY
from relight_cli.cli import cli
from relight_cli.errors import DataError, OutputError
from sweep import _assert_one_error, _inproc, _run_inproc_fail, _snapshot, data

__all__ = ["data"]   # the sweep's tiny inputs, a fixture of this module too

README = ROOT / "formats" / "README.md"


# ----------------------------------------------------------------------------- what relight writes


def _written_runs(d: Path, w: Path) -> dict[str, list[list]]:
    """command -> the runs (argv) that make every kind of output it writes, into ``w``."""
    return {
        "envmap": [["envmap", "builtin:sky", "--size", "8x4", "-o", w / "env.exr",
                    "--preview", w / "env.png"],
                   ["envmap", d / "sky.exr", "--half", "-o", w / "half.exr"]],
        "sh-probe": [["sh-probe", d / "sky.exr", "--degree", "1", "-o", w / "probe.json"]],
        "fit-geometry": [["fit-geometry", "--pose", "fist", "-o", w / "hand.npz", "--report",
                          w / "fit.json"]],
        "camera": [["camera", "--eye", "0,0.1,0.5", "--size", "8x8", "-o", w / "camera.json"]],
        "bake-features": [["bake-features", d / "hand.npz", d / "sky.exr", "--res", "8",
                           "--env-res", "8x4", "-o", w / "feats.exr", "--per-vertex",
                           w / "feats.npz"]],
        "relight": [["relight", d / "hand.npz", d / "sky.exr", "--size", "8x8", "--tex-res", "8",
                     "--aa", "1", "--env-res", "8x4", "--aov", "normal", "-o", w / "render.exr"],
                    ["relight", d / "ball.ply", "--probe", d / "probe.json", "-o",
                     w / "relit.ply"],
                    ["relight", d / "cap", "--model", "teacher", "--checkpoint",
                     d / "teacher.pt", "-o", w / "scores.json"]],
        "dgsm-build": [["dgsm-build", d / "ball.ply", "--receivers", d / "room.ply", "--lights",
                        d / "lights.json", "--size", "4", "--bins", "2", "-o", w / "shadows.exr",
                        "--lights-out", w / "lights.json", "--occluders-out", w / "occ.ply"]],
        "metrics": [["metrics", "image", d / "img.exr", d / "img2.exr", "-o", w / "m.json"],
                    ["metrics", "compare", d / "m.json", d / "m.json", "-o", w / "cmp.json"]],
        "synth-capture": [["synth-capture", d / "hand.npz", "-o", w / "cap", "--cameras", "1",
                           "--leds", "3", "--group", "1", "--n-frames", "3", "--size", "8",
                           "--tex-res", "8", "--aa", "1", "--eval-poses", "1", "--eval-cameras",
                           "1", "--eval-envs", "builtin:sky"],
                          ["synth-capture", d / "hand.npz", "--phone-scan", "builtin:sky",
                           "--views", "2", "--size", "32", "--tex-res", "16", "--aa", "1",
                           "--no-sss", "-o", w / "scan"]],
        "personalize": [["personalize", w / "scan" / "view_00.exr", w / "scan" / "view_01.exr",
                         "--cameras", w / "scan" / "cameras.json", "--keypoints",
                         w / "scan" / "keypoints.json", "--env", "builtin:sky", "--tex-res",
                         "8", "--iterations", "2", "-o", w / "me.npz", "--report",
                         w / "me.json"]],
        "train-teacher": [["train-teacher", d / "cap", "--config", d / "small.json", "--iters",
                           "1", "-o", w / "teacher.pt", "--metrics-out", w / "teacher.json"]],
        "distill": [["distill", d / "teacher.pt", d / "cap", "--envs", "builtin:sky", "--iters",
                     "1", "-o", w / "student.pt", "--metrics-out", w / "student.json"]],
    }


@pytest.fixture(scope="module")
def written(data, tmp_path_factory):
    """(folder, {output path: command that wrote it}): every command, every kind of output."""
    folder = tmp_path_factory.mktemp("written")
    WRITTEN["folder"] = folder
    made = {}
    for command, runs in _written_runs(data, folder).items():
        for args in runs:
            before = set(folder.rglob("*"))
            r = _inproc(*args, "-q")
            assert r.exit_code == 0, (args, r.output)
            made.update({p: command for p in set(folder.rglob("*")) - before if p.is_file()})
    return folder, made


def _tag(path: Path) -> tuple[str, int, dict]:
    """(format, version, provenance record) as stored in ``path``, read without relight."""
    suffix = path.suffix
    if suffix == ".exr":
        import OpenEXR
        header = OpenEXR.File(str(path)).header()
        return (header["relight.format"], header["relight.version"],
                json.loads(header["relight.provenance"]))
    if suffix == ".json":
        obj = json.loads(path.read_text())
        return obj["format"], obj["version"], obj["provenance"]
    if suffix == ".npz":
        with np.load(path, allow_pickle=False) as z:
            return str(z["format"]), int(z["version"]), json.loads(str(z["provenance"]))
    if suffix == ".ply":
        lines = _ply_obj_info(path)
        fmt = [ln.split()[1:] for ln in lines if ln.startswith("relight.format ")]
        prov = [ln.split(" ", 1)[1] for ln in lines if ln.startswith("relight.provenance ")]
        return fmt[0][0], int(fmt[0][1]), json.loads(prov[0])
    if suffix == ".pt":
        import torch
        obj = torch.load(path, weights_only=True)
        return obj["format"], obj["version"], json.loads(obj["provenance"])
    raise AssertionError(f"no reader for {path}")


def _ply_obj_info(path: Path) -> list[str]:
    header = path.read_bytes().split(b"end_header\n", 1)[0].decode("ascii")
    return [ln[len("obj_info "):] for ln in header.splitlines() if ln.startswith("obj_info ")]


def _data_files(written):
    """Every output but PNG previews (which are not a format)."""
    folder, made = written
    return {p: c for p, c in made.items() if p.suffix != ".png"}


# ----------------------------------------------------------------------------- the table


def _table() -> dict[str, dict]:
    """format -> {"version", "files", "spec", "written by", "read by"} from the README."""
    rows = {}
    for line in README.read_text().splitlines():
        cells = [c.strip() for c in re.split(r"(?<!\\)\|", line.strip())[1:-1]]
        if len(cells) != 6 or not cells[0].startswith("`relight/"):
            continue
        rows[cells[0].strip("`")] = dict(zip(("version", "files", "spec", "written by",
                                              "read by"), cells[1:]))
    return rows


def _commands_in(cell: str) -> set[str]:
    """The subcommands named (in backquotes, options after the name) in a table cell."""
    names = {m.split()[0] for m in re.findall(r"`([^`]+)`", cell)}
    return {n for n in names if n in REGISTRY}


def test_table_versions_and_specs_match_the_code():
    """Each row's version is the one its module writes and reads, its spec exists, and
    every format name the code uses has a row."""
    from relight_cli import formats
    rows = _table()
    declared = {}
    for module_file in Path(formats.__file__).parent.glob("*.py"):
        text = module_file.read_text()
        for name, fmt in re.findall(r'^(\w*FORMAT) = "(relight/[\w-]+)"', text, re.M):
            version = re.search(rf"^{name.replace('FORMAT', 'VERSION')} = (\d+)", text, re.M)
            declared[fmt] = int(version.group(1))
    for source in [*(ROOT / "commands").glob("*.py"), *(ROOT / "relight_cli").rglob("*.py")]:
        for fmt, version in re.findall(r'provenance\("(relight/[\w-]+)", (\d+)',
                                       source.read_text()):
            assert declared.setdefault(fmt, int(version)) == int(version), (source, fmt)
    assert sorted(declared) == sorted(rows)
    for fmt, row in rows.items():
        assert int(row["version"]) == declared[fmt], fmt
        spec = re.fullmatch(r"\[([\w.]+)\]\(([\w.]+)(#[\w-]+)?\)", row["spec"])
        assert spec and (README.parent / spec.group(2)).is_file(), (fmt, row["spec"])


def test_table_writers_write_the_format(written):
    """"written by" names exactly the commands whose outputs carry the format."""
    seen: dict[str, set[str]] = {}
    for path, command in _data_files(written).items():
        seen.setdefault(_tag(path)[0], set()).add(command)
    rows = _table()
    assert set(seen) <= set(rows)
    for fmt, row in rows.items():
        assert _commands_in(row["written by"]) == seen.get(fmt, set()), fmt



def _newer(src: Path, dst: Path) -> Path:
    """A copy of relight's file ``src`` that says it is version 99 of its format."""
    if src.is_dir():   # a capture folder: its index and every image say 99
        shutil.copytree(src, dst)
        _newer(src / "capture.json", dst / "capture.json")
        return dst
    if src.suffix == ".exr":
        from relight_cli.formats.exr import VERSION_KEY, read_exr, write_exr
        image = read_exr(str(src))
        write_exr(str(dst), image.channels, dict(image.attributes, **{VERSION_KEY: 99}),
                  envmap=image.envmap)
    elif src.suffix == ".json":
        dst.write_text(json.dumps(dict(json.loads(src.read_text()), version=99)))
    elif src.suffix == ".npz":
        with np.load(src, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        np.savez(dst, **dict(arrays, version=np.array(99)))
    elif src.suffix == ".ply":
        old = b"relight.format relight/gaussians 1\n"
        dst.write_bytes(src.read_bytes().replace(old, old.replace(b" 1\n", b" 99\n"), 1))
    elif src.suffix == ".pt":
        import torch
        torch.save(dict(torch.load(src, weights_only=True), version=99), dst)
    return dst


def _newer_images(src: Path, dst: Path) -> Path:
    """A copy of capture folder ``src`` whose images and renders say they are version 99."""
    shutil.copytree(src, dst)
    for image in dst.rglob("*.exr"):
        if image.parent.name != "envs":
            _newer(image, image.with_name("v99.exr")).replace(image)
    return dst


def _keypoints(d: Path, dst: Path) -> Path:
    from relight_cli.hand.model import builtin_hand
    joints = builtin_hand("right", pose=None).rest_joints
    dst.write_text(json.dumps({"format": "relight/keypoints", "version": 99,
                               "keypoints": [joints.tolist()]}))
    return dst


# format -> (make the bad file from the data folder and the written folder, its name,
#            {reader (the command and option the table names): argv given data, bad, out}).


def _capture_with(d: Path, hand: Path, out: Path) -> Path:
    """A copy of the data's capture (beside ``out``) whose hand.npz is ``hand``."""
    capture = out.parent / "cap-with-hand"
    shutil.copytree(d / "cap", capture)
    shutil.copy(hand, capture / "hand.npz")
    return capture


def _train(d: Path) -> list:
    return ["--config", d / "small.json", "--iters", "1"]

#: The ``written`` folder once made (the personalize readers take its phone scan).
WRITTEN: dict = {}


def _scan_args(o, cameras=None, keypoints=None, template=None):
    scan = WRITTEN["folder"] / "scan"
    return ["personalize", scan / "view_00.exr", scan / "view_01.exr", "--cameras",
            cameras or scan / "cameras.json", "--keypoints", keypoints or scan / "keypoints.json",
            "--env", "builtin:sky", *(["--template", template] if template else []),
            "-o", o / "x.npz"]


READERS = {
    "relight/envmap": (lambda d, w: d / "sky.exr", "env.exr", {
        "envmap": lambda d, b, o: ["envmap", b, "-o", o / "x.exr"],
        "sh-probe": lambda d, b, o: ["sh-probe", b, "-o", o / "x.json"],
        "bake-features": lambda d, b, o: ["bake-features", d / "hand.npz", b, "-o", o / "x.exr"],
        "relight": lambda d, b, o: ["relight", d / "hand.npz", b, "-o", o / "x.exr"],
        "synth-capture --eval-envs": lambda d, b, o: [
            "synth-capture", d / "hand.npz", "-o", o / "cap", "--cameras", "1",
            "--eval-cameras", "1", "--eval-envs", b],
        "distill --envs": lambda d, b, o: ["distill", d / "teacher.pt", d / "cap", "--envs", b,
                                           "-o", o / "x.pt"]}),
    "relight/camera": (lambda d, w: w / "camera.json", "camera.json", {
        "bake-features --camera": lambda d, b, o: [
            "bake-features", d / "hand.npz", d / "sky.exr", "--camera", b, "-o", o / "x.exr"],
        "relight --camera": lambda d, b, o: ["relight", d / "hand.npz", d / "sky.exr",
                                             "--camera", b, "-o", o / "x.exr"],
        "relight --camera (Gaussians)": lambda d, b, o: [
            "relight", d / "ball.ply", "--probe", d / "probe.json", "--camera", b,
            "-o", o / "x.exr"],
        "metrics shadow --camera": lambda d, b, o: [
            "metrics", "shadow", d / "img.exr", d / "img2.exr", "--roi-avatar", d / "ball.ply",
            "--camera", b, "-o", o / "x.json"],
        "camera --from": lambda d, b, o: ["camera", "--from", b, "-o", o / "x.json"],
        "personalize --cameras": lambda d, b, o: _scan_args(o, cameras=b)}),
    "relight/hand": (lambda d, w: d / "hand.npz", "hand.npz", {
        "bake-features": lambda d, b, o: ["bake-features", b, d / "sky.exr", "-o", o / "x.exr"],
        "relight": lambda d, b, o: ["relight", b, d / "sky.exr", "-o", o / "x.exr"],
        "synth-capture": lambda d, b, o: ["synth-capture", b, "-o", o / "cap"],
        "fit-geometry --template": lambda d, b, o: ["fit-geometry", "--template", b,
                                                    "-o", o / "x.npz"],
        "dgsm-build": lambda d, b, o: ["dgsm-build", b, "--receivers", d / "room.ply",
                                       "--lights", d / "lights.json", "-o", o / "x.exr"],
        "train-teacher": lambda d, b, o: ["train-teacher", _capture_with(d, b, o), *_train(d),
                                          "-o", o / "x.pt"],
        "distill": lambda d, b, o: ["distill", d / "teacher.pt", _capture_with(d, b, o),
                                    "--envs", "builtin:sky", "-o", o / "x.pt"],
        "personalize --template": lambda d, b, o: _scan_args(o, template=b)}),
    "relight/keypoints-2d": (lambda d, w: w / "scan" / "keypoints.json", "kp2d.json", {
        "personalize --keypoints": lambda d, b, o: _scan_args(o, keypoints=b)}),
    "relight/personalize-report": (None, "me.json", {}),
    "relight/keypoints": (None, "kp.json", {
        "fit-geometry --keypoints": lambda d, b, o: ["fit-geometry", "--keypoints", b,
                                                     "-o", o / "x.npz"]}),
    "relight/fit-report": (None, "fit.json", {}),
    "relight/features": (lambda d, w: w / "feats.exr", "feats.exr", {}),
    "relight/gaussians": (lambda d, w: d / "ball.ply", "ball.ply", {
        "dgsm-build": lambda d, b, o: ["dgsm-build", b, "--receivers", d / "room.ply",
                                       "--lights", d / "lights.json", "-o", o / "x.exr"],
        "sh-probe": lambda d, b, o: ["sh-probe", b, "--at", "0,0.5,0", "-o", o / "x.json"],
        "relight": lambda d, b, o: ["relight", b, "--probe", d / "probe.json", "-o", o / "x.ply"],
        "metrics lighting": lambda d, b, o: ["metrics", "lighting", "--scene", b, "--avatar",
                                             d / "ball.ply", "-o", o / "x.json"]}),
    "relight/gaussian-sequence": (lambda d, w: _sequence_index(d), "seq.json", {
        "relight": lambda d, b, o: ["relight", b, "--probe", d / "probe.json", "-o", o / "x.ply"],
        "dgsm-build": lambda d, b, o: ["dgsm-build", b, "--receivers", d / "room.ply",
                                       "--lights", d / "lights.json", "-o", o / "x.exr"]}),
    "relight/path": (lambda d, w: _path_file(d), "walk.json", {
        "relight": lambda d, b, o: ["relight", f"{d / 'ball.ply'}:path={b}", "--probe",
                                    d / "probe.json", "-o", o / "x.ply"],
        "dgsm-build": lambda d, b, o: ["dgsm-build", f"{d / 'ball.ply'}:path={b}",
                                       "--receivers", d / "room.ply", "--lights",
                                       d / "lights.json", "-o", o / "x.exr"]}),
    "relight/lights": (lambda d, w: d / "lights.json", "lights.json", {
        "dgsm-build --lights": lambda d, b, o: ["dgsm-build", d / "ball.ply", "--receivers",
                                                d / "room.ply", "--lights", b, "-o", o / "x.exr"],
        "relight --lights": lambda d, b, o: ["relight", d / "hand.npz", "--lights", b,
                                             "-o", o / "x.exr"]}),
    "relight/dgsm": (lambda d, w: w / "shadows.exr", "shadows.exr", {
        "relight --dgsm": lambda d, b, o: ["relight", d / "ball.ply", "--probe", d / "probe.json",
                                           "--receivers", d / "room.ply", "--dgsm", b,
                                           "-o", o / "x.ply"]}),
    "relight/sh-probe": (lambda d, w: d / "probe.json", "probe.json", {
        "relight --probe": lambda d, b, o: ["relight", d / "ball.ply", "--probe", b,
                                            "-o", o / "x.ply"]}),
    "relight/capture": (lambda d, w: d / "cap", "cap", {
        "train-teacher": lambda d, b, o: ["train-teacher", b, *_train(d), "-o", o / "x.pt"],
        "distill": lambda d, b, o: ["distill", d / "teacher.pt", b, "--envs", "builtin:sky",
                                    "-o", o / "x.pt"],
        "camera --from": lambda d, b, o: ["camera", "--from", b / "capture.json",
                                          "-o", o / "x.json"],
        "relight CAPTURE/": lambda d, b, o: ["relight", b, "--model", "teacher", "--checkpoint",
                                             d / "teacher.pt", "-o", o / "x.json"]}),
    "relight/capture-image": (lambda d, w: w / "cap", "cap", {
        "train-teacher": lambda d, b, o: ["train-teacher", b, *_train(d), "-o", o / "x.pt"],
        "distill": lambda d, b, o: ["distill", d / "teacher.pt", b, "--envs", "builtin:sky",
                                    "--iters", "1", "-o", o / "x.pt"],
        "relight CAPTURE/": lambda d, b, o: ["relight", b, "--model", "teacher", "--checkpoint",
                                             d / "teacher.pt", "-o", o / "x.json"]}),
    "relight/vertex-features": (lambda d, w: w / "feats.npz", "feats.npz", {}),
    "relight/metrics": (lambda d, w: d / "m.json", "m.json", {
        "metrics compare": lambda d, b, o: ["metrics", "compare", b, d / "m.json"]}),
    "relight/metrics-comparison": (None, "cmp.json", {}),
    "relight/checkpoint": (lambda d, w: d / "teacher.pt", "teacher.pt", {
        "relight --checkpoint": lambda d, b, o: [
            "relight", d / "hand.npz", d / "sky.exr", "--model", "teacher", "--checkpoint", b,
            "-o", o / "x.exr"],
        "distill": lambda d, b, o: ["distill", b, d / "cap", "--envs", "builtin:sky",
                                    "-o", o / "x.pt"],
        "train-teacher --resume": lambda d, b, o: ["train-teacher", d / "cap", *_train(d),
                                                   "--resume", b, "-o", o / "x.pt"],
        "distill --resume": lambda d, b, o: ["distill", d / "teacher.pt", d / "cap", "--envs",
                                             "builtin:sky", "--resume", b, "-o", o / "x.pt"]}),
}


def _path_file(data: Path) -> Path:
    """A relight/path of two frames."""
    (data / "walk.json").write_text(json.dumps({"format": "relight/path", "version": 1,
                                                "translations": [[0, 0, 0], [0.1, 0, 0]]}))
    return data / "walk.json"


def _sequence_index(data: Path) -> Path:
    """A relight/gaussian-sequence index of one frame: ball.ply as ball_{frame}.ply."""
    import shutil
    shutil.copy(data / "ball.ply", data / "ball_0.ply")
    (data / "seq.json").write_text(json.dumps({"format": "relight/gaussian-sequence",
                                               "version": 1, "frames": "ball_{frame}.ply",
                                               "count": 1}))
    return data / "seq.json"


def _bad_file(fmt: str, data: Path, written_folder: Path, folder: Path) -> Path:
    make, name, _ = READERS[fmt]
    if fmt == "relight/keypoints":
        return _keypoints(data, folder / name)
    if fmt == "relight/capture-image":
        return _newer_images(make(data, written_folder), folder / name)
    return _newer(make(data, written_folder), folder / name)


def test_table_read_by_names_the_readers_tested():
    """"read by" names exactly the commands test_table_readers_read_the_format runs."""
    for fmt, row in _table().items():
        if fmt == "relight/render":
            tested = {"metrics", "camera"}   # test_render_files_are_read_as_images
        else:
            tested = {label.split()[0] for label in READERS[fmt][2]}
        assert _commands_in(row["read by"]) == tested, fmt


@pytest.mark.parametrize("fmt,reader", [(f, r) for f in READERS for r in READERS[f][2]])
def test_table_readers_read_the_format(data, written, tmp_path, fmt, reader):
    """Each reader the table names refuses a file of a newer major version, one line
    naming the file, exit 1."""
    bad = _bad_file(fmt, data, written[0], tmp_path)
    out = tmp_path / "out"
    out.mkdir()
    r = _run_inproc_fail([*READERS[fmt][2][reader](data, bad, out), "-q"], 1)
    assert "version 99" in r.stderr, r.stderr
    assert os.path.basename(bad) in r.stderr, r.stderr
    assert os.listdir(out) == []


def test_render_files_are_read_as_images(written, tmp_path):
    """relight/render has no reader of its own: `metrics image` reads it as any image,
    `camera --from` its OpenEXR camera matrices."""
    folder, _ = written
    r = _inproc("metrics", "image", folder / "render.exr", folder / "render.exr", "-o", "-", "-q")
    assert r.exit_code == 0 and json.loads(r.stdout)["metrics"]["mse"] == 0.0, r.output
    r = _inproc("camera", "--from", folder / "render.exr", "-o", tmp_path / "cam.json", "-q")
    assert r.exit_code == 0, r.output
    assert json.loads((tmp_path / "cam.json").read_text())["width"] == 8


def test_python_readers_refuse_a_newer_version(written, tmp_path):
    """The formats no command reads (features, vertex-features) refuse newer versions too."""
    from relight_cli.formats.features_exr import read_features, read_vertex_features
    folder, _ = written
    for read, name in ((read_features, "feats.exr"), (read_vertex_features, "feats.npz")):
        bad = _newer(folder / name, tmp_path / name)
        with pytest.raises(DataError, match="version") as caught:
            read(str(bad))
        assert caught.value.path == str(bad)


# ----------------------------------------------------------------------------- provenance

SHA256 = re.compile(r"[0-9a-f]{64}|builtin:[0-9a-f]{16}")


def test_every_output_records_its_format_and_provenance(written):
    """Every data file names its format and version, and records how it was made:
    {format, version, tool, command, inputs: {role: {path, sha256}}[, settings]},
    the record's format and version being the file's own."""
    from relight_cli import __version__
    files = _data_files(written)
    assert len(files) >= 20
    for path, command in files.items():
        fmt, version, record = _tag(path)
        assert fmt.startswith("relight/") and isinstance(version, int) and version >= 1, path
        assert set(record) <= {"format", "version", "tool", "command", "inputs", "settings"}
        assert (record["format"], record["version"]) == (fmt, version), path
        assert record["tool"] == f"relight {__version__}", path
        assert record["command"].startswith(f"relight {command} "), path
        for role, item in record["inputs"].items():
            assert set(item) == {"path", "sha256"} and SHA256.fullmatch(item["sha256"]), (path, role)
            if not item["path"].startswith("builtin:"):
                assert item["sha256"] == hashlib.sha256(
                    Path(item["path"]).read_bytes()).hexdigest(), (path, role)
        assert isinstance(record.get("settings", {}), dict), path


def test_exr_provenance_is_three_header_attributes(written):
    """EXR: relight.format (string), relight.version (int), relight.provenance (JSON string)."""
    import OpenEXR
    exrs = [p for p in _data_files(written) if p.suffix == ".exr"]
    assert exrs
    for path in exrs:
        header = OpenEXR.File(str(path)).header()
        assert type(header["relight.format"]) is str, path
        assert type(header["relight.version"]) is int, path
        assert isinstance(json.loads(header["relight.provenance"]), dict), path


def test_json_provenance_is_top_level_fields(written):
    jsons = [p for p in _data_files(written) if p.suffix == ".json"]
    assert jsons
    for path in jsons:
        obj = json.loads(path.read_text())
        assert isinstance(obj["format"], str) and type(obj["version"]) is int, path
        assert isinstance(obj["provenance"], dict), path


def test_npz_provenance_is_three_keys(written):
    """npz: 0-d `format` (string), `version` (integer) and `provenance` (JSON string)."""
    npzs = [p for p in _data_files(written) if p.suffix == ".npz"]
    assert npzs
    for path in npzs:
        with np.load(path, allow_pickle=False) as z:
            assert z["format"].shape == () and z["format"].dtype.kind == "U", path
            assert z["version"].shape == () and z["version"].dtype.kind == "i", path
            assert isinstance(json.loads(str(z["provenance"])), dict), path


def test_ply_provenance_is_obj_info_lines(written):
    """PLY: `obj_info relight.format NAME VERSION` and `obj_info relight.provenance JSON`."""
    plys = [p for p in _data_files(written) if p.suffix == ".ply"]
    assert plys
    for path in plys:
        lines = _ply_obj_info(path)
        assert re.fullmatch(r"relight\.format relight/gaussians \d+", lines[0]), path
        assert lines[1].startswith("relight.provenance {"), path


def test_checkpoint_provenance_is_plain_entries(written):
    """Checkpoints: `format` (str), `version` (int), `provenance` (JSON str) entries,
    loadable with torch.load(weights_only=True)."""
    import torch
    pts = [p for p in _data_files(written) if p.suffix == ".pt"]
    assert pts
    for path in pts:
        obj = torch.load(path, weights_only=True)
        assert type(obj["format"]) is str and type(obj["version"]) is int, path
        assert isinstance(json.loads(obj["provenance"]), dict), path


def test_npz_members_have_fixed_zip_dates(written):
    """Zip members are dated 1980-01-01 00:00:00, whenever the file was written."""
    npzs = [p for p in _data_files(written) if p.suffix == ".npz"]
    for path in npzs:
        with zipfile.ZipFile(path) as z:
            assert {info.date_time for info in z.infolist()} == {(1980, 1, 1, 0, 0, 0)}, path


def test_command_line_leaves_out_presentation_flags(data, tmp_path):
    """-q, --quiet, --debug and --no-clobber change what is shown, not the stored command."""
    plain = ["sh-probe", str(data / "sky.exr"), "--degree", "1", "-o", "-"]
    shown = ["--debug", "sh-probe", str(data / "sky.exr"), "-q", "--degree", "1", "--quiet",
             "--no-clobber", "-o", "-"]
    commands = []
    for args in (plain, shown):
        r = CliRunner().invoke(cli, args)
        assert r.exit_code == 0, r.output
        commands.append(json.loads(r.stdout)["provenance"]["command"])
    assert commands[0] == commands[1] == "relight " + " ".join(plain)


def test_builtin_inputs_are_hashed_by_name(tmp_path):
    """builtin:NAME is recorded with a hash of its name, whatever size it is rendered at."""
    records = []
    for size in ("8x4", "16x8"):
        r = _inproc("envmap", "builtin:sky", "--size", size, "-o", tmp_path / f"{size}.exr", "-q")
        assert r.exit_code == 0, r.output
        records.append(_tag(tmp_path / f"{size}.exr")[2]["inputs"]["input"])
    name_hash = "builtin:" + hashlib.sha256(b"builtin:sky").hexdigest()[:16]
    assert records == [{"path": "builtin:sky", "sha256": name_hash}] * 2


# ----------------------------------------------------------------------------- atomic writes


def test_temporary_file_is_named_and_placed_as_documented(tmp_path):
    """`.NAME.relight-tmp-PID-XXXXXXXX.EXT` in the target's folder (a symlink's: the
    folder of the file it names)."""
    from relight_cli.fileio import atomic_path
    (tmp_path / "real").mkdir()
    (tmp_path / "link.exr").symlink_to(Path("real") / "out.exr")
    for target, folder in ((tmp_path / "out.exr", tmp_path),
                           (tmp_path / "link.exr", tmp_path / "real")):
        with atomic_path(target) as tmp:
            assert os.path.dirname(tmp) == str(folder)
            assert re.fullmatch(rf"\.out\.exr\.relight-tmp-{os.getpid()}-[a-z0-9_]{{8}}\.exr",
                                os.path.basename(tmp)), tmp
            Path(tmp).write_bytes(b"data")
    assert (tmp_path / "out.exr").read_bytes() == (tmp_path / "real" / "out.exr").read_bytes()


def test_finished_output_is_fsynced_before_the_rename(tmp_path, monkeypatch):
    from relight_cli.fileio import atomic_path
    synced, fsync = [], os.fsync

    def spy(fd):
        synced.append((os.readlink(f"/proc/self/fd/{fd}"), (tmp_path / "x.json").exists()))
        fsync(fd)
    monkeypatch.setattr(os, "fsync", spy)
    with atomic_path(tmp_path / "x.json") as tmp:
        Path(tmp).write_text("{}")
    assert synced == [(tmp, False)]


def test_empty_output_is_refused(tmp_path):
    """A writer that left nothing: one-line OutputError, no file (Make would trust it)."""
    from relight_cli.fileio import atomic_path
    with pytest.raises(OutputError, match="nothing was written"):
        with atomic_path(tmp_path / "x.exr"):
            pass
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("kind", ["exr", "png"])
def test_full_disk_reads_exr_and_png_back(tmp_path, monkeypatch, kind):
    """When the file system reports no free block, an EXR or PNG (whose C++ writers can
    drop the error of their last buffer) is read back; one cut short is refused.  The
    full disk is simulated (os.statvfs says 0 free blocks) and the writer's loss by
    truncating the file before the read-back; the real thing is
    test_outputs_and_bad_inputs.py::test_full_file_system_never_leaves_an_empty_output."""
    from relight_cli.formats import exr as exr_module
    from relight_cli.formats import image as image_module
    real = os.statvfs(tmp_path)
    full = os.statvfs_result((real.f_bsize, real.f_frsize, real.f_blocks, 0, 0, *real[5:]))
    monkeypatch.setattr(os, "statvfs", lambda path: full)
    module, reader = (exr_module, "read_exr") if kind == "exr" else (image_module, "read_image")
    read_back, original = [], getattr(module, reader)

    def cut_short(path):
        read_back.append(path)
        size = os.path.getsize(path)
        os.truncate(path, size // 2)
        return original(path)
    monkeypatch.setattr(module, reader, cut_short)
    pixels = np.random.default_rng(0).random((16, 16, 3)).astype(np.float32)
    target = tmp_path / f"x.{kind}"
    with pytest.raises(OutputError, match="no space left"):
        if kind == "exr":
            exr_module.write_exr(str(target), {c: pixels[..., i] for i, c in enumerate("RGB")})
        else:
            image_module.write_png(str(target), pixels)
    assert len(read_back) == 1 and os.listdir(tmp_path) == []


def test_output_is_renamed_into_place(data, tmp_path):
    """The old file is replaced by rename, never rewritten: its other names keep it."""
    out, other_name = tmp_path / "e.exr", tmp_path / "old.exr"
    out.write_bytes(b"old")
    os.link(out, other_name)
    r = _inproc("envmap", data / "sky.exr", "-o", out, "-q")
    assert r.exit_code == 0, r.output
    assert other_name.read_bytes() == b"old" and out.stat().st_ino != other_name.stat().st_ino


def test_failed_second_output_leaves_the_first_unwritten(data, tmp_path, monkeypatch):
    """envmap stages its EXR, then its preview fails: no new EXR, the old one untouched."""
    from relight_cli import preview as preview_module

    def fail(path, *args, **kwargs):
        raise OutputError("cannot write: simulated", path)
    monkeypatch.setattr(preview_module, "write_preview", fail)
    (tmp_path / "e.exr").write_bytes(b"old")
    _run_inproc_fail(["envmap", data / "sky.exr", "-o", tmp_path / "e.exr", "--preview",
                      tmp_path / "e.png", "-q"], 1, "simulated")
    assert os.listdir(tmp_path) == ["e.exr"] and (tmp_path / "e.exr").read_bytes() == b"old"


# ----------------------------------------------------------------------------- what an output may be


def test_socket_output_is_refused(data, tmp_path):
    """(Needs no root, unlike its block-device twin in test_outputs_and_bad_inputs.py.)"""
    import socket
    server = socket.socket(socket.AF_UNIX)
    server.bind(str(tmp_path / "sock"))
    try:
        _run_inproc_fail(["envmap", data / "sky.exr", "-o", tmp_path / "sock"], 2, "socket")
        assert stat.S_ISSOCK(os.lstat(tmp_path / "sock").st_mode)
        assert os.listdir(tmp_path) == ["sock"]
    finally:
        server.close()


# Where each command computes (the work a refused output must not wait for); each
# raises here, so a refusal that came after work is an "internal error", exit 1.
_WORK = [("relight_cli.envmap", "resample"), ("relight_cli.gaussians.probe", "env_samples"),
         ("relight_cli.gaussians.probe", "scene_samples"), ("relight_cli.features", "discretize_env"),
         ("relight_cli.gaussians.dgsm", "build_dgsm"), ("relight_cli.gaussians.dgsm",
                                                         "build_dgsm_groups"),
         ("relight_cli.gaussians.transfer", "relight_gaussians"),
         ("relight_cli.gaussians.splat", "render"), ("relight_cli.render.shading", "HandRenderer"),
         ("relight_cli.render.gbuffer", "render_gbuffer"),
         ("relight_cli.neural.geometry", "PoseTexels"), ("relight_cli.neural.train", "fit"),
         ("relight_cli.hand.fitting", "fit"), ("relight_cli.metrics.image", "image_metrics"),
         ("relight_cli.metrics.lighting", "lighting_metrics")]


def _link(link: Path, target: Path) -> Path:
    """``link`` → ``target``: an output name of the right extension that is an input."""
    link.symlink_to(target)
    return link


def _refusal_cases():
    from sweep import COMMANDS, DUPLICATES, FIRST_INPUT
    cases = {f"input:{n}": (lambda d, t, n=n: COMMANDS[n][0](
        d, _link(t / f"out{COMMANDS[n][1]}", d / FIRST_INPUT[n])), "also an input")
        for n in sorted(COMMANDS) if FIRST_INPUT[n]}
    cases.update({f"two:{n}": (DUPLICATES[n], "two outputs") for n in sorted(DUPLICATES)})
    cases["input:metrics-image-folder"] = (   # the last pair's prediction is the output
        lambda d, t: ["metrics", "image", t / "pred", t / "gt",
                      "-o", _link(t / "out.json", t / "pred" / "z.exr")], "also an input")
    return cases


@pytest.mark.parametrize("case", sorted(_refusal_cases()))
def test_output_that_is_an_input_is_refused_before_any_work(data, tmp_path, monkeypatch, case):
    """An output that is an input, or two outputs on one file: refused (exit 2) before
    anything is computed, nothing written (inputs may have been read)."""
    import importlib
    for module, name in _WORK:
        def work(*args, _name=name, **kwargs):
            raise AssertionError(f"{_name} ran before the output was refused")
        monkeypatch.setattr(importlib.import_module(module), name, work)
    for folder in ("pred", "gt"):   # a batch of pairs: the last prediction is the output
        (tmp_path / folder).mkdir()
        for name in ("a.exr", "z.exr"):
            shutil.copy(data / "img.exr", tmp_path / folder / name)
    build, word = _refusal_cases()[case]
    args = build(data, tmp_path)
    before = _snapshot(data, tmp_path)
    _run_inproc_fail([*args, "-q"], 2, word)
    assert _snapshot(data, tmp_path) == before


def _user_namespace_mounts() -> str | None:
    from sweep import _full_filesystem_available
    return _full_filesystem_available()


def test_read_only_file_system_is_one_line(data, tmp_path):
    """A read-only mount (a tmpfs mounted ro in a user namespace): one line, exit 1."""
    reason = _user_namespace_mounts()
    if reason:
        pytest.skip(reason)
    from sweep import _quote
    mount = tmp_path / "ro"
    mount.mkdir()
    cmd = " ".join(map(_quote, [relight_executable(), "envmap", data / "sky.exr", "-o",
                                mount / "x.exr", "-q"]))
    script = (f"exec 3>&1 1>&2; mount -t tmpfs -o ro tmpfs {mount} || exit 99; "
              f"{cmd}; rc=$?; ls -a {mount} >&3; exit $rc")
    p = subprocess.run(["unshare", "-rm", "bash", "-c", script], capture_output=True, text=True,
                       timeout=120, env=dict(os.environ, PYTHONWARNINGS="ignore"))
    _assert_one_error(p.returncode, p.stderr, 1, "read-only file system", "x.exr")
    assert sorted(p.stdout.split()) == [".", ".."]


# ----------------------------------------------------------------------------- reading JSON


def _json_readers():
    """name -> a function reading one JSON file the way relight's commands do."""
    from relight_cli.formats import camera, capture, keypoints, lights_json, metrics_json
    from relight_cli.formats import sh_probe_json
    from relight_cli.neural.config import resolve_config
    return {"camera": camera.read_cameras, "lights": lights_json.read_lights,
            "sh-probe": sh_probe_json.read_probe, "capture": capture.read_capture,
            "keypoints": keypoints.read_keypoints, "metrics": metrics_json.read_metrics,
            "config": lambda path: resolve_config("tiny", path)}


NOT_JSON = {"NaN": '{"a": NaN}', "Infinity": '{"a": Infinity}', "-Infinity": '{"a": -Infinity}',
            "1e400": '{"a": 1e400}', "depth-65": "[" * 65 + "]" * 65,
            "long-int": '{"a": ' + "9" * 5000 + "}"}
METRICS_READ_AS_NAN = {"NaN", "Infinity", "-Infinity", "1e400"}


@pytest.mark.parametrize("reader,case", [(r, c) for r in sorted(_json_readers()) for c in NOT_JSON
                                         if not (r == "metrics" and c in METRICS_READ_AS_NAN)])
def test_every_json_reader_refuses_what_json_cannot_hold(tmp_path, reader, case):
    """One parser everywhere: each reader refuses these before looking at the content
    (metrics files read NaN/Infinity/1e400 as NaN so that the gate fails on them)."""
    path = tmp_path / "x.json"
    path.write_text(NOT_JSON[case])
    with pytest.raises(DataError, match="invalid JSON") as caught:
        _json_readers()[reader](str(path))
    assert caught.value.path == str(path)


def test_json_nesting_limit_is_64_levels():
    from relight_cli.formats._common import parse_json
    assert parse_json("[" * 64 + "]" * 64, "x.json") is not None
    with pytest.raises(DataError, match="64 levels"):
        parse_json("[" * 65 + "]" * 65, "x.json")


BOOLEANS = {   # reader -> a file that is valid but for one boolean where a number belongs
    "camera": {"K": [[8, 0, 4], [0, 8, 4], [0, 0, 1]], "R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]],
               "t": [0, 0, 1], "width": True, "height": 8},
    "lights": {"format": "relight/lights", "version": 1, "lights": [{"position": [True, 1, 0]}]},
    "sh-probe": {"format": "relight/sh-probe", "version": 1, "degree": 0,
                 "coefficients": [[1, 1, False]]},
    "keypoints": {"format": "relight/keypoints", "version": 1,
                  "keypoints": [[[0, 0, 0]] * 24 + [[0, 0, True]]]},
    "metrics": {"format": "relight/metrics", "version": True, "kind": "image", "metrics": {}},
    "capture": {"format": "relight/capture", "version": True},
}


@pytest.mark.parametrize("reader", sorted(BOOLEANS))
def test_json_booleans_are_not_numbers(tmp_path, reader):
    path = tmp_path / "x.json"
    path.write_text(json.dumps(BOOLEANS[reader]))
    with pytest.raises(DataError) as caught:
        _json_readers()[reader](str(path))
    assert caught.value.path == str(path)


@pytest.mark.parametrize("case", sorted(NOT_JSON))
def test_json_refusals_are_one_line_exit_1(data, tmp_path, case):
    bad = tmp_path / "probe.json"
    bad.write_text(NOT_JSON[case])
    r = _run_inproc_fail(["relight", data / "ball.ply", "--probe", bad, "-o", tmp_path / "x.ply"],
                         1, "invalid JSON")
    assert str(bad) in r.stderr
    assert os.listdir(tmp_path) == ["probe.json"]


# ----------------------------------------------------------------------------- images


def _exr_channels(path: Path) -> dict:
    import OpenEXR
    return OpenEXR.File(str(path), separate_channels=True).channels()


def test_exr_outputs_are_half_or_float(written):
    """Pixels are 16-bit half or 32-bit float (--half, capture images: half)."""
    folder, _ = written
    kinds = {}
    for path in (p for p in _data_files(written) if p.suffix == ".exr"):
        kinds[path.relative_to(folder)] = {c.pixels.dtype for c in _exr_channels(path).values()}
    assert all(k <= {np.dtype(np.float16), np.dtype(np.float32)} for k in kinds.values()), kinds
    assert kinds[Path("half.exr")] == {np.dtype(np.float16)}
    assert kinds[Path("env.exr")] == {np.dtype(np.float32)}


def test_exr_channels_are_named_by_layer(written):
    """Plain images are R, G, B (+ A); colour layers are layer.R, layer.G, layer.B; every
    other channel is layer.NAME."""
    plain = {"relight/envmap", "relight/render", "relight/capture-image"}
    for path in (p for p in _data_files(written) if p.suffix == ".exr"):
        names = set(_exr_channels(path))
        bare = {n for n in names if "." not in n}
        if _tag(path)[0] in plain:
            assert bare in ({"R", "G", "B"}, {"R", "G", "B", "A"}), (path, names)
        else:
            assert not bare, (path, names)
        layers = {n.rsplit(".", 1)[0] for n in names if n.endswith((".R", ".G", ".B"))}
        assert all({f"{layer}.{c}" for c in "RGB"} <= names for layer in layers), (path, names)
    features = set(_exr_channels(written[0] / "feats.exr"))
    assert {"diffuse.R", "diffuse.G", "diffuse.B"} <= features
    assert {"normal.X", "normal.Y", "normal.Z"} <= set(_exr_channels(written[0] / "render.exr"))


def test_capture_images_of_two_hands_name_each_hands_coverage(tmp_path):
    """A capture image of two hands adds handK.A (hand.npz order) beside R G B A."""
    from relight_cli.formats.capture import read_image_hands, write_image
    ones = np.ones((4, 6), np.float32)
    write_image(str(tmp_path / "x.exr"), np.ones((4, 6, 3), np.float32), ones, "k",
                hand_masks=[ones * 0.25, ones * 0.75])
    assert set(_exr_channels(tmp_path / "x.exr")) == {"R", "G", "B", "A", "hand0.A", "hand1.A"}
    hands = read_image_hands(str(tmp_path / "x.exr"), None, 2)[2]
    np.testing.assert_allclose(hands[:, 0, 0], [0.25, 0.75])


def _srgb(x):
    """IEC 61966-2-1 encoding, written out here independently of relight_cli.tonemap."""
    x = np.clip(x, 0, 1)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)


def test_png_preview_is_reinhard_then_srgb(tmp_path):
    """A rendered image's preview (relight; envmap's lat-long maps): Reinhard et al. 2002,
    Eq. 1-3 (key 0.18 over the log-average luminance, then L / (1 + L) applied to the
    colour's luminance), then sRGB, 8 bits; a fixed exposure (fit-geometry's) replaces
    the key's scale.  One level of tolerance: the 8-bit quantisation."""
    from relight_cli.formats.image import read_image
    from relight_cli.preview import picture_box, write_preview
    rng = np.random.default_rng(4)
    radiance = np.exp(rng.normal(0, 2, (12, 10, 3))).astype(np.float32)  # positive, HDR
    rgb = radiance.astype(np.float64)
    lum = rgb @ [0.2126, 0.7152, 0.0722]
    for exposure, scale in ((None, 0.18 / np.exp(np.mean(np.log(lum)))), (2.0, 2.0)):
        write_preview(str(tmp_path / "p.png"), radiance, exposure=exposure)
        shown, _ = read_image(str(tmp_path / "p.png"))
        x0, y0, k = picture_box(shown.shape, 12, 10)     # the picture under its caption
        shown = shown[y0:y0 + 12 * k:k, x0:x0 + 10 * k:k]
        scaled = scale * lum
        expected = _srgb(rgb * (scaled / (1 + scaled) / lum)[..., None])
        assert np.abs(shown - expected).max() <= 1 / 255 + 1e-6, exposure


# ----------------------------------------------------------------------------- conventions


def test_world_is_right_handed_y_up_in_metres():
    """An upright OpenCV camera on +Z looking at the origin has R = diag(1, −1, −1) (a
    rotation, so the world is right-handed like the camera frame); lat-long env maps
    put +Y at the top row; the built-in hand is hand-sized in metres."""
    from relight_cli.envmap import latlong_directions
    from relight_cli.formats.camera import Camera
    from relight_cli.hand.model import builtin_hand
    cam = Camera.look_at([0, 0, 1], [0, 0, 0])
    np.testing.assert_allclose(cam.R, np.diag([1.0, -1.0, -1.0]), atol=1e-12)
    assert np.linalg.det(cam.R) == pytest.approx(1.0)
    top = latlong_directions(8, 16)[0]
    assert (top[:, 1] > 0.9).all()
    extent = np.ptp(builtin_hand("right", pose=None).fine.vertices, axis=0)
    assert 0.1 < extent.max() < 0.3


def test_untagged_files_of_other_tools_are_read(tmp_path):
    """Env maps, keypoints, cameras and a converted capture's images need no relight tag."""
    from relight_cli.formats.camera import read_camera
    from relight_cli.formats.capture import read_image
    from relight_cli.formats.envmap import read_envmap
    from relight_cli.formats.exr import write_exr
    from relight_cli.formats.keypoints import read_keypoints
    ones = np.ones((4, 8), np.float32)
    write_exr(str(tmp_path / "env.exr"), {c: ones for c in "RGB"})
    write_exr(str(tmp_path / "image.exr"), {c: ones for c in "RGBA"})
    assert read_envmap(str(tmp_path / "env.exr")).radiance.shape == (4, 8, 3)
    assert read_image(str(tmp_path / "image.exr"))[1].shape == (4, 8)
    (tmp_path / "kp.json").write_text(json.dumps([[[0.0, 0.0, 0.0]] * 25]))
    assert read_keypoints(str(tmp_path / "kp.json")).positions.shape == (1, 25, 3)
    (tmp_path / "cam.json").write_text(json.dumps(BOOLEANS["camera"] | {"width": 8}))
    assert read_camera(str(tmp_path / "cam.json")).width == 8


@pytest.mark.parametrize("literal", ["NaN", "Infinity", "-Infinity", "1e400"])
def test_metrics_files_read_non_finite_numbers_as_nan(data, tmp_path, literal):
    from relight_cli.formats.metrics_json import read_metrics
    text = (data / "m.json").read_text()
    bad = tmp_path / "m.json"
    bad.write_text(re.sub(r'"psnr": [^,}]+', f'"psnr": {literal}', text, count=1))
    assert math.isnan(read_metrics(str(bad))["metrics"]["psnr"])


def test_the_promise_map_names_existing_tests():
    """The map in this docstring points at tests that exist (here or in the named files)."""
    doc = __doc__.split("==\n", 1)[1]
    named = set(re.findall(r"\b(test_\w+)\b(?!\.py)", doc))
    defined = set(re.findall(r"^def (test_\w+)\(", "".join(
        p.read_text() for p in (ROOT / "tests").rglob("test_*.py")), re.M))
    assert len(named) > 40 and named <= defined, sorted(named - defined)


def test_stdin_left_at_a_terminal_is_a_usage_error(data, tmp_path):
    """`--probe -` with stdin on a terminal (a pty here): exit 2 before any work, rather
    than waiting for someone to type JSON."""
    import pty
    controller, terminal = pty.openpty()
    try:
        p = subprocess.run([relight_executable(), "relight", str(data / "ball.ply"), "--probe",
                            "-", "-o", str(tmp_path / "x.ply")], stdin=terminal,
                           capture_output=True, text=True, timeout=60)
    finally:
        os.close(terminal)
        os.close(controller)
    _assert_one_error(p.returncode, p.stderr, 2, "terminal")
    assert os.listdir(tmp_path) == []
