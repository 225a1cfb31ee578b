"""JAX's persistent compilation cache, switched on for jaxfit when it is imported.

Compiling one kernel takes ~0.6 s and a whole-process single fit is mostly compilation
(PERF.md), so the compiled XLA executables are kept on disk and reused by later processes:

- where: ``$JAXFIT_CACHE_DIR`` if set, else ``<user cache>/jaxfit/jax-<jax version>`` with
  ``<user cache>`` = ``$XDG_CACHE_HOME`` or ``~/.cache`` (``~/Library/Caches`` on macOS,
  ``%LOCALAPPDATA%`` on Windows). One folder per JAX version, so an upgrade starts clean
  instead of piling stale entries into the folder in use.
- off: ``JAXFIT_CACHE=0`` (or ``false``, ``no``, ``off``) before importing jaxfit.
- never overrides JAX: if a cache directory is already configured (``JAX_COMPILATION_CACHE_DIR``,
  ``jax.config.update("jax_compilation_cache_dir", ...)``) or JAX's cache is disabled
  (``JAX_ENABLE_COMPILATION_CACHE=false``), jaxfit changes nothing, thresholds included.
- never fails an import: an unusable directory gives one ``RuntimeWarning`` and no cache.

The thresholds are lowered because JAX by default only stores executables that took >= 1 s
to compile, and ours take 0.2-0.8 s each. This is a process-wide JAX setting: while jaxfit's
cache is on, the user's own jitted functions are cached in the same folder too.

Sharing the folder between processes (checked in jax 0.10.2, ``jax/_src/lru_cache.py`` and
``compiler.py``): every executable is its own file named by a hash of the program, the
compile options, the backend and the jax/jaxlib versions, so processes never write
different contents under one name; ``put`` skips keys whose file exists, so an entry is
written once and never rewritten while read. A reader that catches a file mid-write (or a
file truncated by a crash) gets compressed data that fails zlib's length and checksum check,
and JAX catches every cache read error (``jax_raise_persistent_cache_errors`` is False by
default): it warns and compiles instead. There are no lock files to go stale, because the
cache is unbounded (``jax_compilation_cache_max_size`` = -1; bounding it makes JAX lock
with the optional ``filelock`` package). Delete the folder to clear it.
"""

from __future__ import annotations

import os
import sys
import tempfile
import warnings
from pathlib import Path

import jax

#: Environment variable that turns the cache off when set to one of ``OFF_VALUES``.
ENV_SWITCH = "JAXFIT_CACHE"
#: Environment variable naming another cache folder.
ENV_DIR = "JAXFIT_CACHE_DIR"
OFF_VALUES = frozenset({"0", "false", "no", "off"})

_enabled_dir: str | None = None  # the folder jaxfit configured, None if it configured none


def user_cache_root(environ=os.environ, platform: str = sys.platform) -> Path:
    """The per-user cache folder of the platform (XDG on Linux)."""
    if environ.get("XDG_CACHE_HOME"):
        return Path(environ["XDG_CACHE_HOME"])
    if platform == "darwin":
        return Path.home() / "Library" / "Caches"
    if platform == "win32" and environ.get("LOCALAPPDATA"):
        return Path(environ["LOCALAPPDATA"])
    return Path.home() / ".cache"


def wanted_dir(environ=os.environ, platform: str = sys.platform) -> Path | None:
    """The folder jaxfit should cache in, or None when the user turned the cache off."""
    if environ.get(ENV_SWITCH, "").strip().lower() in OFF_VALUES:
        return None
    if environ.get(ENV_DIR):
        return Path(environ[ENV_DIR]).expanduser()
    return user_cache_root(environ, platform) / "jaxfit" / f"jax-{jax.__version__}"


def unusable(path: Path) -> str | None:
    """Why ``path`` cannot hold the cache (created if missing), or None if it can.

    A probe file is written because a folder can exist and still refuse writes (read-only
    mounts, another user's folder); mkstemp gives each process its own probe name.
    """
    try:
        path.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".probe-", dir=path)
        os.close(fd)
        os.unlink(probe)
    except OSError as err:
        return f"{type(err).__name__}: {err}"
    return None


def _jax_configured() -> bool:
    """Whether the user already chose JAX's cache settings (a folder, or disabling it)."""
    return (jax.config.jax_compilation_cache_dir is not None
            or not jax.config.jax_enable_compilation_cache)


def enable(environ=os.environ) -> str | None:
    """Turn the persistent cache on as configured by the environment; called on import.

    Returns the folder jaxfit set, or None when it set none (off, JAX already configured by
    the user, or the folder unusable, which warns once).
    """
    global _enabled_dir
    path = wanted_dir(environ)
    if path is None or _jax_configured():
        return None
    reason = unusable(path)
    if reason is not None:
        warnings.warn(f"jaxfit: compilation cache disabled, cannot write to {path} ({reason}); "
                      f"set {ENV_DIR} to another folder or {ENV_SWITCH}=0 to silence this",
                      RuntimeWarning, stacklevel=2)
        return None
    jax.config.update("jax_compilation_cache_dir", str(path))
    # Store every executable: ours compile in well under JAX's 1 s default. -1 also stops
    # JAX from raising the size floor for the filesystem.
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
    _enabled_dir = str(path)
    return _enabled_dir


def compilation_cache_dir() -> str | None:
    """The folder JAX's persistent compilation cache uses in this process, or None if off.

    It is jaxfit's own folder unless the user configured JAX's cache first (then theirs).
    Turn jaxfit's off with ``JAXFIT_CACHE=0`` or move it with ``JAXFIT_CACHE_DIR``, both set
    before ``import jaxfit``.
    """
    if not jax.config.jax_enable_compilation_cache:
        return None
    return jax.config.jax_compilation_cache_dir
