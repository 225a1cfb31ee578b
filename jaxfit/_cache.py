"""JAX's persistent compilation cache, switched on for jaxfit when it is imported, plus
jaxfit's own store of its kernels' traced programs (see docs/cache.md for the reasons,
JAX's internals this relies on, and measurements).

- where: ``$JAXFIT_CACHE_DIR`` if set, else ``<user cache>/jaxfit/jax-<jax version>`` with
  ``<user cache>`` = ``$XDG_CACHE_HOME`` or ``~/.cache`` (``~/Library/Caches`` on macOS,
  ``%LOCALAPPDATA%`` on Windows). One folder per JAX version.
- off: ``JAXFIT_CACHE=0`` (or ``false``, ``no``, ``off``) before importing jaxfit.
- never overrides JAX: if a cache directory is already configured (``JAX_COMPILATION_CACHE_DIR``,
  ``jax.config.update("jax_compilation_cache_dir", ...)``) or JAX's cache is disabled
  (``JAX_ENABLE_COMPILATION_CACHE=false``), jaxfit changes nothing, thresholds included.
- never fails an import: an unusable directory gives one ``RuntimeWarning`` and no cache.
- jaxfit's compilations only: JAX's settings are not changed for the process. The folder,
  and thresholds that store every executable (ours compile in 0.1-3 s, many under JAX's
  1 s default), are set thread-locally while a ``Stored`` kernel is traced and first
  called (``scope``), and JAX's cache reads and writes nothing in jaxfit's folder outside
  that (``_guard_jax_entries``): a user's own jitted functions are not cached there (the
  folder had been set for the whole process on import; docs/cache.md, "Library manners").

Stored programs: JAX looks an executable up by the lowered program, so every process would
still trace and lower each kernel first. ``Stored`` kernels therefore also keep the program
(a ``jax.export`` module) in ``exported/<source digest>/<sha256 of the key>.jaxexport``,
keyed by everything it depends on (jaxfit's source, the JAX versions, the devices, JAX's
numeric settings, ``XLA_FLAGS``, the call's static values and argument shapes). Files are
written to a temporary name and renamed into place.

A stored program that makes no LAPACK call is first called inside ``without_lapack``:
``jax.export`` starts LAPACK (importing scipy.linalg) for every program it calls on the
CPU, which had been a warm process's largest cost after importing JAX itself.

Trust contract (jaxfit runs what it reads there):

- the folder must belong to the user and not be writable by group or others (POSIX), else
  one warning and no cache at all;
- a stored program is run only if its file belongs to the user, is not writable by others,
  carries the HMAC-SHA256 tag of (its name, the program) under the folder's secret key
  (``exported.key``: 32 random bytes, mode 0600, made once by the first process, remade
  if it is not a user-only regular file of that length), and takes the call's arguments
  (``_takes``). Anything else (planted, copied over another name or from another folder,
  cut short) is exported again and the file replaced, never run;
- an entry of JAX's own cache that JAX fails to read (cut short, corrupt) is deleted, so
  JAX writes it again after compiling: one JAX warning, then none (``_guard_jax_entries``;
  with another JAX whose private names differ, nothing is hooked).

Not defended: anyone who can read the user's files (the key) or write as the user, and
the executables in JAX's own entries, which JAX deserializes unsigned (the folder's
ownership and mode are what protect those).
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import hmac
import inspect
import os
import secrets
import stat
import sys
import tempfile
import threading
import time
import warnings
from pathlib import Path

import jax
import numpy as np

from ._gc import paused

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
    """Choose jaxfit's cache folder as configured by the environment (created if
    missing); called on import. JAX's own settings are left as they are: jaxfit's
    compilations use the folder through ``scope``.

    Returns the folder jaxfit chose, or None when it chose none (off, JAX already
    configured by the user, or the folder unusable, which warns once).
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
    _enabled_dir = str(path)
    if _scoped_settings() is None:  # another JAX: for the whole process, as before
        jax.config.update("jax_compilation_cache_dir", _enabled_dir)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
    # (else JAX's settings are set only around jaxfit's own compilations: ``scope``)
    _guard_jax_entries()
    return _enabled_dir


def _scoped_settings():
    """JAX's thread-local context managers of (the cache folder, the least compile time,
    the least entry size) that ``scope`` sets (jax 0.10.2's ``jax._src.config`` states),
    or None where this JAX has them under other names."""
    try:
        from jax._src import config

        states = (config.compilation_cache_dir,
                  config.persistent_cache_min_compile_time_secs,
                  config.persistent_cache_min_entry_size_bytes)
        if not all(callable(state) for state in states):
            return None
        return states
    except Exception:
        return None


_inside = threading.local()  # .depth: how many ``scope`` blocks this thread is in


@contextlib.contextmanager
def scope():
    """Within it (in this thread), JAX's persistent cache uses jaxfit's folder and stores
    every executable (thresholds 0 s and -1 bytes: ours compile in well under JAX's 1 s
    default, and -1 also stops JAX from raising the size floor for the filesystem);
    a no-op when jaxfit configured no folder. Outside it JAX's settings are the user's."""
    states = None if _enabled_dir is None else _scoped_settings()
    if states is None:  # (no folder, or set for the whole process by ``enable``)
        yield
        return
    folder, least_time, least_size = states
    _inside.depth = getattr(_inside, "depth", 0) + 1
    try:
        with folder(_enabled_dir), least_time(0.0), least_size(-1):
            yield
    finally:
        _inside.depth -= 1


def _outside_scope() -> bool:
    """Whether JAX's cache is asked outside jaxfit's ``scope`` (always False where the
    folder was set for the whole process)."""
    return (_enabled_dir is not None and not getattr(_inside, "depth", 0)
            and _scoped_settings() is not None)


def compilation_cache_dir() -> str | None:
    """The folder JAX's persistent compilation cache uses in this process, or None if off.

    It is jaxfit's own folder unless the user configured JAX's cache first (then theirs).
    Turn jaxfit's off with ``JAXFIT_CACHE=0`` or move it with ``JAXFIT_CACHE_DIR``, both set
    before ``import jaxfit``.
    """
    if _enabled_dir is not None:
        return _enabled_dir
    if not jax.config.jax_enable_compilation_cache:
        return None
    return jax.config.jax_compilation_cache_dir


def compile_notice() -> str | None:
    """A one-line notice for a process that will compile jaxfit's kernels from scratch
    (no stored program of this jaxfit source in the cache folder, or the cache off), or
    None when they were stored by an earlier run."""
    if _enabled_dir is None:
        if compilation_cache_dir() is None:
            return ("jaxfit: compiling kernels (the compilation cache is off: every run "
                    "compiles, a few seconds per primitive)")
        return None  # the user's own JAX cache folder: its state is theirs
    folder = Path(_enabled_dir) / EXPORTED / _source_digest()[:16]
    try:
        stored = any(folder.glob("*.jaxexport"))
    except OSError:
        stored = False
    if stored:
        return None
    return (f"jaxfit: compiling kernels (first run only: they are kept in {_enabled_dir}, "
            "a few seconds per primitive)")


_notice: list = []  # ``announce``'s notice, until a first call prints it


def announce(notice: str | None) -> None:
    """Print ``notice`` (``compile_notice``'s, or None for none) on stderr once, when the
    process's first ``Stored`` call is about to trace or compile a program: a run that
    stops before (bad input, a missing file) does not say it compiles."""
    _notice[:] = [] if notice is None else [notice]


def _announce() -> None:
    try:
        notice = _notice.pop()  # (atomic: one thread prints it)
    except IndexError:
        return
    print(notice, file=sys.stderr, flush=True)


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
    folder or its key, for arguments it cannot key, or if JAX cannot export the function,
    it calls the jitted function.

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
        self.unproven: dict = {}  # signature -> file of a program read but not yet run
        # Signatures whose first call has returned (their program is compiled), and one
        # lock per signature for that first call: threads (warmup's, the refinement
        # compiled ahead) may make the same first call at once.
        self.ready: set = set()
        self.first_calls: dict = {}
        # Signatures whose exported program makes no LAPACK call: its first call skips
        # LAPACK's start-up (``without_lapack``).
        self.lapack_free: set = set()
        functools.update_wrapper(self, fn)

    def __call__(self, *args, **kwargs):
        if _enabled_dir is None:
            if _notice:
                _announce()
            _run_after_export()
            return self.jitted(*args, **kwargs)
        dyn_args = tuple(a for i, a in enumerate(args) if i not in self.static_positions)
        dyn_kwargs = {k: v for k, v in kwargs.items() if k not in self.static_names}
        leaves, tree = jax.tree_util.tree_flatten((dyn_args, dyn_kwargs))
        signature = self._signature(args, kwargs, leaves, tree)
        if signature in self.ready:  # (compiled by its first call)
            _run_after_export()
            kernel = self.kernels[signature]
            if kernel is self.jitted:
                return self.jitted(*args, **kwargs)
            return kernel(*dyn_args, **dyn_kwargs)
        with scope():  # a call that may trace or compile: in jaxfit's cache folder
            if signature is None:
                _run_after_export()
                return self.jitted(*args, **kwargs)
            with self.first_calls.setdefault(signature, threading.Lock()):
                if signature in self.ready:  # another thread's first call came first
                    return self(*args, **kwargs)
                with paused():  # (tracing's objects: no full collections meanwhile)
                    out = self._first_call(signature, self.kernels.get(signature), leaves,
                                           tree, args, kwargs, dyn_args, dyn_kwargs)
                self.ready.add(signature)
                return out

    def _signature(self, args, kwargs, leaves, tree):
        """The key of the call's program, or None where the plain jit answers."""
        shapes = tuple(_leaf_signature(leaf) for leaf in leaves)
        if None in shapes:
            return None
        static = tuple(_static_value(a) for i, a in enumerate(args)
                       if i in self.static_positions)
        static += tuple((k, _static_value(v)) for k, v in sorted(kwargs.items())
                        if k in self.static_names)
        return (static, str(tree), shapes, _settings())

    def _first_call(self, signature, kernel, leaves, tree, args, kwargs, dyn_args,
                    dyn_kwargs):
        """A call whose program may have to be read, exported or compiled."""
        if _notice:
            _announce()
        if kernel is None:
            kernel = self.kernels[signature] = self._kernel(signature, args, kwargs, leaves,
                                                            tree)
        _run_after_export()  # (traced and lowered, or read: compiling comes next)
        if kernel is self.jitted:
            return self.jitted(*args, **kwargs)
        lapack = contextlib.nullcontext() if signature not in self.lapack_free else \
            without_lapack()
        if signature not in self.unproven:
            with lapack:
                return kernel(*dyn_args, **dyn_kwargs)
        try:  # the first call of a program read from disk
            with lapack:
                out = kernel(*dyn_args, **dyn_kwargs)
        except Exception:  # it loaded but does not compile or run (seen once: "Failed to
            # deserialize StableHLO"): never trusted again; the plain jit answers
            with contextlib.suppress(OSError):
                self.unproven[signature].unlink()
            del self.unproven[signature]
            self.kernels[signature] = self.jitted
            return self.jitted(*args, **kwargs)
        del self.unproven[signature]
        return out

    def _kernel(self, signature, args, kwargs, leaves, tree):
        """The jitted call of the exported program for one signature: read from the
        folder (only a file of this user's that no one else can write, signed with the
        folder's key under this name, holding a program of this call's arguments), or
        exported (traced and lowered) now and written there;
        ``self.jitted`` where JAX cannot export it. ``leaves`` and ``tree``: the call's
        dynamic arguments, flattened."""
        from jax import export

        secret = _secret(_enabled_dir)
        if secret is None:  # no key to sign with: nothing read, nothing written
            return self.jitted
        key = repr((self.name, sorted(self.options.items()), _environment(), signature))
        # One sub-folder per jaxfit source: those of older versions can be deleted whole.
        name = f"{_source_digest()[:16]}/{hashlib.sha256(key.encode()).hexdigest()}"
        path = Path(_enabled_dir) / EXPORTED / f"{name}.jaxexport"
        try:
            if (reason := unsafe(path)) is not None:
                raise OSError(reason)
            blob = unseal(path.read_bytes(), name, secret)
            exported = export.deserialize(bytearray(blob))
            if not _takes(exported, leaves, tree):
                raise ValueError("a program of other arguments")
            self.unproven[signature] = path
        except Exception:  # missing, partial, unreadable, not ours, not signed by this
            # folder's key for this name, or not this call's: export it (again) and
            # replace the file
            try:
                exported = export.export(self.jitted)(*args, **kwargs)
                blob = exported.serialize()
            except Exception:  # (a real error in the call is raised by the jitted one)
                return self.jitted
            _write(path, seal(blob, name, secret))
        if not calls_lapack(exported):
            self.lapack_free.add(signature)
        options = {"compiler_options": self.options} if self.options else {}
        return jax.jit(exported.call, **options)


def calls_lapack(exported) -> bool:
    """Whether an exported program may call LAPACK (its module names a ``lapack_`` custom
    call target; True where the module cannot be read)."""
    try:
        return b"lapack" in exported.mlir_module_serialized
    except Exception:
        return True


_exported = threading.local()  # .callback: ``after_export``'s, until it has run


@contextlib.contextmanager
def after_export(callback):
    """Run ``callback()`` (if not None) once in this thread: as soon as the block's first
    ``Stored`` call has its program (traced and lowered, or read), before compiling or
    running it; at the block's end at the latest. Why: work it starts in a thread (the
    refinement's tracing, ``engine.loop``) then does not take the GIL from this
    program's tracing and lowering, which a cold first fit waits on."""
    _exported.callback = callback
    try:
        yield
    finally:
        _run_after_export()


def _run_after_export():
    callback = getattr(_exported, "callback", None)
    if callback is not None:
        _exported.callback = None
        callback()


_lapack_skip = threading.local()  # .depth: how many ``without_lapack`` blocks this thread is in


@contextlib.contextmanager
def without_lapack():
    """Within it (in this thread), lowering the call of an exported program does not start
    LAPACK: ``jax.export`` starts it for every program it calls on the CPU, and its start
    imports scipy.linalg (0.12-0.15 s CPU, a warm process's largest single cost besides
    importing JAX; docs/engine.md, "Compile cost, this round"). Only for programs that
    ``calls_lapack`` clears; a JAX without the hook (``_hook_lapack_start``) starts it
    as before. A program that does call LAPACK starts it when it is lowered, as usual."""
    if not _hook_lapack_start():
        yield
        return
    _lapack_skip.depth = getattr(_lapack_skip, "depth", 0) + 1
    try:
        yield
    finally:
        _lapack_skip.depth -= 1


@functools.cache
def _hook_lapack_start() -> bool:
    """Wrap ``jax._src.export._export._ensure_backends_initialized`` (jax 0.10.2: it starts
    LAPACK for every exported program lowered for the CPU) so that it does nothing inside
    ``without_lapack``; False (nothing hooked) where JAX has no such function."""
    try:
        from jax._src.export import _export

        start = _export._ensure_backends_initialized
        inspect.signature(start).bind(("cpu",))
    except Exception:
        return False

    @functools.wraps(start)
    def _ensure_backends_initialized(platforms, *args, **kwargs):
        if getattr(_lapack_skip, "depth", 0):
            return None
        return start(platforms, *args, **kwargs)

    _export._ensure_backends_initialized = _ensure_backends_initialized
    return True


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


# --- The key that signs the stored programs -------------------------------------------

#: File in jaxfit's cache folder holding the secret key the stored programs are signed
#: with: only the user can read it (mode 0600).
KEY_FILE = "exported.key"
KEY_BYTES = 32
#: What a stored program's file starts with; then its HMAC-SHA256 tag, then the program.
MAGIC = b"jaxfit exported program, HMAC-SHA256\n"
_TAG_BYTES = hashlib.sha256().digest_size


def seal(blob: bytes, name: str, secret: bytes) -> bytes:
    """The file content for the program ``blob`` stored under ``name``: MAGIC, the
    HMAC-SHA256 tag of (name, blob) under ``secret``, the blob."""
    return MAGIC + _tag(blob, name, secret) + bytes(blob)


def unseal(data: bytes, name: str, secret: bytes) -> bytes:
    """The program of a file read from under ``name``; ValueError unless its tag is the one
    ``seal`` gives with this secret for this name (planted, copied from another name or
    folder, cut short, or of an older format)."""
    head = len(MAGIC) + _TAG_BYTES
    if len(data) < head or not data.startswith(MAGIC):
        raise ValueError("not a sealed program")
    blob = data[head:]
    if not hmac.compare_digest(data[len(MAGIC):head], _tag(blob, name, secret)):
        raise ValueError("its tag does not match: not written by this user's jaxfit "
                         "under this name")
    return blob


def _tag(blob: bytes, name: str, secret: bytes) -> bytes:
    # The name is length-prefixed, so no (name, blob) pair reads as another.
    encoded = name.encode()
    mac = hmac.new(secret, len(encoded).to_bytes(4, "big") + encoded, hashlib.sha256)
    mac.update(blob)
    return mac.digest()


@functools.cache
def _secret(folder: str) -> bytes | None:
    """The key of the cache folder (read once per process), or None if it can be neither
    read nor made (then no program is read or written)."""
    return _load_secret(Path(folder) / KEY_FILE)


def _load_secret(path: Path) -> bytes | None:
    """Read the key file, or make it if missing; one that is not a user-only regular file
    of KEY_BYTES bytes is deleted and made again. Concurrent processes agree: a new key is
    written to a private temporary file and linked into place, which fails if another
    process was first; the losers read the winner's key."""
    for _ in range(4):
        secret, bad = _read_secret(path)
        if secret is not None:
            return secret
        try:
            if bad:
                path.unlink(missing_ok=True)
            return _create_secret(path)
        except FileExistsError:  # another process was first: read its key
            continue
        except OSError:
            return None
    return None


def _read_secret(path: Path) -> tuple[bytes | None, bool]:
    """(the key, False), or (None, whether a file is there that is not a good key)."""
    for attempt in range(5):
        try:
            fd = os.open(path, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0)
                         | getattr(os, "O_BINARY", 0))
        except FileNotFoundError:
            return None, False
        except OSError:  # a symbolic link (O_NOFOLLOW), unreadable, ...
            return None, True
        try:
            st = os.fstat(fd)
            if not stat.S_ISREG(st.st_mode) or (hasattr(os, "getuid") and (
                    st.st_uid != os.getuid() or st.st_mode & 0o077)):
                return None, True  # not a file, or not the user's alone: others may know it
            secret = os.read(fd, KEY_BYTES + 1)
        except OSError:
            return None, True
        finally:
            os.close(fd)
        if len(secret) == KEY_BYTES:
            return secret, False
        # Short: maybe still being written (only where links are refused, see below).
        time.sleep(0.01 * (attempt + 1))
    return None, True


def _create_secret(path: Path) -> bytes:
    """Write a new key to ``path``; FileExistsError if there is a file already."""
    secret = secrets.token_bytes(KEY_BYTES)
    fd, temporary = tempfile.mkstemp(prefix=".key-", dir=path.parent)  # O_EXCL, mode 0600
    try:
        with os.fdopen(fd, "wb") as file:
            file.write(secret)
        try:
            os.link(temporary, path)  # whole or not at all; fails if there is one
        except FileExistsError:
            raise
        except OSError:  # a filesystem without hard links: create it in place
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL
                         | getattr(os, "O_BINARY", 0), 0o600)
            with os.fdopen(fd, "wb") as file:
                file.write(secret)
    finally:
        os.unlink(temporary)
    return secret


# --- JAX's own entries ----------------------------------------------------------------

def _guard_jax_entries() -> bool:
    """Make JAX delete an entry of jaxfit's folder that it fails to read, so that it is
    written again after compiling (JAX's ``put`` skips a key whose file exists: a cut or
    corrupt entry would otherwise warn and recompile in every process, for ever).

    Also keeps jaxfit's folder to jaxfit's compilations: JAX makes one cache object, for
    the folder of its first use, and asks it on every later compilation whatever the
    settings; while that is jaxfit's folder, a compilation outside ``scope`` (a user's own
    function) reads nothing from it and writes nothing to it.

    Wraps ``jax._src.compilation_cache.get_executable_and_time``, which reads, decompresses
    and deserializes an entry, and ``put_executable_and_time`` (jax 0.10.2). Where JAX's
    private names differ it does nothing and returns False; it never raises."""
    try:
        from jax._src import compilation_cache, lru_cache

        read = compilation_cache.get_executable_and_time
        write = compilation_cache.put_executable_and_time
        suffix = lru_cache._CACHE_SUFFIX
        inspect.signature(read).bind("key", None, None, None)
        inspect.signature(write).bind("key", "name", None, None, 0)
    except Exception:  # another JAX: leave it alone
        return False
    if getattr(read, "_jaxfit_guard", False):
        return True

    def not_ours_to_use() -> bool:
        return _outside_scope() and _is_ours(getattr(compilation_cache, "_cache", None))

    @functools.wraps(read)
    def get_executable_and_time(cache_key, *args, **kwargs):
        if not_ours_to_use():
            return None, None
        try:
            return read(cache_key, *args, **kwargs)
        except Exception:
            _drop_entry(getattr(compilation_cache, "_cache", None), cache_key, suffix)
            raise  # JAX warns (once) and compiles, then writes the entry again

    @functools.wraps(write)
    def put_executable_and_time(*args, **kwargs):
        if not not_ours_to_use():
            return write(*args, **kwargs)

    get_executable_and_time._jaxfit_guard = put_executable_and_time._jaxfit_guard = True
    compilation_cache.get_executable_and_time = get_executable_and_time
    compilation_cache.put_executable_and_time = put_executable_and_time
    return True


def _is_ours(cache) -> bool:
    """Whether JAX's cache object ``cache`` is the one of jaxfit's folder."""
    folder = getattr(cache, "_path", None)
    try:
        return (_enabled_dir is not None and folder is not None
                and os.path.realpath(str(folder)) == os.path.realpath(_enabled_dir))
    except Exception:  # (a path JAX holds in another form)
        return False


def _drop_entry(cache, cache_key, suffix) -> None:
    """Delete the entry file of ``cache_key`` if the cache in use is jaxfit's folder."""
    try:
        name = f"{cache_key}{suffix}"
        if (not _is_ours(cache) or not isinstance(cache_key, str)
                or os.sep in name or "/" in name or name.startswith(".")):
            return
        os.unlink(os.path.join(_enabled_dir, name))
    except Exception:  # gone already, or not ours to judge
        pass
