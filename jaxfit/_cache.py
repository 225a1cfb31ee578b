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

JAX's cache is keyed by the lowered program, so every process still traces and lowers each
kernel before it can look the program up: 0.5-0.9 s per primitive, most of a warm
whole-process fit. jaxfit's kernels (``Stored``) therefore also keep the lowered program
itself, as a ``jax.export`` module (JAX's public, versioned serialization of StableHLO), in
the ``exported`` sub-folder, keyed by what the program depends on (jaxfit's source, the JAX
versions, the devices, JAX's numeric settings, ``XLA_FLAGS``, the call's static values and
argument shapes). A later process reads it and skips tracing and lowering; the program is
then compiled, or found in JAX's cache, as before. Each file is written to a temporary name
and renamed into place, so a reader sees a whole file or none; a file that fails to load is
exported again and replaced. (Serialized *executables* were tried first and dropped: on the
CPU one that calls LAPACK crashed a fresh process, and one JAX had itself read from its
cache was saved without its machine code.)
"""

from __future__ import annotations

import functools
import hashlib
import inspect
import os
import sys
import tempfile
import warnings
from pathlib import Path

import jax
import numpy as np

#: Environment variable that turns the cache off when set to one of ``OFF_VALUES``.
ENV_SWITCH = "JAXFIT_CACHE"
#: Environment variable naming another cache folder.
ENV_DIR = "JAXFIT_CACHE_DIR"
OFF_VALUES = frozenset({"0", "false", "no", "off"})

_enabled_dir: str | None = None  # the folder jaxfit configured, None if it configured none


def user_cache_root(environ=os.environ, platform: str = sys.platform) -> Path:
    """The per-user cache folder of the platform (XDG on Linux: a relative
    ``XDG_CACHE_HOME`` is ignored, as the XDG spec says)."""
    if environ.get("XDG_CACHE_HOME") and Path(environ["XDG_CACHE_HOME"]).is_absolute():
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

    The folder must be the user's own and not writable by others (``unsafe``): jaxfit
    runs the programs it finds there. A probe file is written because a folder can exist
    and still refuse writes (read-only mounts); mkstemp gives each process its own probe.
    """
    try:
        path.mkdir(mode=0o700, parents=True, exist_ok=True)
        if (reason := unsafe(path)) is not None:
            return reason
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
    try:
        path = wanted_dir(environ)
    except (RuntimeError, KeyError, OSError) as err:  # no home folder (no HOME, no passwd)
        warnings.warn(f"jaxfit: compilation cache disabled, no user cache folder ({err}); "
                      f"set {ENV_DIR} to a folder or {ENV_SWITCH}=0 to silence this",
                      RuntimeWarning, stacklevel=2)
        return None
    if path is None or _jax_configured():
        return None
    reason = unusable(path)
    if reason is not None:
        warnings.warn(f"jaxfit: compilation cache disabled, cannot use {path} ({reason}); "
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


#: Sub-folder of jaxfit's cache folder that holds the ``Stored`` kernels' programs, in one
#: folder per jaxfit source (a program traced from other code is never read).
EXPORTED = "exported"


@functools.cache
def _source_digest() -> str:
    """Hash of jaxfit's own source files: a program traced from other code is stale."""
    digest = hashlib.sha256()
    root = Path(__file__).resolve().parent
    for path in sorted(root.rglob("*.py")):
        digest.update(path.relative_to(root).as_posix().encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()


def _settings() -> tuple:
    """JAX's settings that change how a function traces; part of every call's signature,
    since a user may change them between calls."""
    cfg = jax.config
    return (cfg.jax_enable_x64, cfg.jax_default_prng_impl, cfg.jax_threefry_partitionable,
            cfg.jax_default_matmul_precision,
            cfg.jax_numpy_dtype_promotion, cfg.jax_numpy_rank_promotion)


def _environment() -> tuple:
    """What a traced program depends on besides its call's signature (read per new
    signature)."""
    import jaxlib

    return (_source_digest(), jax.__version__, jaxlib.__version__,
            tuple((d.platform, d.device_kind, d.id) for d in jax.local_devices()),
            os.environ.get("XLA_FLAGS", ""))


def _leaf_signature(leaf):
    """Shape, dtype and weak type of one dynamic argument, or None where the call is left
    to the plain jitted function: a tracer (the kernel is being traced into another) or
    an array split over several devices (its sharding would be part of the program)."""
    if isinstance(leaf, jax.core.Tracer):
        return None
    # (dtypes themselves, not their str: that alone cost 5 us a leaf, on every call)
    if isinstance(leaf, jax.Array):
        if len(leaf.devices()) > 1:
            return None
        return (leaf.shape, leaf.dtype, getattr(leaf, "weak_type", False))
    if isinstance(leaf, np.ndarray | np.generic):
        return (leaf.shape, leaf.dtype)
    if isinstance(leaf, bool | int | float | complex):
        return (type(leaf).__name__,)  # weakly typed scalars: the value is not compiled in
    return None


@functools.lru_cache(maxsize=1024, typed=True)
def _static_value(value):
    """A static argument as it enters the key: classes by name, everything else by repr
    (kept per value: static arguments are hashable, and a stage's repr costs ~2 us)."""
    if isinstance(value, type):
        return f"{value.__module__}.{value.__qualname__}"
    return repr(value)


class Stored:
    """A jitted function whose traced programs are kept in ``EXPORTED`` between processes
    (see the module docstring), called like the function itself. Without jaxfit's cache
    folder, for arguments it cannot key, or if JAX cannot export the function, it calls
    the jitted function.

    ``jitted``: ``jax.jit`` of ``fn`` with ``static_argnames`` and the compiler
    ``options``, which the reloaded program is compiled with too.
    """

    def __init__(self, jitted, fn, static_argnames=(), options=None):
        self.jitted, self.name = jitted, f"{fn.__module__}.{fn.__qualname__}"
        params = list(inspect.signature(fn).parameters)
        self.static_names = frozenset(static_argnames)
        self.static_positions = frozenset(params.index(n) for n in static_argnames)
        self.options = dict(options or {})
        self.kernels: dict = {}  # signature -> callable of the dynamic arguments
        functools.update_wrapper(self, fn)

    def __call__(self, *args, **kwargs):
        if _enabled_dir is None:
            return self.jitted(*args, **kwargs)
        dyn_args = tuple(a for i, a in enumerate(args) if i not in self.static_positions)
        dyn_kwargs = {k: v for k, v in kwargs.items() if k not in self.static_names}
        leaves, tree = jax.tree_util.tree_flatten((dyn_args, dyn_kwargs))
        shapes = tuple(_leaf_signature(leaf) for leaf in leaves)
        if None in shapes:
            return self.jitted(*args, **kwargs)
        static = tuple(_static_value(a) for i, a in enumerate(args)
                       if i in self.static_positions)
        static += tuple((k, _static_value(v)) for k, v in sorted(kwargs.items())
                        if k in self.static_names)
        signature = (static, str(tree), shapes, _settings())
        kernel = self.kernels.get(signature)
        if kernel is None:
            kernel = self.kernels[signature] = self._kernel(signature, args, kwargs, leaves,
                                                            tree)
        if kernel is self.jitted:
            return self.jitted(*args, **kwargs)
        return kernel(*dyn_args, **dyn_kwargs)

    def _kernel(self, signature, args, kwargs, leaves, tree):
        """The jitted call of the exported program for one signature: read from the
        folder (only a file of this user's that no one else can write, holding a program
        of this call's arguments), or exported (traced and lowered) now and written there;
        ``self.jitted`` where JAX cannot export it. ``leaves`` and ``tree``: the call's
        dynamic arguments, flattened."""
        from jax import export

        key = repr((self.name, sorted(self.options.items()), _environment(), signature))
        # One sub-folder per jaxfit source: those of older versions can be deleted whole.
        path = (Path(_enabled_dir) / EXPORTED / _source_digest()[:16]
                / f"{hashlib.sha256(key.encode()).hexdigest()}.jaxexport")
        try:
            if (reason := unsafe(path)) is not None:
                raise OSError(reason)
            exported = export.deserialize(bytearray(path.read_bytes()))
            if not _takes(exported, leaves, tree):
                raise ValueError("a program of other arguments")
        except Exception:  # missing, partial, unreadable, not ours or not this call's:
            # export it (again) and replace the file
            try:
                exported = export.export(self.jitted)(*args, **kwargs)
                blob = exported.serialize()
            except Exception:  # (a real error in the call is raised by the jitted one)
                return self.jitted
            _write(path, blob)
        options = {"compiler_options": self.options} if self.options else {}
        return jax.jit(exported.call, **options)


def _takes(exported, leaves, tree) -> bool:
    """Whether an exported program takes these arguments: the same tree of dynamic
    arguments, shapes and dtypes, on one device of this backend (a file copied over
    another's name fails here instead of in the call, as a user error)."""
    if exported.in_tree != tree or len(exported.in_avals) != len(leaves):
        return False
    if exported.nr_devices != 1 or jax.default_backend() not in exported.platforms:
        return False
    return all(tuple(aval.shape) == tuple(np.shape(leaf))
               and aval.dtype == jax.numpy.result_type(leaf)
               for aval, leaf in zip(exported.in_avals, leaves, strict=True))


def unsafe(path: Path) -> str | None:
    """Why the file or folder ``path`` may not be trusted, or None: on POSIX it must be
    the current user's and not writable by group or others (as OpenSSH treats key files),
    since jaxfit runs the programs it reads from there."""
    if not hasattr(os, "getuid"):
        return None
    try:
        st = path.stat()
    except OSError as err:
        return f"{type(err).__name__}: {err}"
    if st.st_uid != os.getuid():
        return f"{path} belongs to uid {st.st_uid}, not to this user ({os.getuid()})"
    if st.st_mode & 0o022:
        return (f"{path} is writable by group or others (mode {st.st_mode & 0o777:o}): "
                "anyone could plant programs that jaxfit would run; chmod go-w it")
    return None


def stored_jit(fn, static_argnames=(), options=None) -> Stored:
    """``jax.jit`` of fn (with compiler ``options``), its traced programs kept between
    processes (``Stored``)."""
    jitted = jax.jit(fn, static_argnames=static_argnames,
                     **({"compiler_options": options} if options else {}))
    return Stored(jitted, fn, static_argnames, options)


def _write(path: Path, blob) -> None:
    """Write blob to path all at once (a temporary file renamed into place), or not at all
    (an unwritable folder or a full disk only costs the next process a trace)."""
    from .io.atomic import replacing

    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with replacing(path, private=True) as temporary:
            temporary.write_bytes(blob)
    except OSError:
        pass
