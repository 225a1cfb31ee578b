"""The persistent compilation cache (jaxfit/_cache.py): each case runs fresh interpreters,
because the cache is configured once, on import, for the whole process."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from jaxfit import _cache

# One small fit; prints what JAX's monitoring saw. refine=False and one batch of 64
# keep the compilation (the slow part of each process) short.
SCRIPT = r"""
import collections, json, time, warnings
warnings.simplefilter("always")
import jax.export, jax.monitoring
events = collections.Counter()
jax.monitoring.register_event_listener(lambda name, **_: events.update([name]))
export = jax.export.export
def counted(*args, **kwargs):  # jaxfit's kernels are traced only to be exported
    events.update(["exports"])
    return export(*args, **kwargs)
jax.export.export = counted
import numpy as np
import jaxfit
from jaxfit.evaluation.synthetic import demo_cloud
points, _, _ = demo_cloud("plane", count=300, outlier_ratio=0.2, seed=0)
start = time.perf_counter()
result = jaxfit.fit(points, "plane", batch_size=64, max_hypotheses=64, refine=False, key=0)
print(json.dumps({
    "dir": jaxfit.compilation_cache_dir(),
    "hits": events["/jax/compilation_cache/cache_hits"],
    "misses": events["/jax/compilation_cache/cache_misses"],
    "first_fit_s": time.perf_counter() - start,
    "inliers": result.num_inliers,
    "exports": events["exports"],
}))
"""

def run(env_update: dict[str, str | None]) -> tuple[dict, str]:
    """Run SCRIPT in a fresh interpreter with the environment changed; (its JSON, stderr)."""
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(("JAXFIT_CACHE", "JAX_COMPILATION_CACHE", "JAX_ENABLE_COMP"))}
    env.update({k: v for k, v in env_update.items() if v is not None})
    proc = subprocess.run([sys.executable, "-c", SCRIPT], env=env, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1]), proc.stderr


def entries(folder: Path) -> list[Path]:
    return sorted(folder.glob("*-cache")) if folder.exists() else []


def exported(folder: Path) -> dict[Path, float]:
    """jaxfit's exported kernels in the folder, with their modification times."""
    return {p: p.stat().st_mtime_ns for p in sorted((folder / _cache.EXPORTED).rglob("*"))
            if p.is_file()}


def test_second_process_hits_the_cache(tmp_path):
    folder = tmp_path / "cache"
    first, _ = run({_cache.ENV_DIR: str(folder)})
    written = entries(folder)
    assert first["dir"] == str(folder)
    assert first["misses"] > 0 and first["hits"] == 0
    assert len(written) == first["misses"]  # every compiled executable was stored
    programs = exported(folder)
    assert first["exports"] == len(programs) == 2  # the kernel and the cloud keys
    second, _ = run({_cache.ENV_DIR: str(folder)})
    assert second["hits"] == first["misses"] and second["misses"] == 0
    assert entries(folder) == written  # nothing rewritten or added
    assert second["exports"] == 0 and exported(folder) == programs  # read, not traced
    assert second["inliers"] == first["inliers"]  # same result from the cached kernels


def test_switch_off_writes_nothing(tmp_path):
    folder = tmp_path / "cache"
    out, _ = run({_cache.ENV_DIR: str(folder), _cache.ENV_SWITCH: "0"})
    assert out["dir"] is None and out["hits"] == out["misses"] == out["exports"] == 0
    assert not folder.exists()


def test_unwritable_folder_warns_and_fits(tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")  # a folder below a file fails even for root
    out, err = run({_cache.ENV_DIR: str(blocker / "cache")})
    assert out["dir"] is None and out["inliers"] > 0
    assert err.count("jaxfit: compilation cache disabled") == 1


def test_a_folder_configured_for_jax_wins(tmp_path):
    theirs, ours = tmp_path / "theirs", tmp_path / "ours"
    out, _ = run({"JAX_COMPILATION_CACHE_DIR": str(theirs), _cache.ENV_DIR: str(ours)})
    assert out["dir"] == str(theirs)
    assert not ours.exists()


def test_default_folder_follows_xdg(tmp_path):
    env = {"XDG_CACHE_HOME": str(tmp_path)}
    folder = _cache.wanted_dir(env, platform="linux")
    assert folder.parent == tmp_path / "jaxfit" and folder.name.startswith("jax-")
    assert _cache.wanted_dir({**env, _cache.ENV_DIR: "~/x"}) == Path("~/x").expanduser()


@pytest.mark.parametrize("value", ["0", "false", "OFF", " no "])
def test_switch_values(value):
    assert _cache.wanted_dir({_cache.ENV_SWITCH: value}) is None


def test_unusable_reports_a_reason(tmp_path):
    assert _cache.unusable(tmp_path / "new" / "folder") is None
    blocker = tmp_path / "file"
    blocker.write_text("")
    assert _cache.unusable(blocker / "sub") is not None


def _stored_square(tmp_path, monkeypatch, traced):
    """A fresh ``Stored`` kernel (as a new process would make) writing to tmp_path."""
    import jax

    monkeypatch.setattr(_cache, "_enabled_dir", str(tmp_path))

    def scaled_square(x, factor):
        traced.append(x.shape)
        return factor * x * x

    return _cache.Stored(jax.jit(scaled_square, static_argnames="factor"), scaled_square,
                         ("factor",))


def test_a_stored_kernel_is_read_back_without_tracing(tmp_path, monkeypatch):
    import numpy as np

    traced = []
    x = np.arange(4, dtype=np.float32)
    first = _stored_square(tmp_path, monkeypatch, traced)
    np.testing.assert_array_equal(first(x, factor=3), 3 * x * x)
    assert len(traced) == 1 and len(exported(tmp_path)) == 1
    again = _stored_square(tmp_path, monkeypatch, traced)  # as in the next process
    np.testing.assert_array_equal(again(x, factor=3), 3 * x * x)
    assert len(traced) == 1  # the program came from the file
    # Another static value or shape is another program.
    np.testing.assert_array_equal(again(x, factor=2), 2 * x * x)
    np.testing.assert_array_equal(again(x[:3], factor=3), 3 * x[:3] ** 2)
    assert len(traced) == 3 and len(exported(tmp_path)) == 3
    # So is a call under other JAX settings that change tracing.
    import jax

    with jax.default_matmul_precision("highest"):
        np.testing.assert_array_equal(again(x, factor=3), 3 * x * x)
    assert len(traced) == 4


def test_a_broken_stored_kernel_is_exported_again(tmp_path, monkeypatch):
    import numpy as np

    traced = []
    x = np.arange(4, dtype=np.float32)
    _stored_square(tmp_path, monkeypatch, traced)(x, factor=3)
    (path,) = exported(tmp_path)
    path.write_bytes(path.read_bytes()[:100])  # cut short, as by a crash
    again = _stored_square(tmp_path, monkeypatch, traced)
    np.testing.assert_array_equal(again(x, factor=3), 3 * x * x)
    assert len(traced) == 2 and path.stat().st_size > 100  # traced and replaced


def test_the_random_bits_setting_gets_its_own_program(tmp_path, monkeypatch):
    """jax_threefry_partitionable changes the bits a key gives: a program stored under one
    setting must not serve the other (results never depend on a warm cache)."""
    import jax
    import numpy as np

    monkeypatch.setattr(_cache, "_enabled_dir", str(tmp_path))

    def bits(key):
        return jax.random.bits(key, (8,))

    key = jax.random.key(0)
    stored = _cache.Stored(jax.jit(bits), bits)
    setting = jax.config.jax_threefry_partitionable
    first = np.asarray(stored(key))
    with jax.threefry_partitionable(not setting):
        other = np.asarray(stored(key))
        expected = np.asarray(jax.jit(bits)(key))
    assert not np.array_equal(first, other)
    np.testing.assert_array_equal(other, expected)
    assert len(exported(tmp_path)) == 2



@pytest.mark.skipif(not hasattr(os, "getuid"), reason="POSIX ownership and modes")
def test_a_folder_others_can_write_is_not_used(tmp_path, monkeypatch):
    """jaxfit runs the programs it reads from its folder: one that group or others can
    write (where anyone could plant a program) is refused with one warning."""
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o777)
    assert "writable by group or others" in _cache.unusable(shared)
    env = {_cache.ENV_DIR: str(shared)}
    monkeypatch.setattr(_cache, "_jax_configured", lambda: False)  # as in a new process
    with pytest.warns(RuntimeWarning, match="compilation cache disabled.*writable by group"):
        assert _cache.enable(env) is None
    shared.chmod(0o700)
    assert _cache.unusable(shared) is None


def test_a_program_of_other_arguments_is_replaced(tmp_path, monkeypatch):
    """A stored program copied over another's name (right format, wrong arguments) is
    not run: it is exported again and the file replaced, and the call gives its result."""
    import numpy as np

    traced = []
    x = np.arange(4, dtype=np.float32)
    _stored_square(tmp_path, monkeypatch, traced)(x, factor=3)
    _stored_square(tmp_path, monkeypatch, traced)(x[:3], factor=3)
    short, full = sorted(exported(tmp_path), key=lambda p: p.stat().st_mtime_ns)[::-1]
    full.write_bytes(short.read_bytes())  # the (3,) program under the (4,) one's name
    again = _stored_square(tmp_path, monkeypatch, traced)
    np.testing.assert_array_equal(again(x, factor=3), 3 * x * x)
    assert len(traced) == 3 and full.read_bytes() != short.read_bytes()


def test_a_relative_xdg_cache_home_is_ignored():
    folder = _cache.wanted_dir({"XDG_CACHE_HOME": "relative/cache"}, platform="linux")
    assert folder.is_absolute() and "relative" not in folder.parts


def test_no_home_folder_leaves_jaxfit_importable(tmp_path):
    """Without HOME (and, here, no passwd entry to fall back on) import jaxfit works,
    without a cache and with one warning."""
    code = ("import os, pathlib\n"
            "def no_home(): raise RuntimeError('Could not determine home directory.')\n"
            "pathlib.Path.home = staticmethod(no_home)\n"
            "import jaxfit; print(jaxfit.compilation_cache_dir())\n")
    env = {k: v for k, v in os.environ.items()
           if k not in ("HOME", "XDG_CACHE_HOME") and not k.startswith("JAXFIT_CACHE")}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "None" and out.stderr.count("no user cache folder") == 1

