"""What every ``benchmarks/bench_*.py`` shares: options, the machine's own limits, plots.

* :func:`parser` gives every benchmark ``--out DIR`` (default ``benchmarks/out/``) and
  ``--quick`` (a smoke run: ``make benchmarks QUICK=1`` runs them all in a few minutes);
  :func:`start` checks for matplotlib first, so a runner without it stops at once with
  one line instead of after minutes of work.
* Options are checked as they are parsed: :class:`ArgumentParser` (what :func:`parser`
  makes) reports an unknown option or a bad value as one line ``<script>: error: …``,
  exit 2, with no usage block (``--help`` is unchanged); :func:`integer`, :func:`number`
  and :func:`integers` are the ``type=`` of counts, sizes and lists.
* Paths are checked before any work, nothing created until all pass (DESIGN.md "How
  every command behaves"): :func:`check_out_dir` (an output folder that is a file or
  cannot be made: one line, exit 2), :func:`check_out_file`, :func:`read_report` (a
  damaged JSON record: one line, exit 1), and :func:`run_main`, every script's entry
  point, turns a RelightError or OSError into one line ``<script>: error: … (<path>)``.
* :func:`machine_limits` measures, in the same run, the ceilings the benchmark's numbers
  are read against: float32 GEMM GFLOP/s (torch, else numpy), main-memory copy
  bandwidth, and on request raw embree occlusion rays/s, erf throughput and the dense
  3×3 convolution rate of torch's own conv kernels (``conv=True``: then ``peak_gflops``
  is the best of GEMM and conv, on ``torch_threads`` threads).
* :class:`ConvFlops` counts the FLOPs of the convolutions a model really runs (forward
  hooks, 2 per multiply-add, the backward they imply); :func:`rate_cell` prints a
  measured GFLOP/s, or ``inconsistent measurement`` where it exceeds the same run's peak.
* :func:`plot` draws time against error: every curve, each point labelled, log axes,
  a grid, and the machine line under the axes; exact (zero) errors sit on the axis
  floor with their own marker instead of vanishing from a log plot.
* The teacher benchmarks' capture, physical upper bound, timed training and env-map
  render cost (``bench_teacher.py``, ``bench_linear.py``): :func:`make_capture`,
  :func:`physical_upper_bound`, :func:`train_variant`, :func:`env_render_cost`,
  :func:`write_plot`.
* The studies' captures (``study_hands.py``, ``bench_presets.py``): the env maps
  (:func:`env_specs`), the capture columns (:data:`HANDS`), the one place a capture is
  made (:func:`synth_capture`), a scale's capture made once under its settings' key
  (:func:`study_capture`), and :func:`write_json` (atomic).

How a model is judged (converged, verdict, gate: DESIGN.md) is not here but in the
library, :mod:`relight_cli.neural.judging`, which every script calls.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import platform
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
OUT = HERE / "out"
ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:          # run as a script from anywhere: import the checkout
    sys.path.insert(0, str(ROOT))
#: the studies' sizes (tiny: the CI gate's; converged: every model at its cpu preset)
SCALES = HERE / "studies" / "scales.json"
#: the shared Poly Haven HDRIs, when this checkout sits beside them
HDRI_DIR = (ROOT / ".." / "shared" / "data" / "envmaps" / "polyhaven").resolve()


class ArgumentParser(argparse.ArgumentParser):
    """argparse whose errors (an unknown option, a value of the wrong type or out of range,
    a script's own ``ap.error``) are one line ``<script>: error: <what>``, exit 2, without
    argparse's usage block (DESIGN.md "How every command behaves"); ``--help`` is argparse's
    own."""

    def error(self, message):
        fail(self.prog, " ".join(str(message).split()), None, 2)


def integer(minimum: int):
    """argparse ``type``: an integer ≥ ``minimum`` (else the one-line usage error)."""
    def parse(text):
        try:
            value = int(text)
        except ValueError:
            value = None
        if value is None or value < minimum:
            raise argparse.ArgumentTypeError(f"expected an integer ≥ {minimum}, got {text!r}")
        return value
    parse.__name__ = f"integer ≥ {minimum}"
    return parse


def number(minimum: float):
    """argparse ``type``: a finite number ≥ ``minimum``."""
    def parse(text):
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not (math.isfinite(value) and value >= minimum):
            raise argparse.ArgumentTypeError(f"expected a finite number ≥ {minimum:g}, "
                                             f"got {text!r}")
        return value
    parse.__name__ = f"number ≥ {minimum:g}"
    return parse


def integers(minimum: int, sep: str = ",", count: int | None = None):
    """argparse ``type``: integers ≥ ``minimum`` joined by ``sep`` (``25,100,200``;
    ``128x256`` with ``sep="x", count=2``), checked and given back as the text."""
    one = integer(minimum)

    def parse(text):
        parts = text.split(sep)
        try:
            if count is not None and len(parts) != count:
                raise argparse.ArgumentTypeError
            for part in parts:
                one(part)
        except argparse.ArgumentTypeError:
            how_many = "integers" if count is None else f"{count} integers"
            raise argparse.ArgumentTypeError(f"expected {how_many} ≥ {minimum} joined by "
                                             f"{sep!r}, got {text!r}") from None
        return text
    parse.__name__ = f"integers ≥ {minimum}"
    return parse


def parser(doc: str, quick: str = "a smoke run: fewer, smaller configurations"):
    """argparse with the options every benchmark has; errors are one line
    (:class:`ArgumentParser`)."""
    ap = ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=str(OUT), metavar="DIR",
                    help="folder for the table (.md), data (.json/.csv) and plot (.png) "
                         "[default: benchmarks/out/]")
    ap.add_argument("--quick", action="store_true", help=quick)
    return ap


def start(args, name: str, folders: dict | None = None) -> Path:
    """Check every folder the run writes (``--out`` and ``folders``: option → path; one
    line and exit 2 if one cannot be), that matplotlib is there (one line and exit 1 if
    not), then make ``--out``: nothing is created before every check has passed."""
    check_out_dir(name, args.out, "--out")
    for option, path in (folders or {}).items():
        check_out_dir(name, path, option)
    require_matplotlib(name)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    return out


# ------------------------------------------------------------------ paths and errors
#
# Benchmarks are not product commands, but users run them: like the CLI (DESIGN.md "How
# every command behaves") a bad path is one line ``<script>: error: <what> (<path>)``,
# exit 2 (usage) or 1 (data), no traceback, nothing created, and it is found before any
# work.


def fail(name: str, message: str, path=None, code: int = 1):
    """Print ``<name>: error: <message> (<path>)`` on stderr and exit ``code``."""
    line = f"{name}: error: {message}" + ("" if path is None else f" ({path})")
    try:
        sys.stderr.flush()
    except (OSError, ValueError):
        pass
    print(line, file=sys.stderr, flush=True)
    raise SystemExit(code)


def _folder_problem(path: Path) -> str | None:
    """Why ``path`` cannot be (made into) a folder the run writes into, or None."""
    p = Path(os.path.abspath(path))
    if p.exists():
        if not p.is_dir():
            return "is not a folder"
        if not os.access(p, os.W_OK | os.X_OK):
            return "folder is not writable"
        return None
    parent = p.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        return f"cannot create the folder: {parent} is not a folder"
    if not os.access(parent, os.W_OK | os.X_OK):
        return f"cannot create the folder: {parent} is not writable"
    return None


def check_out_dir(name: str, path, option: str = "--out") -> Path:
    """``path`` is a writable folder, or can be made one; else one line, exit 2.
    Creates nothing."""
    if path is None or str(path) == "":
        fail(name, f"{option} needs a folder", None, 2)
    problem = _folder_problem(Path(path))
    if problem:
        fail(name, f"{option}: {problem}", path, 2)
    return Path(path)


def check_out_file(name: str, path, option: str) -> Path:
    """``path`` is a file the run can write: not a folder, its folder there and writable
    (never made for it); else one line, exit 2.  Creates nothing."""
    p = Path(path)
    if p.is_dir():
        fail(name, f"{option}: is a folder, expected a file", path, 2)
    parent = Path(os.path.abspath(p)).parent
    if not parent.exists():
        fail(name, f"{option}: no such folder: {parent}", path, 2)
    if not parent.is_dir():
        fail(name, f"{option}: {parent} is not a folder", path, 2)
    if not os.access(parent, os.W_OK | os.X_OK):
        fail(name, f"{option}: folder is not writable: {parent}", path, 2)
    if p.exists() and not os.access(p, os.W_OK):
        fail(name, f"{option}: file is not writable", path, 2)
    return p


def read_report(name: str, path) -> dict:
    """A benchmark's JSON record (a table, a report): a dict, or one line and exit 1
    (missing, unreadable, damaged JSON, not an object)."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        fail(name, "no such file", path, 1)
    except IsADirectoryError:
        fail(name, "is a folder, expected a JSON file", path, 1)
    except UnicodeDecodeError:
        fail(name, "damaged JSON: not UTF-8 text", path, 1)
    except OSError as exc:
        fail(name, f"cannot read: {(exc.strerror or str(exc)).lower()}", path, 1)
    try:
        record = json.loads(text)
    except json.JSONDecodeError as exc:
        fail(name, f"damaged JSON: {exc.msg} at line {exc.lineno} column {exc.colno}", path, 1)
    except RecursionError:
        fail(name, "damaged JSON: nested too deeply", path, 1)
    if not isinstance(record, dict):
        fail(name, "damaged JSON: expected an object", path, 1)
    return record


def run_main(name: str, main, *args, **kwargs):
    """Run a script's ``main``: a RelightError or an OSError (a file that vanished, a full
    disk) becomes one line and exit 1 (2 for usage), never a traceback."""
    try:
        return main(*args, **kwargs)
    except OSError as exc:
        where = exc.filename if exc.filename is not None else None
        reason = (exc.strerror or str(exc) or type(exc).__name__).lower()
        fail(name, reason, where, 1)
    except Exception as exc:            # noqa: BLE001 — only RelightError is reworded
        try:
            from relight_cli.errors import RelightError
        except ImportError:             # pragma: no cover
            raise exc from None
        if isinstance(exc, RelightError):
            fail(name, str(exc), None, getattr(exc, "exit_code", 1))
        raise


def require_matplotlib(name: str) -> None:
    try:
        import matplotlib
    except ImportError:
        sys.exit(f"{name}: error: matplotlib is not installed; pip install 'relight[bench]' "
                 f"(make benchmarks does)")
    matplotlib.use("Agg")


# ------------------------------------------------------------------ machine limits


def _best(fn, repeat: int) -> float:
    fn()                                         # warm-up (allocation, thread pool start)
    best = math.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def gemm_gflops(n: int = 1024, repeat: int = 5) -> float:
    """float32 matrix multiply GFLOP/s, best of ``repeat`` (torch if installed, else numpy)."""
    try:
        import torch
        a, b = torch.randn(n, n), torch.randn(n, n)
        seconds = _best(lambda: torch.mm(a, b), repeat)
    except ImportError:
        import numpy as np
        rng = np.random.default_rng(0)
        a, b = (rng.standard_normal((n, n), dtype=np.float32) for _ in range(2))
        seconds = _best(lambda: a @ b, repeat)
    return 2 * n ** 3 / seconds / 1e9


def memory_gbs(mbytes: int = 128, repeat: int = 3) -> float:
    """Main-memory bandwidth, GB/s: bytes read + written by a numpy copy of ``mbytes`` MB."""
    import numpy as np
    src = np.ones(mbytes * 2 ** 20 // 4, np.float32)
    dst = np.empty_like(src)
    seconds = _best(lambda: np.copyto(dst, src), repeat)
    return 2 * src.nbytes / seconds / 1e9


def embree_mrays(rays: int = 500_000, repeat: int = 3) -> float:
    """Raw embree occlusion rays/s (millions), one call, random rays from inside a
    20k-triangle sphere (every ray hits): the tracer's own ceiling on this machine."""
    import numpy as np
    import trimesh

    from relight_cli.raytrace import RayScene
    sphere = trimesh.creation.icosphere(subdivisions=5)
    scene = RayScene([(np.asarray(sphere.vertices), np.asarray(sphere.faces))])
    rng = np.random.default_rng(0)
    origins = rng.uniform(-0.3, 0.3, (rays, 3))
    dirs = rng.normal(size=(rays, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    seconds = _best(lambda: scene.occluded(origins, dirs), repeat)
    return rays / seconds / 1e6


def erf_gelems(n: int = 4_000_000, repeat: int = 3) -> float:
    """scipy.special.erf on float32, billions of values per second (DGSM's inner function)."""
    import numpy as np
    from scipy.special import erf
    x = np.linspace(-4, 4, n, dtype=np.float32)
    out = np.empty_like(x)
    seconds = _best(lambda: erf(x, out=out), repeat)
    return n / seconds / 1e9


#: (in channels, out channels, size) of the dense 3×3 convolutions :func:`conv_gflops`
#: times: the widths and sizes of the teacher's and the student's big layers.
CONV_SHAPES = ((64, 64, 128), (128, 128, 128), (256, 256, 64))


def conv_gflops(repeat: int = 5, shapes=CONV_SHAPES) -> float:
    """float32 GFLOP/s of torch's own dense 3×3 convolutions (batch 1, stride 1, padded;
    oneDNN on x86), in inference mode: the best of ``repeat`` over ``shapes`` and both
    memory layouts.  On CPUs where the GEMM library runs a generic code path (MKL on AMD)
    the conv kernels are faster than ``torch.mm``: this is the ceiling a network's convs
    are read against, with :func:`gemm_gflops`."""
    import torch
    best = 0.0
    with torch.inference_mode():
        for cin, cout, n in shapes:
            conv = torch.nn.Conv2d(cin, cout, 3, padding=1).eval()
            x = torch.randn(1, cin, n, n)
            flops = 2.0 * cin * cout * 9 * n * n
            for layout in (torch.contiguous_format, torch.channels_last):
                c = conv.to(memory_format=layout)
                xl = x.contiguous(memory_format=layout)
                best = max(best, flops / _best(lambda: c(xl), repeat) / 1e9)
    return best


def flop_peak(limits: dict) -> dict:
    """Measure GEMM and conv again and keep, in ``limits``, the best of every measurement
    (``peak_gflops``): call it at the end of a run, so that a machine busier at the start
    than later does not leave a ceiling below what the run itself reached."""
    import torch
    if limits.get("torch_threads") not in (None, torch.get_num_threads()):
        raise RuntimeError(f"torch threads changed during the run: {limits['torch_threads']} "
                           f"→ {torch.get_num_threads()}")
    limits["gemm_gflops"] = max(limits.get("gemm_gflops", 0.0), gemm_gflops())
    limits["conv_gflops"] = max(limits.get("conv_gflops", 0.0), conv_gflops())
    limits["peak_gflops"] = max(limits["gemm_gflops"], limits["conv_gflops"],
                                limits.get("gemm_gflops_2048", 0.0))
    limits["peak_measurements"] = limits.get("peak_measurements", 1) + 1
    return limits


def set_threads(threads: int | None) -> int:
    """torch's intra-op threads for the whole run (None: keep torch's default, which
    follows OMP_NUM_THREADS); returns the count every measurement of the run uses."""
    import torch
    if threads:
        torch.set_num_threads(int(threads))
    return torch.get_num_threads()


class ConvFlops:
    """FLOPs of the convolutions (and linear layers) ``model`` runs while counting.

    Forward: 2·(C_in/groups)·C_out·k_h·k_w·H_out·W_out per conv per sample (2 per
    multiply-add), 2·in·out per linear row; bias adds, activations, resizes and losses
    are not counted (a lower bound of the arithmetic, so a rate computed from it is a
    lower bound too).  Backward, when autograd records the pass: the weight gradient
    costs one forward, the input gradient another — only where the layer's input needs a
    gradient (not for the first layer), so a training pass is ≈ 3× its forward.
    ``forward``/``backward``/``total`` accumulate; counting stops at :meth:`close`.
    """

    def __init__(self, model, training_only: bool = False):
        import torch
        self.forward = 0.0
        self.backward = 0.0
        self.training_only = training_only
        self._hooks = [m.register_forward_hook(self._hook) for m in model.modules()
                       if isinstance(m, (torch.nn.Conv2d, torch.nn.Linear))]

    def _hook(self, module, inputs, output):
        import torch
        if self.training_only and not module.training:
            return
        if isinstance(module, torch.nn.Conv2d):
            kh, kw = module.kernel_size
            flops = 2.0 * output.numel() * (module.in_channels // module.groups) * kh * kw
        else:
            flops = 2.0 * output.numel() * module.in_features
        self.forward += flops
        if torch.is_grad_enabled() and output.requires_grad:
            if module.weight.requires_grad:
                self.backward += flops
            if inputs[0].requires_grad:
                self.backward += flops

    @property
    def total(self) -> float:
        return self.forward + self.backward

    def close(self) -> None:
        for h in self._hooks:
            h.remove()
        self._hooks = []

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


def rate_cell(gflops: float, peak: float, threads: int | None = None,
              peak_threads: int | None = None) -> str:
    """A measured GFLOP/s for a table: the number, or ``inconsistent measurement`` (with
    both numbers) where it exceeds the same run's peak or was measured on another number
    of threads than the peak — a rate above the machine's own ceiling means the FLOP
    count or the timing is wrong, and must not be read as a result."""
    if threads is not None and peak_threads is not None and threads != peak_threads:
        return (f"**inconsistent measurement** ({gflops:.1f} on {threads} threads, peak on "
                f"{peak_threads})")
    if not math.isfinite(gflops) or gflops > peak:
        return f"**inconsistent measurement** ({gflops:.1f} > peak {peak:.1f})"
    return f"{gflops:.1f}"


def consistent(gflops: float, peak: float) -> bool:
    return math.isfinite(gflops) and gflops <= peak


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "?"


def run_command(script: str, argv: list[str]) -> str:
    """The command that made a run, relative to the checkout, ``--out`` left out (outputs
    never hold a machine's paths)."""
    args, skip = [], False
    for a in argv:
        if skip:
            skip = False
            continue
        if a == "--out":
            skip = True
            continue
        if a.startswith("--out="):
            continue
        args.append(a)
    return " ".join(["python", f"benchmarks/{script}", *args])


def run_description(command: str, quick: bool, seconds: float) -> str:
    """One line: the command, its mode and the wall time of the run."""
    mode = "quick mode (`--quick`, a smoke run)" if quick else "full mode"
    m, s = divmod(int(round(seconds)), 60)
    return f"Made by `{command}` in {mode}; the whole run took {m} min {s} s of wall-clock time."


def load_average() -> str:
    try:
        return " ".join(Path("/proc/loadavg").read_text().split()[:3])
    except OSError:
        return "?"


def machine_limits(embree: bool = False, erf: bool = False, conv: bool = False) -> dict:
    """The machine and its measured ceilings (this run): see the module docstring."""
    limits = {"platform": platform.platform(), "cpu_model": cpu_model(),
              "python": platform.python_version(),
              "cpus": os.cpu_count(), "load_average": load_average()}
    try:
        import torch
        limits["torch"] = torch.__version__
        limits["torch_threads"] = torch.get_num_threads()
    except ImportError:
        pass
    limits["gemm_gflops"] = gemm_gflops()
    if conv:
        limits["conv_gflops"] = conv_gflops()
        limits["peak_gflops"] = max(limits["gemm_gflops"], limits["conv_gflops"])
    limits["memory_gbs"] = memory_gbs()
    if embree:
        limits["embree_mrays"] = embree_mrays()
    if erf:
        limits["erf_gelems"] = erf_gelems()
    return limits


def machine_line(m: dict) -> str:
    """One line for tables and plots."""
    cpus = f"{m['cpus']} CPUs" + (f" ({m['cpu_model']})" if m.get("cpu_model") else "")
    parts = [f"{cpus} (load {m['load_average']})"]
    if "torch" in m:
        parts.append(f"torch {m['torch']} on {m['torch_threads']} threads")
    parts.append(f"fp32 GEMM {m['gemm_gflops']:.1f} GFLOP/s")
    if "conv_gflops" in m:
        parts.append(f"fp32 3×3 conv {m['conv_gflops']:.1f} GFLOP/s")
    parts.append(f"memory copy {m['memory_gbs']:.1f} GB/s")
    if "embree_mrays" in m:
        parts.append(f"embree {m['embree_mrays']:.2f} Mrays/s")
    if "erf_gelems" in m:
        parts.append(f"erf {m['erf_gelems']:.2f} Gvalues/s")
    return f"Machine: {m['platform']}, " + ", ".join(parts) + " (measured in this run)."


# ------------------------------------------------------------------ plots


def figure(panels: int = 1, width: float = 6.4, height: float = 4.4):
    """A matplotlib figure with ``panels`` axes side by side."""
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, panels, figsize=(width * panels, height), squeeze=False)
    return fig, list(axes[0])


def plot(ax, curves: dict, xlabel: str, ylabel: str, title: str = "", logx: bool = True,
         logy: bool = True, labels: bool = True) -> None:
    """Every curve of ``curves`` {name: [(x, y) or (x, y, point label), ...]} on ``ax``.

    Each curve is drawn in order of x (cost); points whose x or y is not finite are
    left out; on a log axis, y ≤ 0 (an exact result) is drawn on the axis floor with a
    downward triangle.
    """
    finite = [(p[0], p[1]) for pts in curves.values() for p in pts
              if _finite(p[0]) and _finite(p[1])]
    positive = [y for _, y in finite if y > 0]
    floor = (min(positive) / 10 if positive else 1e-12) if logy else None
    exact_shown = False
    for name, pts in curves.items():
        pts = sorted((p for p in pts if _finite(p[0]) and _finite(p[1])
                      and (not logx or p[0] > 0)), key=lambda p: float(p[0]))
        if not pts:
            continue
        xs = [p[0] for p in pts]
        ys = [p[1] if not logy or p[1] > 0 else floor for p in pts]
        line, = ax.plot(xs, ys, marker="o", markersize=4, linewidth=1.5, label=name)
        zero = [(x, floor) for x, (_, y, *_) in zip(xs, pts) if logy and y <= 0]
        if zero:
            ax.plot(*zip(*zero), linestyle="none", marker="v", markersize=7,
                    color=line.get_color(), label=None if exact_shown else "exact (0)")
            exact_shown = True
        if labels:
            for x, y, p in zip(xs, ys, pts):
                if len(p) > 2 and p[2]:
                    ax.annotate(str(p[2]), (x, y), textcoords="offset points", xytext=(4, 3),
                                fontsize=7, color=line.get_color())
    if logx:
        ax.set_xscale("log")
    if logy:
        ax.set_yscale("log")
    ax.grid(True, which="major", alpha=0.5)
    ax.grid(True, which="minor", alpha=0.15)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title, fontsize=10)
    if any(curves.values()):
        ax.legend(fontsize=7, loc="best")


def save(fig, path: Path, machine: dict | None = None) -> Path:
    """Write ``fig`` as a PNG (no time stamp), the machine line under the axes."""
    import matplotlib.pyplot as plt
    if machine is not None:
        fig.text(0.01, 0.005, machine_line(machine), fontsize=6.5, color="0.35", ha="left",
                 va="bottom", wrap=True)
    fig.tight_layout(rect=(0, 0.05 if machine is not None else 0, 1, 1))
    fig.savefig(path, dpi=110, metadata={"Software": None})
    plt.close(fig)
    print(f"wrote {path}", flush=True)
    return path


def _finite(v) -> bool:
    try:
        return math.isfinite(float(v))
    except (TypeError, ValueError):
        return False


class Tee:
    """Print lines to stdout and keep them (benchmarks whose tables are printed as they go):
    ``log("a", "b")`` prints and keeps two lines."""

    def __init__(self):
        self.lines: list[str] = []

    def __call__(self, *lines):
        for line in lines:
            print(line, flush=True)
            self.lines.extend(str(line).split("\n"))

    def text(self) -> str:
        return "\n".join(self.lines) + "\n"


class recorded:
    """``with recorded() as rec:`` — everything printed inside still reaches stdout and is
    kept in ``rec.text`` (benchmarks whose tables are printed piece by piece)."""

    def __enter__(self):
        import contextlib
        import io

        class _Both(io.TextIOBase):
            def __init__(self, first):
                self.first, self.copy = first, io.StringIO()

            def write(self, text):
                self.first.write(text)
                self.copy.write(text)
                return len(text)

            def flush(self):
                self.first.flush()

        self._stream = _Both(sys.stdout)
        self._redirect = contextlib.redirect_stdout(self._stream)
        self._redirect.__enter__()
        return self

    def __exit__(self, *exc):
        self._redirect.__exit__(*exc)
        self.text = self._stream.copy.getvalue()
        return False


# ------------------------------------------------------------------ the studies' captures

#: synth-capture's HAND argument and motion seed per capture column: one subject (the
#: default --skin-seed 0) captured right, left and with two interacting hands; the
#: two-hand capture's own motion seed makes every one of its poses new to the teachers
HANDS = {"right": ("builtin:right", 0), "left": ("builtin:left", 0), "both": ("builtin:two", 3)}
#: bump when synth-capture renders the same settings differently (cached captures)
CAPTURE_VERSION = 2


def env_specs() -> dict:
    """The env maps of the studies: the shared Poly Haven HDRIs when present (the last two
    sorted ones held out: never trained on, the captures' ground-truth env renders),
    else built-ins."""
    hdris = sorted(str(p) for p in HDRI_DIR.glob("*.hdr")) if HDRI_DIR.is_dir() else []
    if len(hdris) >= 3:
        return {"source": f"Poly Haven HDRIs ({HDRI_DIR})",
                "train": ["builtin:sky", "builtin:studio", "builtin:uniform"] + hdris[:-2],
                "eval": hdris[-2:]}
    return {"source": "built-in env maps (the shared Poly Haven HDRIs are absent)",
            "train": ["builtin:studio", "builtin:uniform", "builtin:point"],
            "eval": ["builtin:sky"]}


def digest(obj) -> str:
    """A cache key: 16 hex digits of the SHA-256 of ``obj``'s sorted JSON."""
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:16]


def synth_capture(folder: Path, hand: str, seed: int, capture: dict, eval_envs: list) -> None:
    """The one place the studies make a capture: ``relight synth-capture``'s job
    (:func:`relight_cli.jobs.synth_capture.make_capture`)."""
    from relight_cli.jobs.synth_capture import make_capture
    # every setting the scale (or a study's stage) names reaches the stage: an unknown one
    # is an error, not a default (a stage's keyframe_every was once dropped here); a
    # scale that does not name eval_env_space or ggx_shadowing keeps the renders its cached
    # captures (and the committed tables made from them) have: the studies' stage is
    # URHand's Schlick-Smith lobe until a scale says otherwise
    make_capture(str(folder), hand, seed=seed, eval_envs=eval_envs,
                 **{"eval_env_space": "vertices", "ggx_shadowing": "schlick", **capture})


def study_capture(work: Path, log, scale: str = "converged", stage: dict | None = None):
    """``(folder, env maps)``: the study scale's right-hand capture, made once under
    ``work`` (``capture-KEY``, keyed by its settings); ``stage`` overrides some of the
    scale's capture settings (e.g. ``{"lights": 128}``: another capture, its own key)."""
    settings = json.loads(SCALES.read_text())[scale]
    settings["capture"].update(stage or {})
    envs = env_specs()
    key = digest({"capture": settings["capture"], "eval": envs["eval"], "v": CAPTURE_VERSION})
    folder = Path(work) / f"capture-{key}"
    if not (folder / "capture.json").is_file():
        log(f"making the capture {folder}")
        synth_capture(folder, *HANDS["right"], settings["capture"], envs["eval"])
    return folder, envs


def write_json(path: Path, obj, ensure_ascii: bool = False) -> None:
    """``obj`` as indented JSON, atomically (the project's output helper): an interrupted
    run leaves no half file."""
    from relight_cli.fileio import write_text_atomic
    write_text_atomic(str(path), json.dumps(obj, indent=1, ensure_ascii=ensure_ascii) + "\n")


# ------------------------------------------------------------------ the teacher benchmarks
# (bench_teacher.py and bench_linear.py: their capture, baselines and timed training)


def timed_teacher_task(data, cfg, evaluate: bool = True):
    """A TeacherTask that times every training step (data, forward, backward, Adam;
    validation excluded) and counts the conv FLOPs each step runs; ``evaluate=False``
    skips the final validation (a throughput run does not need its scores)."""
    from relight_cli.neural.train import TeacherTask

    class Timed(TeacherTask):
        def evaluate(self, model, device):
            return super().evaluate(model, device) if evaluate else {}

        def __init__(self):
            super().__init__(data, cfg)
            self.steps = []              # (seconds, flops fwd+bwd, flops fwd) per step
            self.flops = None

        def build(self, device, resume=None):
            model = super().build(device, resume)
            self.flops = ConvFlops(model, training_only=True)
            return model

        def before_step(self, optimizer, step):
            self._start = (time.perf_counter(), self.flops.total, self.flops.forward)

        def after_step(self, step, world):
            t0, total, forward = self._start
            self.steps.append((time.perf_counter() - t0, self.flops.total - total,
                               self.flops.forward - forward))
    return Timed()


def make_capture(folder: Path, two_hands: bool, frames: int, quick: bool) -> Path:
    """The benchmark's capture, through ``relight synth-capture``'s job."""
    from relight_cli.jobs import synth_capture as J
    settings = dict(cameras=4 if quick else 6, lights=32, group=4, res=48 if quick else 64,
                    tex_res=128, aa=1, eval_poses=2, eval_cameras=2,
                    eval_envs=("builtin:sky", "builtin:studio"))
    if two_hands:
        from relight_cli.formats.hand_npz import write_hand
        from relight_cli.hand.model import builtin_hand
        from relight_cli.hand.scene import two_hands as pair
        from relight_cli.render.capture import hand_motion
        motion = folder.parent / f"{folder.name}_motion.npz"
        write_hand(str(motion), pair(hand_motion(builtin_hand("right"), frames, seed=5)))
        J.make_capture(str(folder), str(motion), motion="file", **settings)
    else:
        J.make_capture(str(folder), frames=frames, **settings)
    return folder


def physical_upper_bound(folder: Path) -> dict:
    """Held-out frames re-rendered with the stage's own renderer and true materials."""
    import numpy as np

    from relight_cli.formats import capture as C
    from relight_cli.formats.lights_json import Lights
    from relight_cli.neural.data import CaptureData
    from relight_cli.neural.train import _metrics
    from relight_cli.render.appearance import hand_materials
    from relight_cli.render.capture import FrameRenderer, Plan, StageSettings

    data = CaptureData(str(folder), 32, holdout=0.25)
    s = data.capture.settings
    settings = StageSettings(**{k: v for k, v in s.items() if k in StageSettings.__dataclass_fields__})
    materials = hand_materials(data.hand, "fine", max(settings.tex_res, 256), settings.seed)
    plan = Plan(data.hand, data.capture.cameras,
                Lights.from_radiant_intensity(data.capture.light_positions,
                                              data.capture.light_intensity),
                data.capture.light_names, data.capture.frames, np.zeros(3), data.capture.key)
    renderer = FrameRenderer(plan, materials, settings)
    rows = []
    for frame in data.heldout_frames:
        for cam, result in renderer.frame(frame, [data.capture.camera(n) for n in frame.images]):
            gt, mask = C.read_image(os.path.join(str(folder), C.image_path(frame.index, cam.name)))
            m = _metrics(result.image, gt, mask)
            if m:
                rows.append(m)
    return {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}


def validation(iters: int) -> dict:
    """Validation every sixth of the run on 6 samples; a quick run (< 60 iterations) gets a
    few points on 2 samples, so that validation does not cost more than training."""
    if iters >= 60:
        return {"val_every": max(1, iters // 6), "val_samples": 6}
    return {"val_every": max(2, iters // 3), "val_samples": 2}


def train_variant(folder: Path, variant: str, iters: int) -> dict:
    """One ``tiny`` OLAT teacher (``teacher``, ``no-visibility`` or ``ggx``) trained on
    ``folder`` for ``iters`` iterations, timed: metrics, seconds, iterations/s, the
    held-out MSE against training seconds (validation excluded)."""
    import numpy as np
    import torch

    from relight_cli.neural.config import resolve_config
    from relight_cli.neural.data import CaptureData
    from relight_cli.neural.train import fit

    overrides = {"iters": iters, **validation(iters),
                 "lambda_vgg": 0.0, "neg_start": iters // 4}
    if variant == "no-visibility":
        overrides["visibility"] = False
    if variant == "ggx":
        overrides["model"] = "ggx"
    cfg = resolve_config("tiny", None, overrides)
    data = CaptureData(str(folder), cfg.tex_res, cfg.aa, cfg.visibility, cfg.falloff, cfg.holdout)
    task = timed_teacher_task(data, cfg)
    t0 = time.perf_counter()
    result = fit(task, cfg, torch.device("cpu"), show_progress=False)
    total = time.perf_counter() - t0
    task.flops.close()
    # training seconds (validation excluded) at each validation step
    elapsed = np.cumsum([0.0] + [t for t, _, _ in task.steps])
    curve = [(float(elapsed[min(h["step"], len(task.steps))]), h.get("heldout", {}).get("mse"))
             for h in result.history]
    train_seconds = float(elapsed[-1])
    return {"metrics": result.metrics, "seconds": total, "train_seconds": train_seconds,
            "its": len(task.steps) / train_seconds, "peak_rss_mb": result.peak_memory_mb,
            "curve": curve}


def env_render_cost(folder: Path, widths: str, tex: int, channels_last: bool | None = None
                    ) -> dict:
    """One env-map render of preset ``widths`` at ``tex``² (``channels_last``: the layout
    a checkpoint of that setting is loaded in, :mod:`relight_cli.neural.checkpoints`)."""
    import torch

    from relight_cli.builtin_envs import builtin_envmap
    from relight_cli.envmap import discretize_env
    from relight_cli.neural import teacher as T
    from relight_cli.neural.checkpoints import _layout
    from relight_cli.neural.config import resolve_config
    from relight_cli.neural.data import CaptureData
    from relight_cli.neural.models import build_model
    from relight_cli.render.gbuffer import render_gbuffer

    values = {"tex_res": tex}
    if channels_last is not None:
        values["channels_last"] = channels_last
    cfg = resolve_config(widths, None, values)
    data = CaptureData(str(folder), tex, 2)
    model = _layout(build_model(cfg, data.pose_dim).eval(), cfg)
    denv = discretize_env(builtin_envmap("builtin:sky"), 16, 32)
    timing = T.Timing()
    t0 = time.perf_counter()
    texels = data.texels(0)
    cam = data.capture.cameras[0]
    gb = render_gbuffer(texels.meshes, cam, 2, scene=texels.renderer.scene)
    timing.add("geometry", time.perf_counter() - t0)
    lights, weights = T.env_light_inputs(texels, denv, True, timing)
    with ConvFlops(model) as flops:
        T.render_lights(model, texels, gb, data.poses(0), lights, weights, True, cfg.falloff,
                        timing=timing)
    return {"preset": widths, "tex_res": tex, "directions": int(len(weights)),
            "channels_last": cfg.channels_last,
            **{k: v for k, v in timing.seconds.items()},
            "network_gflop": flops.forward / 1e9,
            "network_gflops": flops.forward / 1e9 / timing.seconds["network"],
            "threads": torch.get_num_threads(),
            "total": float(sum(timing.seconds.values()))}


def write_plot(path: Path, curves: dict, machine: dict, what: str = "teacher"):
    """Held-out MSE (×1e-3) against training seconds, every curve."""
    fig, (ax,) = figure(1, 7.2, 4.6)
    plot(ax, {name: [(t, m * 1e3) for t, m in curve if m] for name, curve in curves.items()},
           "training seconds (validation excluded)", "held-out MSE x 1e-3 (log)",
           f"{what}: validation during training", logx=False, labels=False)
    save(fig, path, machine)
