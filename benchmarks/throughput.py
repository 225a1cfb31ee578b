"""Point-hypothesis evaluations per second: jaxfit's kernel against jaxfit.evaluation.reference.

For each primitive, N in {1e3, 1e4, 1e5, 1e6} and H in {1024, 4096}, the same H
hypotheses are sampled,
estimated and MSAC-scored three ways, side by side in one run:
- jaxfit: one call of the jitted kernel (sample -> vmap'd estimate -> chunked scoring),
  every hypothesis scored on every point (``full_scoring``: no screen on a subset),
  warm (compiled beforehand), best of 9 calls;
- reference, vectorised: NumPy estimates, then the hypotheses scored at once in blocks
  (at most 1e8 evaluations timed, reported per evaluation), best of 3;
- reference, one at a time: the thesis's loop, estimate then score per hypothesis
  (timed on a subset of the hypotheses and reported per evaluation), best of 3.

Run: ``python -m benchmarks.throughput [--quick]``. Writes
``benchmarks/results/throughput.json``, ``throughput.md`` and ``throughput.png``.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxfit
from jaxfit.engine import backend
from jaxfit.engine.cloud import normalise
from jaxfit.engine.cloud import padded as pad
from jaxfit.engine.kernel import SUPPORT, estimate_batch
from jaxfit.engine.sampling import draw_samples
from jaxfit.engine.scoring import score
from jaxfit.evaluation import reference
from jaxfit.evaluation.synthetic import demo_cloud
from jaxfit.io.preview import pyplot
from jaxfit.shapes import REGISTRY

RESULTS = Path(__file__).resolve().parent / "results"


def _seconds(fn, repeats):
    """Best of ``repeats`` runs, for every method alike: on this shared machine the
    spread between runs is load from others, which only ever adds time."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def full_scoring(cls, hypotheses: int):
    """The kernel's stages (its sampler, the vmap'd thesis estimator, the chunked MSAC
    scan, the fit's CPU options) with every hypothesis scored once on every point:
    (points (B, 3), n, key, threshold) -> costs (H,). Above ``SCREEN_POINTS`` points the
    fit's kernel scores all H on a spread subset and only its best few on all, so H x N
    would overstate what that kernel evaluates."""

    def costs(points, n, key, threshold):
        key_sample, key_support = jax.random.split(key)
        idx, distinct = draw_samples(key_sample, n, hypotheses, cls.sample_size)
        support = points[jax.random.randint(key_support, (SUPPORT,), 0, n)]
        thetas, valid = estimate_batch(cls, points[idx], support)
        return score(cls, thetas, valid & distinct, points, n, threshold, counts=False)

    options = {"compiler_options": backend.CPU_OPTIONS} if backend.on_cpu() else {}
    return jax.jit(costs, **options)


def measure(name: str, n: int, hypotheses: int, loop_hypotheses: int, seed: int = 0,
            vec_hypotheses: int | None = None) -> dict:
    cls = REGISTRY[name]
    points, _, _ = demo_cloud(name, count=n, seed=seed)
    center, scale = normalise(points)
    unit = (points - center) / scale
    threshold = 0.01
    padded = pad(unit, np.float32)
    key = jax.random.key(seed)
    thr = jnp.float32(threshold)
    scoring = full_scoring(cls, hypotheses)

    def kernel():
        jax.block_until_ready(scoring(padded, n, key, thr))

    kernel()  # compile
    t_jax = _seconds(kernel, 9)

    def fit():  # the whole host loop, same hypothesis count, no refinement
        jaxfit.fit(points, name, threshold=threshold * scale, max_hypotheses=hypotheses,
                   min_hypotheses=hypotheses, max_stall=hypotheses, refine=False, key=seed)

    fit()
    t_fit = _seconds(fit, 3)

    rng = np.random.default_rng(seed)
    samples = unit[rng.integers(0, n, (hypotheses, cls.sample_size))]
    support = unit[rng.integers(0, n, SUPPORT)]

    vec = vec_hypotheses or hypotheses

    def vectorised():
        thetas, valid = reference.estimate_batch(name, samples[:vec], support)
        reference.score_batch(name, thetas, valid, unit, threshold)

    t_vec = _seconds(vectorised, 3) * hypotheses / vec

    def one_at_a_time():
        for sample in samples[:loop_hypotheses]:
            theta, valid = reference.estimate(name, sample, support)
            if valid:
                reference.msac_cost(name, theta, unit, threshold)

    t_loop = _seconds(one_at_a_time, 3) * hypotheses / loop_hypotheses
    evals = hypotheses * n
    return {
        "shape": name, "N": n, "H": hypotheses,
        "jaxfit_evals_per_s": evals / t_jax,
        "fit_seconds": t_fit,
        "reference_loop_seconds": t_loop,
        "numpy_vectorised_evals_per_s": evals / t_vec,
        "numpy_loop_evals_per_s": evals / t_loop,
        "speedup_vs_vectorised": t_vec / t_jax,
        "speedup_vs_loop": t_loop / t_jax,
        "fit_speedup_vs_loop": t_loop / t_fit,
    }


def table(rows) -> str:
    lines = [
        "| shape | N | H | jaxfit (M eval/s) | NumPy vectorised | NumPy one-at-a-time "
        "| kernel × vectorised | kernel × one-at-a-time | `fit` (ms) | reference loop (ms) "
        "| `fit` × loop |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['shape']} | {r['N']:,} | {r['H']} | {r['jaxfit_evals_per_s'] / 1e6:,.0f} "
            f"| {r['numpy_vectorised_evals_per_s'] / 1e6:,.0f} "
            f"| {r['numpy_loop_evals_per_s'] / 1e6:,.1f} "
            f"| {r['speedup_vs_vectorised']:.1f} | {r['speedup_vs_loop']:.0f} "
            f"| {r['fit_seconds'] * 1e3:,.1f} | {r['reference_loop_seconds'] * 1e3:,.0f} "
            f"| {r['fit_speedup_vs_loop']:.0f} |"
        )
    return "\n".join(lines)


def plot(rows, path):
    """Evaluations per second against N, one panel per primitive, log-log, at the
    largest H measured."""
    largest = max(r["H"] for r in rows)
    rows = [r for r in rows if r["H"] == largest]
    plt = pyplot()
    shapes = list(dict.fromkeys(r["shape"] for r in rows))
    fig, axes = plt.subplots(1, len(shapes), figsize=(3.2 * len(shapes), 3.2), sharey=True,
                             squeeze=False)
    axes = axes[0]
    series = [("jaxfit_evals_per_s", "jaxfit kernel"),
              ("numpy_vectorised_evals_per_s", "NumPy vectorised"),
              ("numpy_loop_evals_per_s", "NumPy one at a time")]
    for ax, shape in zip(axes, shapes, strict=True):
        mine = [r for r in rows if r["shape"] == shape]
        for field, label in series:
            ax.loglog([r["N"] for r in mine], [r[field] for r in mine], "o-", label=label)
        ax.set_title(shape)
        ax.set_xlabel("points N")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel("point-hypothesis evaluations / s")
    axes[0].legend(fontsize=8)
    fig.suptitle(f"MSAC scoring throughput, H = {rows[0]['H']} hypotheses, same samples")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="N up to 1e4 only")
    parser.add_argument("--hypotheses", type=int, nargs="+", default=[1024, 4096])
    parser.add_argument("--shapes", nargs="+", default=["plane", "sphere", "cylinder", "cone",
                                                        "box"])
    args = parser.parse_args(argv)
    sizes = [1_000, 10_000] if args.quick else [1_000, 10_000, 100_000, 1_000_000]
    rows = []
    for name in args.shapes:
        for hypotheses in args.hypotheses:
            for n in sizes:
                loop = max(16, min(hypotheses, 2_000_000 // n))
                vec = max(16, min(hypotheses, 100_000_000 // n))
                row = measure(name, n, hypotheses, loop, vec_hypotheses=vec)
                rows.append(row)
                print(table([row]).splitlines()[-1], flush=True)
    RESULTS.mkdir(parents=True, exist_ok=True)
    meta = {"machine": platform.processor() or platform.machine(), "jax": jax.__version__,
            "devices": [str(d) for d in jax.devices()], "cpus": __import__("os").cpu_count()}
    (RESULTS / "throughput.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=2))
    md = table(rows)
    (RESULTS / "throughput.md").write_text(md + "\n")
    print(md)
    plot(rows, RESULTS / "throughput.png")


if __name__ == "__main__":
    main()
