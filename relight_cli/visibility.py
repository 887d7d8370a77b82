"""Binary visibility of receivers towards env-map directions, traced once per pose.

:class:`VisibilityCache` traces exactly the (receiver, direction) pairs asked for and
not traced before, in large embree batches (:class:`relight_cli.raytrace.RayScene`)
spread over a process-wide thread pool (:func:`trace_threads` workers: embree and
numpy release the GIL), so every env map, shininess and specular model of a pose
reuses one trace.  Results do not depend on the thread count or the chunking.
"""

from __future__ import annotations

import os
import threading
import time

import numpy as np

from relight_cli.geometry import Receivers

def trace_threads() -> int:
    """Worker threads for ray tracing: the CPUs this process may run on.

    embreex's occlusion query runs without the GIL (as do numpy's large array
    operations), so threads working on disjoint receivers scale with cores: raw embree
    on the default bake's rays ran 1.7× faster on 2 idle cores than on one.
    """
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:          # not on Linux
        return max(1, os.cpu_count() or 1)


# Rays per traced chunk: small enough that every worker gets several (load balance,
# bounded peak memory for the per-ray origin/direction arrays), large enough that
# the per-call Python overhead (~50 µs) is noise.
_MIN_CHUNK = 1 << 15
_MAX_CHUNK = 1 << 20
# (receiver, direction) entries per ray-building step (12 MiB of tiled float32 directions).
_TILE = 1 << 20
# One float32 xyz triple as a single 12-byte record, for memcpy-speed repeat/compress.
_VEC3 = np.dtype((np.void, 12))


def _row_chunks(per_row: np.ndarray, workers: int) -> list[slice]:
    """Split rows into contiguous slices of about equal total ``per_row`` (rays)."""
    total = int(per_row.sum())
    target = min(_MAX_CHUNK, max(_MIN_CHUNK, -(-total // (4 * workers))))
    bounds = np.searchsorted(np.cumsum(per_row), np.arange(target, total, target), side="left")
    edges = np.unique(np.concatenate([[0], bounds + 1, [len(per_row)]]))
    edges = edges[edges <= len(per_row)]
    return [slice(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b > a]


_THREAD_POOLS: dict = {}


def thread_pool(workers: int):
    """A process-wide thread pool of ``workers`` threads, started once (starting threads
    per pose costs milliseconds on a busy machine; idle workers cost nothing)."""
    key = (os.getpid(), workers)     # a forked child has no threads: it needs its own pool
    if key not in _THREAD_POOLS:
        from concurrent.futures import ThreadPoolExecutor
        _THREAD_POOLS[key] = ThreadPoolExecutor(workers, thread_name_prefix="relight-trace")
    return _THREAD_POOLS[key]


class VisibilityCache:
    """Binary visibility h[i, m] of receivers towards env directions, traced on demand.

    ``require(need)`` traces exactly the pairs asked for that were not traced
    before, in large embree batches (chunks of receivers traced concurrently by
    ``threads`` workers), so a pose's visibility is traced once and reused by
    every env map, shininess and specular model.  The result does not depend on
    ``threads`` or chunking: every ray is independent (tests check it equals one
    flat :meth:`~relight_cli.raytrace.RayScene.occluded` call).

    Args:
        scene: a :class:`~relight_cli.raytrace.RayScene` of every occluding mesh, or
            None for "nothing occludes" (the ``--no-visibility`` ablation).
        receivers: the receiving points.
        directions: [M, 3] unit directions.
        ray_offset: metres (scalar or [N]) to lift ray origins along the normal (avoids hitting the
            receiver's own triangles through rounding).
        threads: worker threads (None = :func:`trace_threads`; 1 = trace on the caller's thread).
    """

    def __init__(self, scene, receivers: Receivers, directions: np.ndarray, ray_offset,
                 threads: int | None = None):
        self.scene = scene
        self.receivers = receivers
        self.directions = np.asarray(directions, np.float64)
        self.ray_offset = np.broadcast_to(np.asarray(ray_offset, np.float64),
                                          (len(receivers),))[:, None]
        shape = (len(receivers), len(self.directions))
        self.traced = np.zeros(shape, bool)
        self.visible = np.zeros(shape, bool)
        self.rays_traced = 0
        self.seconds = 0.0
        self.threads = trace_threads() if threads is None else max(1, int(threads))
        self._origins = None
        self._dirs32 = None
        self._warm = False
        self._tiled = None
        self._lock = threading.Lock()

    def ray_origins(self) -> np.ndarray:
        """[N, 3] float32 ray origins (receiver lifted along its normal), metres, world."""
        if self._origins is None:   # directions first: a thread seeing origins finds both
            self._dirs32 = self.directions.astype(np.float32)
            self._origins = (self.receivers.points + self.ray_offset
                             * self.receivers.normals).astype(np.float32)
        return self._origins

    def require(self, need: np.ndarray) -> int:
        """Trace every pair of ``need`` ([N, M] bool) not traced yet; return how many.

        Chunks of receivers are traced concurrently on ``threads`` workers."""
        t0 = time.perf_counter()
        todo = need & ~self.traced                                # [N, M]
        per_row = np.count_nonzero(todo, axis=1)
        count = int(per_row.sum())
        if count:
            if self.scene is None:
                self.visible |= todo
            else:
                chunks = _row_chunks(per_row, self.threads)
                workers = min(self.threads, len(chunks))
                counted = self.scene.rays_traced
                if workers > 1:
                    self.warm_up()
                    list(thread_pool(workers).map(
                        lambda rows: self._trace_rows(rows, todo[rows], per_row[rows]), chunks))
                else:
                    for rows in chunks:
                        self._trace_rows(rows, todo[rows], per_row[rows])
                # RayScene's counter is not thread-safe (+= from several workers): set it once.
                self.scene.rays_traced = counted + count
                self.rays_traced += count
            self.traced |= todo
        self.seconds += time.perf_counter() - t0
        return count

    def require_rows(self, rows: slice, need: np.ndarray) -> int:
        """:meth:`require` for receivers ``rows`` only (``need`` [len(rows), M] bool), traced
        on the calling thread.  Calls for disjoint rows may run concurrently (after
        :meth:`warm_up`); the counters are then updated under a lock, except
        ``scene.rays_traced``, which the caller must correct (see :meth:`require`)."""
        t0 = time.perf_counter()
        traced = self.traced[rows]
        todo = need & ~traced
        per_row = np.count_nonzero(todo, axis=1)
        count = int(per_row.sum())
        if count:
            if self.scene is None:   # nothing occludes: visible, and no ray traced
                self.visible[rows] |= todo
                count = 0
            else:
                self._trace_rows(rows, todo, per_row)
            traced |= todo
        with self._lock:
            self.rays_traced += count
            self.seconds += time.perf_counter() - t0
        return count

    def warm_up(self):
        """Build embree's BVH (done on the first query) before threads race to it."""
        if self.scene is not None and not self._warm:
            counted = self.scene.rays_traced
            self.scene.occluded(np.zeros((1, 3), np.float32), np.array([[0, 0, 1]], np.float32))
            self.scene.rays_traced = counted
            self._warm = True

    def _trace_rows(self, rows: slice, todo: np.ndarray, per_row: np.ndarray):
        """Trace ``todo`` ([len(rows), M] bool) of receivers ``rows``; write ``visible[rows]``."""
        origins = self.ray_origins().view(_VEC3).reshape(-1)        # [N] 12-byte records
        m = len(self.directions)
        step = max(1, _TILE // max(1, m))
        for s in range(0, len(per_row), step):
            t = todo[s:s + step]
            b = len(t)
            tiled = self._tiled_dirs(b)
            # Row-major pair order: origins repeat per receiver and directions are a
            # boolean compress of the tiled grid (both memcpy-like; a fancy-index gather of
            # [rays, 3] floats was 5× slower), and the mask assignment walks the same order.
            o = np.repeat(origins[rows.start + s:rows.start + s + b], per_row[s:s + b])
            d = tiled[:b * m][np.ascontiguousarray(t).reshape(-1)]
            blocked = self.scene.occluded(o.view(np.float32).reshape(-1, 3),
                                          d.view(np.float32).reshape(-1, 3))
            self.visible[rows.start + s:rows.start + s + b][t] = ~blocked

    def _tiled_dirs(self, rows: int) -> np.ndarray:
        """[≥ rows·M] 12-byte records: the float32 direction grid repeated ``rows`` times."""
        tiled = self._tiled
        if tiled is None or len(tiled) < rows * len(self.directions):
            base = np.ascontiguousarray(self._dirs32).view(_VEC3).reshape(-1)
            tiled = np.tile(base, max(rows, 1))
            self._tiled = tiled      # racing threads each build a valid one; either is kept
        return tiled
