"""What every ``benchmarks/bench_*.py`` shares: options, the machine's own limits, plots.

* :func:`parser` gives every benchmark ``--out DIR`` (default ``benchmarks/out/``) and
  ``--quick`` (a smoke run: ``make benchmarks QUICK=1`` runs them all in a few minutes);
  :func:`start` checks for matplotlib first, so a runner without it stops at once with
  one line instead of after minutes of work.
* :func:`machine_limits` measures, in the same run, the ceilings the benchmark's numbers
  are read against: float32 GEMM GFLOP/s (torch, else numpy), main-memory copy
  bandwidth, and on request raw embree occlusion rays/s and erf throughput.
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


def load_average() -> str:
    try:
        return " ".join(Path("/proc/loadavg").read_text().split()[:3])
    except OSError:
        return "?"


def machine_limits(embree: bool = False, erf: bool = False) -> dict:
    """The machine and its measured ceilings (this run): see the module docstring."""
    limits = {"platform": platform.platform(), "python": platform.python_version(),
              "cpus": os.cpu_count(), "load_average": load_average()}
    try:
        import torch
        limits["torch"] = torch.__version__
        limits["torch_threads"] = torch.get_num_threads()
    except ImportError:
        pass
    limits["gemm_gflops"] = gemm_gflops()
    limits["memory_gbs"] = memory_gbs()
    if embree:
        limits["embree_mrays"] = embree_mrays()
    if erf:
        limits["erf_gelems"] = erf_gelems()
    return limits


def machine_line(m: dict) -> str:
    """One line for tables and plots."""
    parts = [f"{m['cpus']} CPUs (load {m['load_average']})"]
    if "torch" in m:
        parts.append(f"torch {m['torch']} on {m['torch_threads']} threads")
    parts.append(f"fp32 GEMM {m['gemm_gflops']:.1f} GFLOP/s")
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
