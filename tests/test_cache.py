"""The persistent compilation cache (jaxfit/_cache.py): each case runs fresh interpreters,
because the cache is configured once, on import, for the whole process."""

from __future__ import annotations

import concurrent.futures
import json
import os
import shutil
import stat
import subprocess
import sys
import threading
from pathlib import Path

import pytest
from conftest import run_with_cache

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

def run(env_update: dict[str, str | None], script: str = SCRIPT) -> tuple[dict, str]:
    """Run a script (default SCRIPT) in a fresh interpreter with the environment changed;
    (its JSON, stderr)."""
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(("JAXFIT_CACHE", "JAX_COMPILATION_CACHE", "JAX_ENABLE_COMP"))}
    env.update({k: v for k, v in env_update.items() if v is not None})
    proc = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True,
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
    assert first["exports"] == len(programs) == 1  # the kernel (the cloud keys: NumPy)
    second, _ = run({_cache.ENV_DIR: str(folder)})
    assert second["hits"] == first["misses"] and second["misses"] == 0
    assert entries(folder) == written  # nothing rewritten or added
    assert second["exports"] == 0 and exported(folder) == programs  # read, not traced
    assert second["inliers"] == first["inliers"]  # same result from the cached kernels


# SCRIPT's fit, then a jitted function of the user's: what each stored in the folder.
USER_SCRIPT = SCRIPT.replace("print(json.dumps({", """
import os
from pathlib import Path
folder = Path(jaxfit.compilation_cache_dir())
def stored():
    return {p.name for p in folder.glob("*-cache")}
after_fit, user_events = stored(), collections.Counter(events)
@jax.jit
def users_own(x):
    return jax.numpy.sin(x) * 3.0 + jax.numpy.cos(x) ** 2
users_own(jax.numpy.arange(7.0)).block_until_ready()
user_events = {k: events[k] - user_events[k] for k in events}
print(json.dumps({"user_wrote": sorted(stored() - after_fit),
                  "user_hits": user_events.get("/jax/compilation_cache/cache_hits", 0),
                  "jax_dir": jax.config.jax_compilation_cache_dir,
                  "jax_min_time": jax.config.jax_persistent_cache_min_compile_time_secs,
                  "jax_min_size": jax.config.jax_persistent_cache_min_entry_size_bytes,""", 1)


def test_the_users_own_functions_are_not_cached_in_jaxfits_folder(tmp_path):
    folder = tmp_path / "cache"
    for process in ("first", "second"):
        out, _ = run({_cache.ENV_DIR: str(folder)}, USER_SCRIPT)
        assert out["dir"] == str(folder) and out["inliers"] > 0
        # JAX's settings are the process's own; jaxfit set its folder only around its
        # own compilations (they were set for the whole process on import)
        assert (out["jax_dir"], out["jax_min_time"], out["jax_min_size"]) == (None, 1.0, 0)
        assert out["user_wrote"] == [] and out["user_hits"] == 0
        if process == "first":
            assert out["misses"] > 0 and out["hits"] == 0
        else:  # jaxfit's kernels still come from the folder
            assert out["hits"] > 0 and out["misses"] == 0 and out["exports"] == 0


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

    tmp_path.mkdir(exist_ok=True)
    monkeypatch.setattr(_cache, "_enabled_dir", str(tmp_path))

    def scaled_square(x, factor):
        traced.append(x.shape)
        return factor * x * x

    return _cache.Stored(jax.jit(scaled_square, static_argnames="factor"), scaled_square,
                         ("factor",))


def test_after_export_runs_once_between_tracing_and_running(tmp_path, monkeypatch):
    """``after_export``'s callback runs once: after the block's first Stored call is
    traced (before it runs), before a compiled one runs, or at the block's end."""
    import numpy as np

    events = []
    x = np.arange(4, dtype=np.float32)
    square = _stored_square(tmp_path, monkeypatch, events)
    with _cache.after_export(lambda: events.append("callback")):
        square(x, factor=3)
        square(x, factor=3)
    assert events == [x.shape, "callback"]  # traced, then the callback, once
    with _cache.after_export(lambda: events.append("ready")):
        square(x, factor=3)  # (compiled: the callback before it runs)
    with _cache.after_export(lambda: events.append("no call")):
        pass
    with _cache.after_export(None):
        square(x, factor=3)
    assert events == [x.shape, "callback", "ready", "no call"]


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



# --- Trust (issue 14, Security): signed programs, JAX's entries, shared folders ---------

# A tiny whole-process fit (~1 s with warm caches); prints its results. Two batch sizes:
# two stored programs (two kernels), so that one can be copied over the other.
FIT = r"""
import json, warnings
warnings.simplefilter("always")
import jax, numpy as np
import jaxfit
from jaxfit.evaluation.synthetic import demo_cloud
points, _, _ = demo_cloud("sphere", count=200, outlier_ratio=0.2, seed=0)
small = jaxfit.fit(points, "sphere", batch_size=32, max_hypotheses=32, refine=False, key=0)
result = jaxfit.fit(points, "sphere", batch_size=64, max_hypotheses=64, refine=False, key=0)
print(json.dumps({"dir": jaxfit.compilation_cache_dir(), "cost": float(result.cost),
                  "small_cost": float(small.cost),
                  "inliers": np.flatnonzero(result.inliers).tolist(),
                  "model": [np.asarray(leaf).tolist() for leaf in jax.tree.leaves(result.model)]}))
"""


def fit_with_cache(folder: Path) -> tuple[dict, str | None, str]:
    """FIT in a fresh interpreter caching in folder: (its results, the cache folder it
    used, its stderr)."""
    out, err = run_with_cache(FIT, folder)
    return out, out.pop("dir"), err


def warning_count(stderr: str) -> int:
    return stderr.count("Warning: ")


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    """One clean run's results, and a copy of the folder it left for ``warm_copy``."""
    base = tmp_path_factory.mktemp("trust")
    results, used, err = fit_with_cache(base / "cache")
    assert used == str(base / "cache") and warning_count(err) == 0, err
    shutil.copytree(base / "cache", base / "pristine")
    return results, base


def sources(folder: Path) -> set[str]:
    """The jaxfit sources (digests) the folder holds programs of."""
    return {p.name for p in (folder / _cache.EXPORTED).iterdir()}


def warm_copy(clean) -> Path:
    """The clean run's folder as it left it, at the path it ran in (JAX's keys depend on
    the cache folder's path: it passes XLA a cache path inside it), with the programs of
    jaxfit's source as it is now (made again if the source was edited since)."""
    results, base = clean
    folder = base / "cache"
    shutil.rmtree(folder, ignore_errors=True)
    shutil.copytree(base / "pristine", folder)
    if sources(folder) != {_cache._source_digest.__wrapped__()[:16]}:
        shutil.rmtree(folder)
        assert fit_with_cache(folder)[0] == results
    return folder


def read_the_copy(folder: Path) -> None:
    """Skip unless the last run read the programs of the copy (not those of a source
    edited meanwhile, which would make the test pass without reading them)."""
    if len(sources(folder)) != 1:
        pytest.skip("jaxfit's source changed while the test ran; rerun it")


def programs(folder: Path) -> dict[str, Path]:
    """The stored programs of a folder by the name their tag is keyed on."""
    root = folder / _cache.EXPORTED
    return {p.relative_to(root).with_suffix("").as_posix(): p for p in exported(folder)}


def plus_three_tenths(blob: bytes) -> bytes:
    """A valid program of the same arguments as ``blob``'s that adds 0.3 to its
    floating-point results (what someone could plant to falsify fits)."""
    import jax
    import jax.numpy as jnp
    from jax import export

    genuine = export.deserialize(bytearray(blob))
    args, kwargs = jax.tree_util.tree_unflatten(
        genuine.in_tree, [jax.ShapeDtypeStruct(a.shape, a.dtype, weak_type=a.weak_type)
                          for a in genuine.in_avals])

    def planted(*args, **kwargs):
        return jax.tree_util.tree_map(
            lambda r: r + 0.3 if jnp.issubdtype(r.dtype, jnp.floating) else r,
            genuine.call(*args, **kwargs))

    return export.export(jax.jit(planted))(*args, **kwargs).serialize()


@pytest.mark.parametrize("forgery", ["raw program", "tag of another key"])
def test_a_planted_program_is_not_run(clean, tmp_path, forgery):
    """Someone who can write into the folder but not read the user's key replaces every
    stored program with one of the same arguments that shifts the results: none is run,
    the fit equals the clean one and the files are replaced by genuine ones."""
    folder = warm_copy(clean)
    secret = (folder / _cache.KEY_FILE).read_bytes()
    planted = {}
    for name, path in programs(folder).items():
        evil = plus_three_tenths(_cache.unseal(path.read_bytes(), name, secret))
        if forgery == "tag of another key":
            evil = _cache.seal(evil, name, os.urandom(_cache.KEY_BYTES))
        path.write_bytes(evil)
        planted[name] = evil
    results, used, err = fit_with_cache(folder)
    read_the_copy(folder)
    assert used == str(folder) and results == clean[0]
    assert warning_count(err) == 0, err
    for name, path in programs(folder).items():
        assert path.read_bytes() != planted[name]
        _cache.unseal(path.read_bytes(), name, secret)  # signed again with the key


def test_a_program_copied_over_another_name_is_replaced(clean, tmp_path):
    folder = warm_copy(clean)
    (first, source), (second, target) = sorted(programs(folder).items())
    target.write_bytes(source.read_bytes())
    results, used, err = fit_with_cache(folder)
    read_the_copy(folder)
    assert used == str(folder) and results == clean[0]
    assert warning_count(err) == 0 and "tree" not in err.lower(), err
    secret = (folder / _cache.KEY_FILE).read_bytes()
    assert target.read_bytes() != source.read_bytes()
    _cache.unseal(target.read_bytes(), second, secret)


def test_a_program_copied_over_one_of_the_same_arguments_is_not_run(tmp_path, monkeypatch):
    """The factor-2 program under the factor-3 one's name takes the same arguments (it
    passes ``_takes``), so only its tag, keyed on the name, tells it apart."""
    import numpy as np

    traced = []
    x = np.arange(4, dtype=np.float32)
    _stored_square(tmp_path, monkeypatch, traced)(x, factor=3)
    (three,) = exported(tmp_path)
    _stored_square(tmp_path, monkeypatch, traced)(x, factor=2)
    (two,) = set(exported(tmp_path)) - {three}
    three.write_bytes(two.read_bytes())
    again = _stored_square(tmp_path, monkeypatch, traced)
    np.testing.assert_array_equal(again(x, factor=3), 3 * x * x)
    assert len(traced) == 3 and three.read_bytes() != two.read_bytes()


def test_a_program_from_another_cache_folder_is_not_run(tmp_path, monkeypatch):
    import numpy as np

    traced = []
    x = np.arange(4, dtype=np.float32)
    _stored_square(tmp_path / "a", monkeypatch, traced)(x, factor=3)
    _stored_square(tmp_path / "b", monkeypatch, traced)(x, factor=3)
    (a,), (b,) = exported(tmp_path / "a"), exported(tmp_path / "b")
    assert a.relative_to(tmp_path / "a") == b.relative_to(tmp_path / "b")  # one name
    b.write_bytes(a.read_bytes())  # valid, same name, but signed with a's key
    again = _stored_square(tmp_path / "b", monkeypatch, traced)
    np.testing.assert_array_equal(again(x, factor=3), 3 * x * x)
    assert len(traced) == 3 and b.read_bytes() != a.read_bytes()


@pytest.mark.skipif(not hasattr(os, "getuid"), reason="POSIX ownership and modes")
@pytest.mark.parametrize("owner", ["this user", "another user"])
def test_a_world_writable_folder_is_not_used(clean, tmp_path, owner):
    folder = warm_copy(clean)
    if owner == "another user":
        if os.geteuid() != 0:
            pytest.skip("giving the folder to another user (uid 65534) needs root")
        for path in [folder, *folder.rglob("*")]:
            os.chown(path, 65534, 65534)
    folder.chmod(0o777)
    results, used, err = fit_with_cache(folder)
    assert used is None and results == clean[0]
    assert warning_count(err) == 1 and err.count("compilation cache disabled") == 1, err


def test_a_truncated_jax_entry_is_written_again(clean, tmp_path):
    """JAX never rewrites an entry whose file exists: jaxfit deletes one that fails to
    load, so it warns once (JAX's warning) and the next process reads it silently."""
    folder = warm_copy(clean)
    entry = max(entries(folder), key=lambda p: p.stat().st_size)
    cut = entry.read_bytes()[: entry.stat().st_size // 2]
    entry.write_bytes(cut)
    results, used, err = fit_with_cache(folder)
    read_the_copy(folder)
    assert used == str(folder) and results == clean[0]
    assert warning_count(err) <= 1, err
    assert entry.exists() and entry.read_bytes() != cut
    results, _, err = fit_with_cache(folder)
    assert results == clean[0] and warning_count(err) == 0, err


def test_seal_binds_the_name_and_the_key():
    secret, other = os.urandom(32), os.urandom(32)
    sealed = _cache.seal(b"program", "abc/def", secret)
    assert _cache.unseal(sealed, "abc/def", secret) == b"program"
    flipped = bytearray(sealed)
    flipped[-1] ^= 1
    for data, name, key in [(sealed, "abc/deg", secret), (sealed, "abc/def", other),
                            (sealed[:-1], "abc/def", secret), (bytes(flipped), "abc/def", secret),
                            (b"program", "abc/def", secret), (b"", "abc/def", secret)]:
        with pytest.raises(ValueError):
            _cache.unseal(data, name, key)


@pytest.mark.skipif(not hasattr(os, "getuid"), reason="POSIX ownership and modes")
def test_the_key_file_is_private_and_kept(tmp_path):
    path = tmp_path / _cache.KEY_FILE
    secret = _cache._load_secret(path)
    assert len(secret) == _cache.KEY_BYTES and path.read_bytes() == secret
    assert path.stat().st_mode & 0o777 == 0o600
    assert _cache._load_secret(path) == secret
    assert [p.name for p in tmp_path.iterdir()] == [_cache.KEY_FILE]  # no temporary left


@pytest.mark.skipif(not hasattr(os, "getuid"), reason="POSIX ownership and modes")
@pytest.mark.parametrize("flaw", ["group-readable", "short", "long", "a link", "a folder",
                                  "another user's"])
def test_a_key_file_that_cannot_be_trusted_is_made_again(tmp_path, flaw):
    path = tmp_path / _cache.KEY_FILE
    secret = _cache._load_secret(path)
    if flaw == "group-readable":
        path.chmod(0o640)
    elif flaw in ("short", "long"):
        path.write_bytes(secret[:-1] if flaw == "short" else secret + b"x")
    elif flaw == "a link":
        path.unlink()
        (tmp_path / "elsewhere").write_bytes(secret)
        (tmp_path / "elsewhere").chmod(0o600)
        path.symlink_to(tmp_path / "elsewhere")
    elif flaw == "a folder":
        path.unlink()
        path.mkdir()
    else:
        if os.geteuid() != 0:
            pytest.skip("giving the key file to another user (uid 65534) needs root")
        os.chown(path, 65534, 65534)
    if path.is_dir():
        assert _cache._load_secret(path) is None  # cannot replace a folder: no programs
        return
    fresh = _cache._load_secret(path)
    assert fresh is not None and fresh != secret and path.read_bytes() == fresh
    st = path.lstat()
    assert stat.S_ISREG(st.st_mode) and st.st_mode & 0o777 == 0o600
    assert st.st_uid == os.getuid()


def test_processes_making_the_key_at_once_agree(tmp_path):
    """First writer wins: every concurrent maker returns the key that ends up on disk."""
    path = tmp_path / _cache.KEY_FILE
    barrier = threading.Barrier(8)

    def make(_):
        barrier.wait()
        return _cache._load_secret(path)

    with concurrent.futures.ThreadPoolExecutor(8) as pool:
        keys = set(pool.map(make, range(8)))
    assert keys == {path.read_bytes()}


def test_the_jax_entry_guard_leaves_another_jax_alone(monkeypatch):
    from jax._src import compilation_cache

    assert _cache._guard_jax_entries()  # installed (once) on import, idempotent
    guarded = compilation_cache.get_executable_and_time
    assert _cache._guard_jax_entries() and compilation_cache.get_executable_and_time is guarded
    monkeypatch.delattr(compilation_cache, "get_executable_and_time")
    assert _cache._guard_jax_entries() is False


def test_an_entry_outside_jaxfit_folder_is_never_deleted(tmp_path, monkeypatch):
    theirs = tmp_path / "theirs"
    theirs.mkdir()
    (theirs / "k-cache").write_bytes(b"broken")
    monkeypatch.setattr(_cache, "_enabled_dir", str(tmp_path / "ours"))

    class Cache:
        _path = theirs

    _cache._drop_entry(Cache(), "k", "-cache")
    assert (theirs / "k-cache").exists()
    monkeypatch.setattr(_cache, "_enabled_dir", str(theirs))
    _cache._drop_entry(Cache(), "../k", "-cache")  # not a plain name
    assert (theirs / "k-cache").exists()
    _cache._drop_entry(Cache(), "k", "-cache")
    assert not (theirs / "k-cache").exists()


def test_a_stored_program_that_fails_when_run_is_dropped(tmp_path, monkeypatch):
    """A signed program of the right arguments that fails in its first call (seen once
    in a shared tree: "Failed to deserialize StableHLO" raised out of decompose) gives
    the plain jit's result and its file is removed, instead of the error."""
    import numpy as np
    from jax import export

    traced = []
    x = np.arange(4, dtype=np.float32)
    _stored_square(tmp_path, monkeypatch, traced)(x, factor=3)
    (path,) = exported(tmp_path)
    real = export.deserialize

    class Failing:
        def __init__(self, inner):
            self.inner = inner

        def __getattr__(self, name):
            return getattr(self.inner, name)

        def call(self, *args, **kwargs):
            raise RuntimeError("Failed to deserialize StableHLO")

    monkeypatch.setattr(export, "deserialize", lambda blob: Failing(real(blob)))
    again = _stored_square(tmp_path, monkeypatch, traced)
    np.testing.assert_array_equal(again(x, factor=3), 3 * x * x)
    assert not path.exists()
    np.testing.assert_array_equal(again(x, factor=3), 3 * x * x)  # the plain jit from now on


def test_a_jax_without_scoped_settings_gets_the_folder_for_the_process(tmp_path, monkeypatch):
    updates = {}
    monkeypatch.setattr(_cache.jax.config, "update", lambda name, value: updates.update(
        {name: value}))
    monkeypatch.setattr(_cache, "_enabled_dir", None)
    monkeypatch.setattr(_cache, "_jax_configured", lambda: False)
    monkeypatch.setattr(_cache, "_scoped_settings", lambda: None)
    folder = tmp_path / "cache"
    assert _cache.enable({_cache.ENV_DIR: str(folder)}) == str(folder)
    assert updates == {"jax_compilation_cache_dir": str(folder),
                       "jax_persistent_cache_min_compile_time_secs": 0.0,
                       "jax_persistent_cache_min_entry_size_bytes": -1}
    assert not _cache._outside_scope()  # (JAX's cache then serves every compilation)
    with _cache.scope():  # a no-op
        assert _cache.jax.config.jax_compilation_cache_dir != str(folder)


def test_scope_sets_the_folder_in_its_thread_only(tmp_path, monkeypatch):
    monkeypatch.setattr(_cache, "_enabled_dir", str(tmp_path))
    seen, before = {}, _cache.jax.config.jax_compilation_cache_dir  # (the process's own)
    with _cache.scope():
        seen["inside"] = _cache.jax.config.jax_compilation_cache_dir
        other = threading.Thread(target=lambda: seen.update(
            other=_cache.jax.config.jax_compilation_cache_dir))
        other.start()
        other.join()
        assert not _cache._outside_scope()
    assert seen == {"inside": str(tmp_path), "other": before}
    assert _cache._outside_scope() and _cache.jax.config.jax_compilation_cache_dir == before


def test_threads_making_a_stored_programs_first_call_at_once_agree(tmp_path, monkeypatch):
    import numpy as np

    traced = []
    x = np.arange(4, dtype=np.float32)
    _stored_square(tmp_path, monkeypatch, traced)(x, factor=3)  # written to the folder
    again = _stored_square(tmp_path, monkeypatch, traced)  # as in the next process
    start = threading.Barrier(8)

    def call(_):
        start.wait()
        return again(x, factor=3)

    # (the first call of a program read from disk had raised KeyError in all threads
    # but one: warmup's threads met it)
    with concurrent.futures.ThreadPoolExecutor(8) as pool:
        found = list(pool.map(call, range(8)))
    for out in found:
        np.testing.assert_array_equal(out, 3 * x * x)
    assert len(traced) == 1 and not again.unproven


def test_the_collector_is_paused_only_while_programs_are_made():
    """``_gc.paused``: the cyclic collector is off inside (nested blocks and other
    threads' blocks share one pause) and back as it was after the last one ends; a
    collector the user turned off stays off."""
    import gc

    from jaxfit import _gc

    assert gc.isenabled()
    done = threading.Event()
    with _gc.paused():
        assert not gc.isenabled()

        def other():
            with _gc.paused():
                done.wait(10)

        thread = threading.Thread(target=other)
        thread.start()
        with _gc.paused():
            assert not gc.isenabled()
    assert not gc.isenabled()  # (the other thread's block still runs)
    done.set()
    thread.join()
    assert gc.isenabled()
    gc.disable()
    try:
        with _gc.paused():
            pass
        assert not gc.isenabled()
    finally:
        gc.enable()
