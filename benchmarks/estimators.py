"""The thesis's estimators against the oriented-point ones on the RN/RNIM/SN/SNIM suite.

    python -m benchmarks.estimators [--repeats 10] [--out benchmarks/results]

Three ways of fitting each (shape, scenario, level), on the same clouds and keys:
"thesis" (cylinder 3 points, cone 4, sphere 4, box 5), "oriented (true normals)" (the scenario's
exact normals) and "oriented (estimated normals)" (``jaxfit.estimate_normals`` from the
points, what a user without normals gets). Every fit uses batches of 256 hypotheses so the
hypothesis counts are resolved finely. Writes estimators.{json,md,png}.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from jaxfit.evaluation import evaluate
from jaxfit.io.preview import pyplot

SHAPES = ("cylinder", "cone", "sphere", "box")
SCENARIOS = ("RN", "RNIM", "SN", "SNIM")
VARIANTS = {  # label -> (estimator, normals)
    "thesis": ("thesis", "estimated"),
    "oriented, true normals": ("oriented", "true"),
    "oriented, estimated normals": ("oriented", "estimated"),
}
BATCH = 256


def measure(repeats: int) -> list[dict]:
    """One summary row per (shape, scenario, level, variant)."""
    out = []
    for label, (estimator, normals) in VARIANTS.items():
        rows = evaluate.run(SHAPES, SCENARIOS, repeats=repeats, normals=normals,
                            estimator=estimator, batch_size=BATCH)
        for entry in evaluate.summarise(rows):
            group = [r for r in rows if (r["shape"], r["scenario"], r["level"])
                     == (entry["shape"], entry["scenario"], entry["level"])]
            entry["hypotheses_median"] = float(np.median(
                [r.get("num_hypotheses", np.nan) for r in group]))
            entry["variant"] = label
            out.append(entry)
    return out


def _main_measure(shape: str) -> str:
    # axis angle for cylinder / cone, centre for the sphere, worst side for the box
    return evaluate.MEASURES[shape][0]


def markdown(summary: list[dict]) -> str:
    lines = ["Medians over the repeats: the main error (axis angle in degrees for cylinder "
             "and cone, centre error / size for the sphere, worst relative side error for the "
             "box), hypotheses drawn, and time "
             "per fit (ms, including normal estimation where estimated).", ""]
    for shape in SHAPES:
        measure = _main_measure(shape)
        lines += [f"### {shape}: {measure}", "",
                  "| scenario | level | " + " | ".join(VARIANTS) + " |",
                  "|---|---|" + "---|" * len(VARIANTS)]
        keys = dict.fromkeys((s["scenario"], s["level"]) for s in summary
                             if s["shape"] == shape)
        for scenario, level in keys:
            cells = []
            for label in VARIANTS:
                s = next(s for s in summary if (s["shape"], s["scenario"], s["level"],
                                                 s["variant"]) == (shape, scenario, level,
                                                                   label))
                cells.append(f"{s[f'{measure}_median']:.3g} ({s['hypotheses_median']:.0f} h, "
                             f"{1000 * s['runtime_s_median']:.0f} ms)")
            lines.append(f"| {scenario} | {level:g} | " + " | ".join(cells) + " |")
        lines.append("")
    return "\n".join(lines)


def plot(summary: list[dict], path: Path):
    plt = pyplot()

    fig, axes = plt.subplots(len(SHAPES), len(SCENARIOS), figsize=(13, 8.5), squeeze=False)
    for row, shape in enumerate(SHAPES):
        measure = _main_measure(shape)
        for col, scenario in enumerate(SCENARIOS):
            ax = axes[row, col]
            for label in VARIANTS:
                points = sorted((s["level"], s[f"{measure}_median"]) for s in summary
                                if (s["shape"], s["scenario"], s["variant"])
                                == (shape, scenario, label))
                ax.plot(*zip(*points, strict=True), "o-", label=label)
            ax.set_title(f"{shape}, {scenario}", fontsize=9)
            ax.set_ylabel(measure, fontsize=8)
            ax.set_xlabel("outlier share" if scenario.startswith("RN") else "sc", fontsize=8)
            ax.set_yscale("log")
            ax.grid(alpha=0.3)
            ax.tick_params(labelsize=7)
    axes[0, 0].legend(fontsize=7)
    fig.suptitle("thesis vs oriented estimators (median over repeats)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--out", default="benchmarks/results")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    summary = measure(args.repeats)
    (out / "estimators.json").write_text(json.dumps(summary, indent=1))
    (out / "estimators.md").write_text(markdown(summary))
    plot(summary, out / "estimators.png")
    print(markdown(summary))


if __name__ == "__main__":
    main()
