"""What every ``benchmarks/bench_*.py`` shares: options, the machine's own limits, plots.

* :func:`parser` gives every benchmark ``--out DIR`` (default ``benchmarks/out/``) and
  ``--quick`` (a smoke run: ``make benchmarks QUICK=1`` runs them all in a few minutes);
  :func:`start` checks for matplotlib first, so a runner without it stops at once with
  one line instead of after minutes of work.
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
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import sys
import time
from pathlib import Path

OUT = Path(__file__).resolve().parent / "out"
ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:          # run as a script from anywhere: import the checkout
    sys.path.insert(0, str(ROOT))


def parser(doc: str, quick: str = "a smoke run: fewer, smaller configurations"):
    """argparse with the options every benchmark has."""
    ap = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=str(OUT), metavar="DIR",
                    help="folder for the table (.md), data (.json/.csv) and plot (.png) "
                         "[default: benchmarks/out/]")
    ap.add_argument("--quick", action="store_true", help=quick)
    return ap


def start(args, name: str) -> Path:
    """Check that matplotlib is there (one line and exit 1 if not), make ``--out``."""
    require_matplotlib(name)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    return out


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
