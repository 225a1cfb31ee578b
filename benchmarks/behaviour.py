"""Bit-for-bit behaviour digests: a fixed set of fits, a decomposition and a detect scene.

Run: ``python -m benchmarks.behaviour --out FILE`` writes one SHA-256 per case (every
float of the result as its exact bytes, the inlier mask, hypothesis count and status);
``--compare FILE`` also checks them against an earlier run and exits 1 on any change.
A refactoring that must not change behaviour is run before and after
(``benchmarks/results/behaviour/``). Digests depend on the machine and the JAX version:
compare runs made on the same one.

Only public names are used (``jaxfit.fit``, ``fit_batch``, ``decompose``, ``detect``,
``jaxfit.synthetic``, ``jaxfit.scenarios``), so the script runs on either side of a
change of layout.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from pathlib import Path

import jax
import numpy as np

import jaxfit
from jaxfit import scenarios, synthetic

SHAPES = ("plane", "sphere", "cylinder", "cone", "box")


def _hash_value(h, value):
    """Feed value (model dicts, arrays, numbers, strings) into h, exactly."""
    if isinstance(value, dict):
        for name in sorted(value):
            h.update(name.encode())
            _hash_value(h, value[name])
    elif isinstance(value, (list, tuple)):
        h.update(b"[%d" % len(value))
        for item in value:
            _hash_value(h, item)
    elif isinstance(value, str):
        h.update(value.encode())
    elif value is None:
        h.update(b"None")
    else:
        arr = np.asarray(value)
        h.update(str(arr.dtype).encode() + str(arr.shape).encode())
        h.update(np.ascontiguousarray(arr).tobytes())


def digest(value) -> str:
    h = hashlib.sha256()
    _hash_value(h, value)
    return h.hexdigest()[:16]


def _result(r) -> dict:
    if r is None:
        return {"none": None}
    return {"model": r.model.to_dict(), "inliers": np.packbits(r.inliers),
            "num_inliers": np.int64(r.num_inliers), "cost": np.float64(r.cost),
            "drawn": np.int64(r.num_hypotheses), "status": r.status.value,
            "threshold": np.float64(r.threshold)}


def cases():
    """(name, thunk) pairs; each thunk returns a digestible value."""
    out = []
    for shape in SHAPES:
        cls = jaxfit.shapes.REGISTRY[shape]
        for scenario, level in (("RN", 0.3), ("SNIM", 0.05)):
            case = scenarios.make(shape, scenario, level, count=2000, seed=3)
            for est in ("thesis", "oriented"):
                if est not in cls.estimators:
                    continue
                out.append((f"{shape}/{scenario}/{est}", lambda c=case, s=shape, e=est:
                            _result(jaxfit.fit(c.points, s, estimator=e, key=1))))
        case = scenarios.make(shape, "RN", 0.2, count=1500, seed=5)
        out.append((f"{shape}/no-refine", lambda c=case, s=shape:
                    _result(jaxfit.fit(c.points, s, refine=False, key=2))))
        out.append((f"{shape}/gate", lambda c=case, s=shape:
                    _result(jaxfit.fit(c.points, s, normal_angle=30, key=3))))
        clouds = [scenarios.make(shape, "RN", 0.3, count=n, seed=10 + i).points
                  for i, n in enumerate((300, 700, 1200, 2500, 5000))]
        out.append((f"{shape}/batch", lambda cs=clouds, s=shape:
                    [_result(r) for r in jaxfit.fit_batch(cs, s, key=4, skip_failures=True)]))
    big = scenarios.make("cylinder", "RN", 0.4, count=30000, seed=7)
    out.append(("cylinder/30k", lambda: _result(jaxfit.fit(big.points, "cylinder", key=5))))
    sph = scenarios.make("sphere", "RN", 0.3, count=3000, seed=8)
    r = float(sph.model.radius)
    out.append(("sphere/radius_range", lambda: _result(
        jaxfit.fit(sph.points, "sphere", radius_range=(0.8 * r, 1.2 * r), key=6))))
    cyl = scenarios.make("cylinder", "SN", 0.05, count=3000, seed=9)
    out.append(("cylinder/axis_prior", lambda: _result(
        jaxfit.fit(cyl.points, "cylinder", axis_prior=(cyl.model.axis, 20), key=7))))
    out.append(("cylinder/thesis-fixed", lambda: _result(
        jaxfit.fit(cyl.points, "cylinder", estimator="thesis", min_hypotheses=4096,
                   max_hypotheses=4096, max_stall=10**6, batch_size=512, key=8))))

    def decomposition():
        points = synthetic.composite("mallet", count=8000, seed=0)[0]
        result = jaxfit.decompose(points, gain=0.9, key=0)
        return [{"kind": p.kind, "indices": np.asarray(p.indices), "model": p.model.to_dict()}
                for p in result.parts]

    def detection():
        points = synthetic.scene(0, count=3000)[0]
        result = jaxfit.detect(points, key=0)
        return [{"model": d.model.to_dict(), "indices": np.asarray(d.indices)}
                for d in result.shapes] + [np.asarray(result.unassigned)]

    out.append(("decompose/mallet", decomposition))
    out.append(("detect/scene0", detection))
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="JSON file to write")
    parser.add_argument("--compare", type=Path, help="an earlier run's JSON to check against")
    args = parser.parse_args(argv)
    # read before writing: --compare and --out may name the same file
    before = json.loads(args.compare.read_text())["digests"] if args.compare else None
    found, started = {}, time.perf_counter()
    for name, thunk in cases():
        found[name] = digest(thunk())
        print(f"{name:<28} {found[name]}", flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"jax": jax.__version__,
                                    "digests": found}, indent=1) + "\n")
    print(f"{len(found)} cases in {time.perf_counter() - started:.1f} s; wrote {args.out}")
    if before is not None:
        changed = [n for n in sorted(set(before) | set(found)) if before.get(n) != found.get(n)]
        for name in changed:
            print(f"CHANGED {name}: {before.get(name)} -> {found.get(name)}")
        print(f"{len(found) - len(changed)} of {len(found)} cases identical")
        return 1 if changed else 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
