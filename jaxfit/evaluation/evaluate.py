"""The thesis's evaluation (THESIS.md section 4) as a reproducible suite.

For every (shape, scenario, level) the suite makes ``repeats`` clouds with fixed seeds
(``scenarios``), fits them all in one ``fit_batch`` call, and measures the errors of
``measures`` (each primitive's ``error_measures``) plus runtime and inlier
precision/recall. ``run`` returns one row (a dict) per fit; ``write`` turns rows into
``runs.csv``, ``summary.md`` (means and medians per level: the thesis's tables) and one
PNG per primitive (each shown measure against the noise level, one line per scenario:
the thesis's figures).

Thresholds: the thesis fixed one per test. Here a fit uses ``threshold = max(0.01, sc) *
size`` with ``size = scenarios.shape_size(model)`` and sc the SN scattering factor (0 for
RN): 1 % of the shape's size on exact surfaces, and the noise amplitude (what a user who
knows the sensor would set) under surface noise. The measures and results:
docs/evaluation.md.
"""

from __future__ import annotations

import csv
import sys
import time
from pathlib import Path

import numpy as np

from ..engine import fit_batch
from ..shapes import REGISTRY
from . import measures, scenarios

#: The primitives of the thesis's evaluation, in the order they are run.
SHAPES = ("sphere", "cylinder", "cone", "box")
#: The measures shown in tables and plots, per primitive name (all are kept in the CSV):
#: each primitive's ``shown_measures``.
MEASURES = {name: cls.shown_measures for name, cls in REGISTRY.items()}
#: Columns shown for every primitive after its own measures.
COMMON = ("precision", "recall", "runtime_s")


def threshold_for(case: scenarios.Scenario) -> float:
    """The fit threshold used for a scenario (see the module docstring)."""
    sc = case.level if case.scenario.startswith("SN") else 0.0
    return max(0.01, sc) * case.size


#: What an oriented estimator reads in ``run``: normals estimated from the points, or
#: the scenario's true ones.
NORMALS = ("estimated", "true")


def run(shapes=SHAPES, scenario_names=scenarios.SCENARIOS, *, repeats: int = 10,
        count: int = 2000, seed: int = 0, progress: bool = True, normals: str = "estimated",
        **fit_kwargs) -> list[dict]:
    """Fit every (shape, scenario, level) ``repeats`` times; one dict per fit.

    Repeat r of every setting uses seed ``seed + r`` for the cloud and for the fit's key,
    so each row can be reproduced alone. ``fit_kwargs`` go to ``fit_batch`` (e.g.
    ``estimator``). ``normals``: what an oriented estimator reads, "estimated" from the
    points by ``fit`` (what a user without normals gets) or the scenario's "true" ones.
    """
    if normals not in NORMALS:
        raise ValueError(f"normals must be one of {NORMALS}, got {normals!r}")
    settings = [(shape, name, level) for shape in shapes for name in scenario_names
                for level in scenarios.levels(name)]
    rows, started = [], time.perf_counter()
    warmed = set()
    for done, (shape, name, level) in enumerate(settings):
        cases = [scenarios.make(shape, name, level, count=count, seed=seed + r)
                 for r in range(repeats)]
        clouds = [c.points for c in cases]
        thresholds = [threshold_for(c) for c in cases]
        if normals == "true":
            fit_kwargs["normals"] = [c.normals for c in cases]
        if shape not in warmed:  # compile outside the timed call
            fit_batch(clouds, shape, thresholds=thresholds, key=seed, skip_failures=True,
                      **fit_kwargs)
            warmed.add(shape)
        start = time.perf_counter()
        results = fit_batch(clouds, shape, thresholds=thresholds, key=seed,
                            skip_failures=True, **fit_kwargs)
        per_fit = (time.perf_counter() - start) / repeats
        for r, (case, result) in enumerate(zip(cases, results, strict=True)):
            row = {"shape": shape, "scenario": name, "level": level, "repeat": r,
                   "seed": seed + r, "threshold": thresholds[r], "runtime_s": per_fit,
                   "estimator": estimator_name(shape, fit_kwargs.get("estimator"), normals)}
            if result is None:
                row["failed"] = 1
            else:
                row.update(measures.errors(case.model, result.model, points=case.points,
                                           fitted_inliers=result.inliers,
                                           true_inliers=case.inliers))
                row.update(num_hypotheses=result.num_hypotheses, status=result.status.value,
                           failed=0)
            rows.append(row)
        if progress:
            _progress(done + 1, len(settings), started, f"{shape} {name} {level:g}")
    if progress:
        print(file=sys.stderr)
    return rows


def estimator_name(shape: str, estimator: str | None, normals: str) -> str:
    """How a row was fitted: "thesis", or "oriented (estimated normals)" / "(true ...)"."""
    est = REGISTRY[shape].estimator(estimator)
    return f"oriented ({normals} normals)" if est.uses_normals else est.name


def _progress(done, total, started, label):
    width = 30
    filled = int(width * done / total)
    elapsed = time.perf_counter() - started
    eta = elapsed / done * (total - done)
    bar = "#" * filled + "-" * (width - filled)
    print(f"\r[{bar}] {done}/{total} {label:<22} {elapsed:5.0f}s elapsed, ~{eta:4.0f}s left",
          end="", file=sys.stderr, flush=True)


def summarise(rows) -> list[dict]:
    """Mean and median of every shown measure per (shape, scenario, level)."""
    groups: dict[tuple, list[dict]] = {}
    for row in rows:
        groups.setdefault((row["shape"], row["scenario"], row["level"]), []).append(row)
    out = []
    for (shape, name, level), group in groups.items():
        entry = {"shape": shape, "scenario": name, "level": level, "runs": len(group),
                 "failed": sum(r.get("failed", 0) for r in group)}
        for measure in MEASURES[shape] + COMMON:
            values = np.array([r[measure] for r in group if measure in r], dtype=float)
            entry[f"{measure}_mean"] = float(np.nanmean(values)) if values.size else np.nan
            entry[f"{measure}_median"] = float(np.nanmedian(values)) if values.size else np.nan
        out.append(entry)
    return out


def markdown(summary) -> str:
    """One table per primitive and scenario: mean / median of each measure per level."""
    parts = []
    for shape in dict.fromkeys(s["shape"] for s in summary):
        shown = MEASURES[shape] + COMMON
        for name in dict.fromkeys(s["scenario"] for s in summary if s["shape"] == shape):
            level_name = "outliers" if name.startswith("RN") else "sc"
            parts.append(f"### {shape}, {name}\n")
            parts.append(f"| {level_name} | " + " | ".join(shown) + " |")
            parts.append("|---" * (len(shown) + 1) + "|")
            for s in summary:
                if s["shape"] == shape and s["scenario"] == name:
                    cells = [f"{s[f'{m}_mean']:.4g} / {s[f'{m}_median']:.4g}" for m in shown]
                    fail = f" ({s['failed']} failed)" if s["failed"] else ""
                    parts.append(f"| {s['level']:g}{fail} | " + " | ".join(cells) + " |")
            parts.append("")
    return "Cells are mean / median over the repeats.\n\n" + "\n".join(parts)


def plot(summary, path: Path, shape: str):
    """Medians of each measure against the noise level, one line per scenario."""
    from ..io.preview import pyplot

    plt = pyplot()

    shown = MEASURES[shape] + COMMON
    mine = [s for s in summary if s["shape"] == shape]
    fig, axes = plt.subplots(2, len(shown), figsize=(3.0 * len(shown), 5.6), squeeze=False)
    for row, family in enumerate(("RN", "SN")):
        for col, measure in enumerate(shown):
            ax = axes[row, col]
            for name in (family, family + "IM"):
                points = sorted((s["level"], s[f"{measure}_median"]) for s in mine
                                if s["scenario"] == name)
                if points:
                    ax.plot(*zip(*points, strict=True), "o-", label=name)
            ax.set_title(measure, fontsize=9)
            ax.set_xlabel("outlier share" if family == "RN" else "sc", fontsize=8)
            ax.grid(alpha=0.3)
            ax.tick_params(labelsize=7)
            if col == 0 and ax.get_lines():
                ax.legend(fontsize=7)
    fig.suptitle(f"{shape}: median over repeats")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def write(rows, out) -> Path:
    """Write runs.csv, summary.md and <shape>.png under ``out``; returns the folder."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    fields = list(dict.fromkeys(k for row in rows for k in row))
    with open(out / "runs.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=fields)
        writer.writeheader()
        writer.writerows(rows)
    summary = summarise(rows)
    (out / "summary.md").write_text(markdown(summary))
    try:
        for shape in dict.fromkeys(s["shape"] for s in summary):
            plot(summary, out / f"{shape}.png", shape)
    except ImportError:
        print("matplotlib is not installed: no plots",
              file=sys.stderr)
    return out
