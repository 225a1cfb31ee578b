"""Compile (and so cache) jaxfit's kernels ahead of the first real fit.

``warmup()`` fits a synthetic cloud of each shape at each point bucket with the default
options, so the programs a default ``fit`` of a cloud of that bucket runs (the fused
hypothesis kernel and the refinement) are compiled in this process and, with jaxfit's
cache on, stored for every later one (``jaxfit._cache``). On machines with more cores the
fits run in threads: XLA's compilation releases the GIL, so one shape compiles while
another traces (figures: docs/engine.md, "Compile cost").
"""

from __future__ import annotations

import concurrent.futures
import os
import time
from collections.abc import Callable, Iterable

from ._checks import model_class, positive
from .shapes import REGISTRY

#: Point buckets warmed by default: clouds of up to 1,024 points, of 1,025-2,048 points
#: (and every decomposition: its fits run in the 2,048 bucket, ``parts.MAX_FIT_POINTS``,
#: with the same programs as a fit's) and of 8,193-16,384 points (the CLI's 10k-point
#: clouds). A cloud in another bucket compiles its own kernel on its first fit.
DEFAULT_BUCKETS = (1024, 2048, 16384)
#: Synthetic clouds' outlier share and seed (any value compiles the same programs).
OUTLIERS = 0.3
SEED = 0


def _jobs(shapes, buckets) -> list[tuple[str, int]]:
    """(shape name, bucket) pairs, checked: shapes registered, buckets powers of two
    of at least ``cloud.MIN_BUCKET``."""
    from .engine.cloud import MIN_BUCKET

    names = list(REGISTRY) if shapes is None else [model_class(s).name for s in (
        [shapes] if isinstance(shapes, str) else shapes)]
    sizes = DEFAULT_BUCKETS if buckets is None else tuple(buckets)
    for size in sizes:
        if (isinstance(size, bool) or not isinstance(size, int) or size < MIN_BUCKET
                or size & (size - 1)):
            raise ValueError(f"buckets must be powers of two of at least {MIN_BUCKET} "
                             f"(point counts a cloud is padded to), got {size!r}")
    return [(name, size) for name in dict.fromkeys(names) for size in dict.fromkeys(sizes)]


def _warm_one(name: str, bucket: int) -> float:
    """Seconds to fit one synthetic ``name`` cloud of ``bucket`` points (compiling its
    programs on the first call)."""
    from .engine import fit
    from .evaluation.synthetic import demo_cloud

    points, _, _ = demo_cloud(name, count=bucket, outlier_ratio=OUTLIERS, seed=SEED)
    start = time.perf_counter()
    fit(points, name, key=SEED)
    return time.perf_counter() - start


def warmup(shapes: Iterable[str] | str | None = None, *, buckets: Iterable[int] | None = None,
           say: Callable[[str], None] | None = None, workers: int | None = None
           ) -> dict[str, float]:
    """Compile the default fit's programs of each shape (default: every registered one)
    for each point bucket (default ``DEFAULT_BUCKETS``), in ``workers`` threads (default:
    half the CPU count, at least 1 and at most 4: XLA's compilation already keeps ~1.4
    cores busy, and 2 threads on 2 cores did not pay).

    Returns ``{"<shape>/<bucket>": seconds}``, each job's wall time (a few ms where the
    programs were cached already). ``say`` gets one line per finished job.
    """
    jobs = _jobs(shapes, buckets)
    workers = max(1, min(4, (os.cpu_count() or 2) // 2)) if workers is None else workers
    workers = positive(workers, "workers", integer=True)
    seconds: dict[str, float] = {}
    with concurrent.futures.ThreadPoolExecutor(max_workers=workers) as pool:
        running = {pool.submit(_warm_one, name, size): f"{name}/{size}" for name, size in jobs}
        for done in concurrent.futures.as_completed(running):
            label = running[done]
            seconds[label] = done.result()
            if say is not None:
                say(f"warmed {label}: {seconds[label]:.2f} s")
    return {f"{name}/{size}": seconds[f"{name}/{size}"] for name, size in jobs}
