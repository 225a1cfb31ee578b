"""Whole datasets: one task (``fit``, ``detect`` or ``decompose``) on every model of a set
of inputs, on local worker processes or on Dask distributed (``jaxfit batch``).

- inputs: model files; folders, searched recursively for ``extensions`` (default every
  format ``jaxfit.io.load_points`` reads); globs (``scans/**/*.ply``); manifests: a
  ``.jsonl`` file of one ``{"path": ..., "name": ...}`` object per line, or a ``.csv``
  whose header names a ``path`` column (and optionally ``name``). Relative manifest paths
  are read from the manifest's folder. Files under the output folder are never inputs.
- outputs: ``OUT/<model>/`` per model with the task's files and, written last,
  ``status.json`` (the model's summary row, the task, its options and the source's size
  and modification time); ``OUT/summary.csv`` and ``OUT/summary.json`` (``COLUMNS``).
  Every file is written to a temporary name and renamed into place (``io.atomic``).
- failures: a model that raises is a row with status ``failed`` and the one-line error;
  a worker process that dies (out of memory, a crash in native code) is restarted and
  the models it held are run again one at a time, so only the one that kills a worker
  alone is recorded as failed. The run goes on either way.
- resuming: a model whose ``status.json`` says ``ok`` for the same task, options and
  source, with all its files present, is not run again (its row is reused).
- executors, one task function (``run_model``) for all: ``workers=0`` runs in this
  process; ``workers=N`` in N local processes started with ``spawn`` (each imports jaxfit
  once and keeps its compiled kernels across models); ``scheduler="local"`` on a Dask
  ``LocalCluster`` of N single-threaded worker processes, ``scheduler="tcp://host:port"``
  on a running Dask cluster (its workers need jaxfit installed and the output folder on
  a shared file system). Models are sent smallest file first, so neighbours share point
  buckets and kernels.

Measurements: benchmarks/results/batch_models.md. Usage: docs/batch.md.
"""

from __future__ import annotations

import collections
import csv
import dataclasses
import functools
import glob
import io
import json
import os
import sys
import time
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

from .io.atomic import replacing, write_json
from .io.points import SUPPORTED_EXTENSIONS

TASKS = ("fit", "detect", "decompose")
#: Columns of summary.csv (and keys of each row of summary.json).
COLUMNS = ("model", "source", "task", "status", "points", "parts", "kinds",
           "inlier_fraction", "mean_distance", "seconds", "reused", "error")
#: The file a model's folder gets last; its presence with status ok marks it complete.
STATUS = "status.json"
MANIFESTS = (".jsonl", ".csv")
#: Seconds between progress lines when stderr is not a terminal (a log file).
LOG_EVERY = 5.0


@dataclasses.dataclass(frozen=True)
class Job:
    """One model: ``name`` is its output sub-folder (relative, '/'-separated), ``source``
    the file read, ``size`` its bytes (the sort key)."""

    name: str
    source: str
    size: int


@dataclasses.dataclass(frozen=True)
class Summary:
    """Outcome of ``run_batch``: one row per model (``COLUMNS``), in model-name order."""

    rows: list[dict]
    out: Path
    seconds: float

    @property
    def num_failed(self) -> int:
        return sum(row["status"] != "ok" for row in self.rows)

    @property
    def num_reused(self) -> int:
        return sum(bool(row["reused"]) for row in self.rows)

    def report(self) -> str:
        """One line: counts, time and the summary files."""
        ok = len(self.rows) - self.num_failed
        return (f"{len(self.rows)} models in {self.seconds:.1f} s: {ok} ok ({self.num_reused} "
                f"from an earlier run), {self.num_failed} failed; wrote "
                f"{self.out / 'summary.csv'}, {self.out / 'summary.json'}")


# ----- inputs --------------------------------------------------------------------------


def find_jobs(inputs: Iterable, out=None, extensions=None) -> list[Job]:
    """The models named by ``inputs`` (files, folders, globs, manifests; see the module
    docstring), sorted by file size then name; ``out``: files under it are skipped.

    Raises ValueError naming an input that matches nothing, and when no model is found.
    """
    extensions = _extensions(extensions)
    skip = Path(out).resolve() if out is not None else None
    found: list[tuple[str, Path]] = []  # (name, path)
    for entry in [inputs] if isinstance(inputs, str | os.PathLike) else inputs:
        text = os.fspath(entry)
        path = Path(text)
        if path.is_dir():
            files = [p for p in _walk(path, extensions) if not _under(p, skip)]
            found += [(p.relative_to(path).with_suffix("").as_posix(), p) for p in files]
        elif path.is_file() and _is_manifest(path):
            found += _read_manifest(path)
        elif path.is_file():
            found.append((path.stem, path))
        elif glob.has_magic(text):
            files = sorted(Path(p) for p in glob.glob(text, recursive=True))
            files = [p for p in files if p.is_file() and p.suffix.lower() in extensions
                     and not _under(p, skip)]
            if not files:
                raise ValueError(f"no model file matches {text!r} "
                                 f"(extensions {', '.join(extensions)})")
            found += [(p.stem, p) for p in files]
        else:
            raise ValueError(f"input {text!r}: no such file or folder")
    jobs = _named(found)
    if not jobs:
        raise ValueError(f"no model files in {', '.join(map(str, inputs))} (looked for "
                         f"{', '.join(extensions)})")
    return sorted(jobs, key=lambda job: (job.size, job.name))


def _extensions(extensions) -> tuple[str, ...]:
    if extensions is None:
        return SUPPORTED_EXTENSIONS
    chosen = tuple(e.lower() if e.startswith(".") else f".{e.lower()}" for e in extensions)
    if unknown := [e for e in chosen if e not in SUPPORTED_EXTENSIONS]:
        raise ValueError(f"extension {unknown[0]!r} is not a model format; use some of "
                         f"{', '.join(SUPPORTED_EXTENSIONS)}")
    return chosen


def _walk(folder: Path, extensions) -> list[Path]:
    """Model files under ``folder`` (recursively), hidden files and folders left out."""
    files = []
    for root, dirs, names in os.walk(folder):
        dirs[:] = sorted(d for d in dirs if not d.startswith("."))
        files += [Path(root) / n for n in sorted(names)
                  if not n.startswith(".") and Path(n).suffix.lower() in extensions]
    return files


def _under(path: Path, folder: Path | None) -> bool:
    return folder is not None and path.resolve().is_relative_to(folder)


def _is_manifest(path: Path) -> bool:
    """A ``.jsonl`` file, or a ``.csv`` whose first line is a header with a ``path``
    column (a point file's first line is numbers, or a header such as ``x,y,z``)."""
    suffix = path.suffix.lower()
    if suffix == ".jsonl":
        return True
    if suffix != ".csv":
        return False
    with open(path, newline="", errors="replace") as handle:
        header = next(csv.reader([handle.readline()]), [])
    return "path" in (cell.strip().lower() for cell in header)


def _read_manifest(path: Path) -> list[tuple[str, Path]]:
    """(name, path) of each entry of a manifest; a missing file raises ValueError."""
    if path.suffix.lower() == ".jsonl":
        entries = []
        for number, line in enumerate(path.read_text().splitlines(), 1):
            if not line.strip():
                continue
            try:
                entry = json.loads(line)
            except json.JSONDecodeError as err:
                raise ValueError(f"{path} line {number}: not JSON ({err.msg})") from None
            if not isinstance(entry, dict) or not isinstance(entry.get("path"), str):
                raise ValueError(f"{path} line {number}: expected an object with a 'path'")
            entries.append(entry)
    else:
        with open(path, newline="") as handle:
            rows = csv.DictReader(handle)
            rows.fieldnames = [f.strip().lower() for f in rows.fieldnames or []]
            entries = [row for row in rows if (row.get("path") or "").strip()]
    found = []
    for entry in entries:
        source = Path(entry["path"].strip())
        source = source if source.is_absolute() else path.parent / source
        if not source.is_file():
            raise ValueError(f"{path}: model file {entry['path']!r} not found")
        name = (entry.get("name") or "").strip() or source.stem
        if Path(name).is_absolute() or ".." in Path(name).parts:
            raise ValueError(f"{path}: name {name!r} must be a relative folder name")
        found.append((Path(name).as_posix(), source))
    return found


def _named(found: list[tuple[str, Path]]) -> list[Job]:
    """Jobs with unique names (a file listed twice is one job): names two files share get
    the extension, then -2, -3, ... in path order, so the same inputs give the same names
    on every run (what resuming relies on)."""
    by_path = {}
    for name, path in found:
        by_path.setdefault(str(path.resolve()), name)
    counts = collections.Counter(by_path.values())
    named = {}
    for path in sorted(by_path):
        name = by_path[path]
        if counts[name] > 1:
            name = f"{name}-{Path(path).suffix.lstrip('.').lower()}"
        base, k = name, 1
        while name in named:
            k += 1
            name = f"{base}-{k}"
        named[name] = path
    return [Job(name, path, os.stat(path).st_size) for name, path in named.items()]


# ----- the task function ---------------------------------------------------------------


def run_model(job: Job, task: str, options: dict, out: str) -> dict:
    """Run ``task`` on one model, write its folder ``out/job.name`` (``status.json``
    last) and return its summary row. Never raises for a failed model (the row says
    ``failed`` and why): one bad model must not stop a dataset."""
    folder = Path(out) / job.name
    row = dict.fromkeys(COLUMNS)
    row.update(model=job.name, source=job.source, task=task, reused=False)
    start = time.perf_counter()
    try:
        folder.mkdir(parents=True, exist_ok=True)
        measures = TASK_FUNCTIONS[task](job.source, folder, options)
        row.update({k: float(f"{v:.6g}") if isinstance(v, float) else v
                    for k, v in measures.items()})
        row["status"] = "ok"
    except Exception as err:  # recorded, and the run goes on
        row.update(status="failed", error=f"{type(err).__name__}: {' '.join(str(err).split())}")
    row["seconds"] = round(time.perf_counter() - start, 3)
    try:
        files = sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*")
                       if p.is_file() and p.name != STATUS and not p.name.startswith("."))
        record = {"row": row, "task": task, "options": options, "source": _stamp(job),
                  "files": files}
        write_json(folder / STATUS, record)
    except OSError as err:
        row.update(status="failed", error=f"cannot write {folder / STATUS}: {err}")
    return row


def _fit(source: str, folder: Path, options: dict) -> dict:
    """fit.json (``FitResult.to_dict``) and model.ply; measures over the inliers."""
    from .engine import fit
    from .io import load_points

    points = load_points(source, num_points=options["num_points"], seed=options["seed"])
    (shape,) = options["shapes"]
    result = fit(points, shape, key=options["seed"])
    write_json(folder / "fit.json", result.to_dict())
    with replacing(folder / "model.ply") as path:
        result.model.to_mesh().export(path)
    inside = np.asarray(result.model.distance(points[result.inliers]))
    return {"points": len(points), "parts": 1, "kinds": _kinds([result.model.name]),
            "inlier_fraction": result.num_inliers / len(points),
            "mean_distance": float(inside.mean()) if inside.size else None}


def _detect(source: str, folder: Path, options: dict) -> dict:
    """scene.json, points.npy, scene.glb, preview.png (``Scene.save``; the file's own
    normals are used where it has them); measures over the points detections took."""
    from .detect import DEFAULT_SHAPES, detect
    from .io.inputs import as_cloud

    points, normals = as_cloud(source, num_points=options["num_points"], seed=options["seed"])
    scene = detect(points, options["shapes"] or DEFAULT_SHAPES, normals=normals,
                   key=options["seed"])
    scene.save(folder)
    distances = [np.asarray(d.model.distance(points[d.indices])) for d in scene.shapes]
    taken = np.concatenate(distances) if distances else np.empty(0)
    return {"points": len(points), "parts": len(scene.shapes),
            "kinds": _kinds(d.model.name for d in scene.shapes),
            "inlier_fraction": taken.size / len(points),
            "mean_distance": float(taken.mean()) if taken.size else None}


def _decompose(source: str, folder: Path, options: dict) -> dict:
    """parts.json, points.npy, decomposition.glb, preview.png (``Decomposition.save``); the PSDA's
    mean distance of every point to its part's primitive."""
    from .decomposition import decompose
    from .decomposition.psda import SHAPES, overall_distance

    result = decompose(source, shapes=options["shapes"] or SHAPES,
                       num_points=options["num_points"], key=options["seed"])
    result.save(folder)
    assigned = sum(part.indices.size for part in result.parts)
    return {"points": len(result.points), "parts": len(result.parts),
            "kinds": _kinds(part.model.name for part in result.parts),
            "inlier_fraction": assigned / len(result.points),
            "mean_distance": overall_distance(result.parts) if result.parts else None}


TASK_FUNCTIONS: dict[str, Callable[[str, Path, dict], dict]] = {
    "fit": _fit, "detect": _detect, "decompose": _decompose}


def _kinds(names: Iterable[str]) -> str:
    """'cylinder:2 plane:1': how many primitives of each kind, by name."""
    counts = collections.Counter(names)
    return " ".join(f"{name}:{counts[name]}" for name in sorted(counts))


def _stamp(job: Job) -> dict:
    stat = os.stat(job.source)
    return {"path": job.source, "size": stat.st_size, "mtime_ns": stat.st_mtime_ns}


def completed(job: Job, task: str, options: dict, out) -> dict | None:
    """The row of an earlier run of the same task and options on the same, unchanged
    source whose files are all present, or None (then the model is run again)."""
    folder = Path(out) / job.name
    try:
        record = json.loads((folder / STATUS).read_text())
        complete = (record["row"]["status"] == "ok" and record["task"] == task
                    and record["options"] == options and record["source"] == _stamp(job)
                    and all((folder / name).is_file() for name in record["files"]))
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return {**record["row"], "reused": True} if complete else None


def _failed(job: Job, task: str, error: str) -> dict:
    row = dict.fromkeys(COLUMNS)
    row.update(model=job.name, source=job.source, task=task, status="failed", reused=False,
               error=error)
    return row


# ----- executors -----------------------------------------------------------------------


def _run_here(jobs, call, on_row, task):
    for job in jobs:
        on_row(call(job))


def _run_processes(jobs, call, on_row, task, workers: int):
    """``workers`` spawned processes, at most one model each at a time. When a process
    dies the pool is restarted and the models in flight are run again alone: a model
    that kills a worker by itself is recorded as failed."""
    import concurrent.futures as cf
    import multiprocessing
    from concurrent.futures.process import BrokenProcessPool

    context = multiprocessing.get_context("spawn")
    queue = collections.deque((job, False) for job in jobs)  # (job, alone)
    running: dict = {}
    pool = cf.ProcessPoolExecutor(workers, mp_context=context)
    try:
        while queue or running:
            while queue and len(running) < workers:
                job, alone = queue[0]
                if (alone and running) or any(a for _, a in running.values()):
                    break
                queue.popleft()
                running[pool.submit(call, job)] = (job, alone)
            done, _ = cf.wait(running, return_when=cf.FIRST_COMPLETED)
            broken = []
            for future in done:
                job, alone = running.pop(future)
                try:
                    on_row(future.result())
                except BrokenProcessPool:
                    broken.append((job, alone))
            if not broken:
                continue
            broken += running.values()  # in flight in the dead pool: run again too
            running.clear()
            pool.shutdown(wait=True, cancel_futures=True)
            for job, alone in reversed(broken):
                if alone:
                    on_row(_failed(job, task, "the worker process died on this model (out "
                                              "of memory, or a crash in native code)"))
                else:
                    queue.appendleft((job, True))
            pool = cf.ProcessPoolExecutor(workers, mp_context=context)
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def _dask():
    """distributed's Client, LocalCluster and as_completed, or a ValueError saying how
    to install them."""
    try:
        from distributed import Client, LocalCluster, as_completed
    except ImportError:
        raise ValueError("a Dask scheduler needs Dask distributed: pip install "
                         "'jaxfit[cluster]' (or 'dask[distributed]')") from None
    return Client, LocalCluster, as_completed


def _run_dask(jobs, call, on_row, task, scheduler, workers: int):
    """On a Dask ``LocalCluster`` (``scheduler="local"``: ``workers`` single-threaded
    processes) or the cluster at ``scheduler``; smallest models get the highest
    priority. A model whose worker dies is retried by Dask on another; one that kills
    its workers repeatedly (Dask's ``KilledWorker``) is recorded as failed."""
    import logging

    client_class, cluster_class, as_completed = _dask()
    if scheduler == "local":
        cluster = cluster_class(n_workers=max(1, workers), threads_per_worker=1,
                                processes=True, dashboard_address=None,
                                silence_logs=logging.ERROR)
        client = client_class(cluster)
    else:
        cluster = None
        address = getattr(scheduler, "scheduler_address", scheduler)  # a cluster object
        try:
            client = client_class(address, timeout=30)
        except (OSError, TimeoutError, ValueError) as err:
            raise ValueError(f"cannot reach the Dask scheduler {address}: {err}") from None
    try:
        futures = {client.submit(call, job, key=f"jaxfit-{i:06d}", pure=False,
                                 priority=len(jobs) - i): job for i, job in enumerate(jobs)}
        for future in as_completed(futures):
            try:
                on_row(future.result())
            except Exception as err:  # KilledWorker, a lost connection: recorded
                on_row(_failed(futures[future], task, f"{type(err).__name__}: "
                                                      f"{' '.join(str(err).split())}"))
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


# ----- progress and summaries ----------------------------------------------------------


class _Progress:
    """A progress line on stderr: done / total, failures, models per minute and the
    time left at that rate (rewritten in place on a terminal, every ``LOG_EVERY`` s in
    a log)."""

    def __init__(self, total: int, reused: int, stream=None, enabled: bool = True):
        self.total, self.done, self.failed, self.ran = total, reused, 0, 0
        self.stream = stream or sys.stderr
        self.enabled = enabled
        self.tty = enabled and hasattr(self.stream, "isatty") and self.stream.isatty()
        self.start = self.last = time.perf_counter()

    def update(self, row: dict) -> None:
        self.done += 1
        self.ran += 1
        self.failed += row["status"] != "ok"
        now = time.perf_counter()
        if self.enabled and (self.tty or now - self.last >= LOG_EVERY
                             or self.done == self.total):
            self.last = now
            end = "\n" if not self.tty or self.done == self.total else ""
            print(("\r" if self.tty else "") + self.line(now), end=end, file=self.stream,
                  flush=True)

    def line(self, now: float) -> str:
        elapsed = now - self.start
        rate = self.ran / elapsed * 60 if elapsed > 0 else 0.0
        left = (self.total - self.done) / rate * 60 if rate > 0 else float("nan")
        return (f"batch: {self.done}/{self.total} models, {self.failed} failed, "
                f"{rate:.1f} models/min, elapsed {_clock(elapsed)}, ETA {_clock(left)}")


def _clock(seconds: float) -> str:
    if not np.isfinite(seconds):
        return "?"
    minutes, secs = divmod(int(round(seconds)), 60)
    hours, minutes = divmod(minutes, 60)
    return f"{hours}:{minutes:02d}:{secs:02d}" if hours else f"{minutes}:{secs:02d}"


def write_summary(rows: list[dict], out, meta: dict) -> None:
    """``out/summary.csv`` (``COLUMNS``) and ``out/summary.json`` (``meta`` and the
    rows), each written whole or not at all."""
    out = Path(out)
    text = io.StringIO()
    writer = csv.DictWriter(text, COLUMNS, lineterminator="\n")
    writer.writeheader()
    writer.writerows({k: ("" if row.get(k) is None else row[k]) for k in COLUMNS}
                     for row in rows)
    with replacing(out / "summary.csv") as path:
        path.write_text(text.getvalue())
    write_json(out / "summary.json", {**meta, "models": rows})


# ----- the entry point -----------------------------------------------------------------


def run_batch(inputs, out, *, task: str = "decompose", shapes=None, workers: int | None = None,
              scheduler=None, num_points: int = 20000, seed: int = 0,
              extensions=None, progress: bool = False) -> Summary:
    """Run ``task`` on every model of ``inputs`` and write ``out`` (see the module
    docstring for inputs, outputs, resuming and executors).

    Parameters
    ----------
    inputs : a path, folder, glob or manifest, or a list of them.
    out : output folder (made if missing).
    task : one of ``TASKS``.
    shapes : fit: the one primitive (a name, or a list of one); detect / decompose: the
        candidate names, default theirs.
    workers : local worker processes (default 1; 0: this process); with
        ``scheduler="local"``, the LocalCluster's workers; not with another scheduler
        (a running cluster has its own workers).
    scheduler : None (local processes), ``"local"`` (a Dask LocalCluster), a Dask
        scheduler address such as ``"tcp://10.0.0.1:8786"``, or a Dask cluster object
        (its ``scheduler_address``: a dask-jobqueue ``SLURMCluster``, say).
    num_points : points sampled from a mesh's surface; seed : the sampling and fitting
        seed of every model.
    extensions : model extensions a folder or glob is searched for (default all).
    progress : print a progress line with rate and ETA on stderr.

    Returns a ``Summary``. Bad arguments (an unknown task, no model found, Dask missing)
    raise ValueError before any model is run.
    """
    from ._checks import model_class

    if task not in TASKS:
        raise ValueError(f"unknown task {task!r}; use one of {', '.join(TASKS)}")
    shapes = [shapes] if isinstance(shapes, str | type) else (list(shapes) if shapes else None)
    shapes = [model_class(s).name for s in shapes] if shapes else None  # names go to JSON
    if task == "fit" and (shapes is None or len(shapes) != 1):
        raise ValueError("the fit task needs exactly one shape (--shape S)")
    remote = scheduler is not None and not (isinstance(scheduler, str) and scheduler == "local")
    if remote and workers is not None:
        raise ValueError("workers sets the local processes or the LocalCluster's; a running "
                         "Dask cluster has its own workers: leave workers out")
    workers = 1 if workers is None else workers
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 0:
        raise ValueError(f"workers must be a non-negative integer, got {workers!r}")
    if scheduler is not None:
        _dask()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    jobs = find_jobs(inputs, out, extensions)
    options = {"shapes": shapes, "num_points": int(num_points), "seed": int(seed)}
    started = time.perf_counter()
    rows = {}
    for job in jobs:
        if (row := completed(job, task, options, out)) is not None:
            rows[job.name] = row
    todo = [job for job in jobs if job.name not in rows]
    bar = _Progress(len(jobs), len(rows), enabled=progress)
    if progress and not todo:
        print(f"batch: {len(jobs)} models, all done earlier", file=sys.stderr, flush=True)
    elif progress:
        where = (f"Dask scheduler {getattr(scheduler, 'scheduler_address', scheduler)}"
                 if scheduler is not None else
                 f"{workers} worker process{'es' * (workers != 1)}" if workers else
                 "this process")
        print(f"batch: {len(jobs)} models ({len(rows)} done earlier), {task} on {where}",
              file=sys.stderr, flush=True)

    def on_row(row):
        rows[row["model"]] = row
        bar.update(row)

    call = functools.partial(run_model, task=task, options=options, out=str(out))
    listed = [inputs] if isinstance(inputs, str | os.PathLike) else inputs
    meta = {"task": task, "options": options, "inputs": [os.fspath(i) for i in listed]}
    try:
        if not todo:
            pass
        elif scheduler is not None:
            _run_dask(todo, call, on_row, task, scheduler, workers)
        elif workers == 0:
            _run_here(todo, call, on_row, task)
        else:
            _run_processes(todo, call, on_row, task, min(workers, len(todo)))
    finally:
        ordered = [rows[job.name] for job in sorted(jobs, key=lambda j: j.name)
                   if job.name in rows]
        seconds = time.perf_counter() - started
        write_summary(ordered, out, {**meta, "seconds": round(seconds, 3),
                                     "complete": len(ordered) == len(jobs)})
    return Summary(ordered, out, seconds)
