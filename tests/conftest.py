"""Shared test fixtures: the real-data folder, CLI runners, the run's tiny trained models."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = (ROOT / ".." / "shared" / "data").resolve()

# Under pytest-xdist (``make test`` runs one worker per core) every worker, and every
# ``relight`` it starts, computes on one thread: two workers each running torch's default
# of one thread per core oversubscribe the machine, and OpenMP's spinning threads then
# run several times slower than one thread each.  Set before any test imports torch.
if os.environ.get("PYTEST_XDIST_WORKER"):
    for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[_var] = "1"


def shared_path(*parts: str) -> Path:
    """A file under ../shared/data, or skip the test when it is absent."""
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"real test data not available: {path}")
    return path


@pytest.fixture
def shared():
    return shared_path


def relight_executable() -> str:
    """The installed console script (next to this interpreter, else on PATH)."""
    exe = Path(sys.executable).with_name("relight")
    if exe.exists():
        return str(exe)
    found = shutil.which("relight")
    if not found:
        pytest.skip("the relight console script is not installed")
    return found


def run_relight(*args: str, cwd=None, timeout: float = 300) -> subprocess.CompletedProcess:
    """Run the installed ``relight`` console script in a subprocess."""
    env = dict(os.environ)
    env.setdefault("PYTHONWARNINGS", "ignore")
    return subprocess.run([relight_executable(), *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, timeout=timeout, env=env)


@pytest.fixture
def run_cli():
    """In-process CliRunner call of the relight group: returns click's Result."""
    from click.testing import CliRunner

    from relight_cli.cli import cli

    def run(*args):
        runner = CliRunner()
        return runner.invoke(cli, [str(a) for a in args], catch_exceptions=False)
    return run


@pytest.fixture(scope="session")
def tiny_models(tmp_path_factory):
    """The run's shared tiny captures and models (tests/models.py): ``tiny_models.get(kind,
    capture_args, train_args, config=None, teacher=None) -> Path``, each made once per run,
    by whichever xdist worker asks first."""
    from models import TinyModels
    base = tmp_path_factory.getbasetemp()
    # under xdist each worker's basetemp is RUN/popen-gwN: the cache is shared in RUN
    root = (base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base) / "tiny-models"
    return TinyModels(root)


#: The test files that take longest under ``make test`` (seconds summed over their tests,
#: two workers on a 2-core AMD EPYC, 2026-12-04: readme_example 147, neural/test_student 145,
#: neural/test_teacher 125, study_gate 96, neural_linear 74, outputs_and_bad_inputs 69; the
#: whole suite 1005).  They are collected first so that xdist (``--dist loadfile
#: --no-loadscope-reorder``) hands them out first: by default it orders files by how many
#: tests they hold, which left the single two-minute README pipeline running alone at the end.
#: Paths are relative to tests/ (two files may share a basename: tests/formats/test_camera.py).
SLOW_FILES = ("system/test_readme_example.py", "neural/test_student.py", "neural/test_teacher.py",
              "system/test_study_gate.py", "neural/test_linear.py",
              "system/test_outputs_and_bad_inputs.py")
TESTS = Path(__file__).resolve().parent


def _tests_path(path: Path) -> str:
    try:
        return path.resolve().relative_to(TESTS).as_posix()
    except ValueError:
        return path.name


def pytest_collection_modifyitems(config, items):
    """The slow files first (in :data:`SLOW_FILES` order); every other test keeps its place."""
    rank = {name: i for i, name in enumerate(SLOW_FILES)}
    items.sort(key=lambda item: rank.get(_tests_path(item.path), len(rank)))


def as_foreign_ply(path) -> None:
    """Strip relight's ``obj_info`` lines from a PLY written by ``write_gaussians``, so it
    reads as a 3DGS file from another tool (sRGB colours, formats/gaussians_ply.md)."""
    data = Path(path).read_bytes()
    head, sep, body = data.partition(b"end_header\n")
    lines = [line for line in head.split(b"\n") if not line.startswith(b"obj_info relight.")]
    Path(path).write_bytes(b"\n".join(lines) + sep + body)
