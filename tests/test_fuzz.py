"""Fuzzing (hypothesis) of what users hand the library: point files, and the inputs of
``jaxfit.fit``, ``fit_batch`` and ``jaxfit.detect``.

Point files (``jaxfit.io.points.load_points``, every extension it reads): arbitrary
bytes, and valid files with damaged bytes, truncations and numbers replaced (huge
counts, negative, NaN, out-of-range indices) either load into a finite (N, 3) float64
array or raise ``LoadError`` (a ValueError) with a message; never another exception, a
MemoryError behind the LoadError, a hang (SIGALRM), or an allocation far beyond the
file's size (tracemalloc's peak).

fit/detect: arbitrary arrays, thresholds, keys and options either give a result or
raise a ValueError/TypeError (``FitError`` is a ValueError) with a message, raised in
jaxfit's own code rather than deep in JAX or NumPy. Kernels compile per shape, batch
size, estimator, point bucket and local-optimisation row count, so: every shape's input
checks are fuzzed with the kernels stubbed out (``_stopped_at_the_kernels``: hundreds of
examples for the cost of none); the fits that do run use two shapes (``RUN_SHAPES``),
clouds of at most ``MAX_POINTS`` points (one bucket, one row count), the default batch
size and a fixed budget (``FIT``), and options that compile nothing new.

Every test is derandomized (the same examples on every run). What the fuzzing found is
kept as an ``@example`` beside the test it broke or as a plain test below the fuzz tests
(each failed before its fix). The .iv grammar itself is fuzzed
in test_iv.py.
"""

import contextlib
import importlib
import io
import os
import re
import signal
import traceback
import tracemalloc
import warnings
from decimal import Decimal
from fractions import Fraction

import jax
import numpy as np
import pytest
import trimesh
from hypothesis import HealthCheck, event, example, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

import jaxfit
from jaxfit.engine.cloud import MIN_BUCKET
from jaxfit.io.points import SUPPORTED_EXTENSIONS, LoadError, load_points
from jaxfit.shapes import REGISTRY

#: Examples of one reader test: each is a small file read in milliseconds.
READ = settings(max_examples=150, deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
#: Surface samples drawn from a mesh file (few, so sampling costs nothing).
SAMPLES = 64
#: Seconds one file may take to read before it counts as a hang.
READ_SECONDS = 10
#: Bytes a read may allocate beyond a fixed allowance per byte of file (tracemalloc sees
#: NumPy's buffers): a header promising 10**9 points must not be believed.
ALLOWANCE, PER_BYTE = 32 * 2**20, 64


# ----- valid files to damage ------------------------------------------------------------

def _mesh():
    """A small closed mesh: a box with one corner pulled out (8 vertices, 12 faces)."""
    box = trimesh.creation.box(extents=(1.0, 2.0, 3.0))
    vertices = np.array(box.vertices)
    vertices[0] *= 1.5
    return trimesh.Trimesh(vertices, box.faces, process=False)


def _npy(array) -> bytes:
    out = io.BytesIO()
    np.save(out, array, allow_pickle=False)
    return out.getvalue()


def _seeds() -> dict[str, bytes]:
    """Extension (with a variant tag after '#') -> the bytes of a valid file of it."""
    mesh = _mesh()
    points = np.asarray(mesh.vertices)
    rows = "\n".join(" ".join(f"{v:.6g}" for v in p) for p in points)
    gltf = mesh.export(file_type="gltf", embed_buffers=True)
    return {
        ".ply#ascii": mesh.export(file_type="ply", encoding="ascii"),
        ".ply#binary": mesh.export(file_type="ply", encoding="binary"),
        ".ply#cloud": trimesh.PointCloud(points).export(file_type="ply", encoding="ascii"),
        ".obj": mesh.export(file_type="obj").encode(),
        ".stl#binary": mesh.export(file_type="stl"),
        ".stl#ascii": mesh.export(file_type="stl_ascii").encode(),
        ".off": mesh.export(file_type="off").encode(),
        ".glb": mesh.export(file_type="glb"),
        ".gltf": next(iter(gltf.values())),
        ".iv": b"#Inventor V2.1 ascii\nSeparator { Coordinate3 { point [ 0 0 0, 1 0 0, "
               b"0 1 0, 0 0 1 ] } IndexedFaceSet { coordIndex [ 0, 1, 2, -1, 0, 1, 3, -1 ] }"
               b" Cube { width 2 } }\n",
        ".xyz": (rows + "\n").encode(),
        ".txt": ("# x y z\n" + rows + "\n").encode(),
        ".csv": ("x,y,z,intensity\n" + rows.replace(" ", ",").replace("\n", ",1\n")
                 + ",1\n").encode(),
        ".pts": (f"{len(points)}\n" + rows.replace("\n", " 7\n") + " 7\n").encode(),
        ".crd": (rows + "\n").encode(),
        ".npy": _npy(points),
        ".npy#int": _npy(np.arange(12, dtype=np.int16).reshape(3, 4)),
    }


SEEDS = _seeds()
#: Numbers that break careless readers: counts far beyond the data, negative or NaN
#: values, out-of-range indices, overflow.
NASTY = ["0", "-1", "-8", "8", "9", "12", "99", "255", "65536", "2147483648", "4294967295",
         "1000000000000", "9223372036854775808", "1" + "0" * 400, "nan", "-nan", "inf",
         "-inf", "1e300", "-1e300", "1e-300", "1e999", "0x10", "3.5", "-0", "", "1,2"]


def test_the_seed_files_load(folder):
    """Each undamaged seed reads as points (so the mutations start from a valid file)."""
    for name, data in SEEDS.items():
        points = _read(folder, name, data)
        assert points is not None and len(points) >= 3, name


# ----- reading under guard ---------------------------------------------------------------

@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    return tmp_path_factory.mktemp("fuzz")


class _Hang(BaseException):
    """A BaseException, so that the readers' ``except Exception`` cannot hide it."""


@contextlib.contextmanager
def _time_limit(seconds):
    """Raise _Hang in the main thread after ``seconds`` (SIGALRM; POSIX only)."""
    if not hasattr(signal, "setitimer"):
        yield
        return

    def alarm(signum, frame):
        raise _Hang(f"still reading after {seconds} s")

    previous = signal.signal(signal.SIGALRM, alarm)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def _causes(err):
    while err is not None:
        yield err
        err = err.__cause__ or err.__context__


def _read(folder, name, data: bytes):
    """load_points on ``data`` saved as a file of extension ``name`` (up to '#'): the
    points, checked, or None after a LoadError with a message."""
    path = folder / ("fuzz" + name.split("#")[0])
    path.write_bytes(data)
    tracemalloc.start()
    try:
        with _time_limit(READ_SECONDS), warnings.catch_warnings():
            warnings.simplefilter("ignore")  # overflow in trimesh's area, numpy's loadtxt
            points = load_points(path, num_points=SAMPLES, seed=0)
    except LoadError as err:
        assert str(err)
        memory = [e for e in _causes(err) if isinstance(e, MemoryError)]
        assert not memory, f"{err} (an allocation the file's size cannot justify)"
        return None
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        assert peak < ALLOWANCE + PER_BYTE * len(data), f"{peak} bytes for {len(data)}"
    assert isinstance(points, np.ndarray) and points.dtype == np.float64
    assert points.ndim == 2 and points.shape[1] == 3 and len(points) >= 1
    assert np.isfinite(points).all()
    assert points.flags.c_contiguous
    return points


# ----- point files -----------------------------------------------------------------------

EXTENSIONS = st.sampled_from(sorted(SEEDS))


@READ
@given(name=st.sampled_from(SUPPORTED_EXTENSIONS), data=st.binary(max_size=600))
@example(name=".iv", data=b"\x00")  # jaxfit.io.iv.IVError, not a LoadError, before
def test_arbitrary_bytes(folder, name, data):
    _read(folder, name, data)


@READ
@given(name=EXTENSIONS, keep=st.floats(0, 1), tail=st.binary(max_size=64))
def test_a_valid_file_cut_short_or_with_junk_after(folder, name, keep, tail):
    seed = SEEDS[name]
    _read(folder, name, seed[:int(keep * len(seed))] + tail)


_EDITS = st.lists(st.tuples(st.sampled_from(["replace", "insert", "delete", "flip"]),
                            st.floats(0, 1, exclude_max=True), st.binary(min_size=1, max_size=8)),
                  min_size=1, max_size=6)


@READ
@given(name=EXTENSIONS, edits=_EDITS)
@example(name=".glb", edits=[("insert", 0.75, b"\0" * 8)])  # read(1 GB) before
@example(name=".npy", edits=[("replace", 0.0234375, b"\1")])  # version 1.1: read(662 MB)
def test_damaged_bytes_of_a_valid_file(folder, name, edits):
    data = bytearray(SEEDS[name])
    for op, where, new in edits:
        at = int(where * len(data))
        if op == "replace":
            data[at:at + len(new)] = new
        elif op == "insert":
            data[at:at] = new
        elif op == "delete":
            del data[at:at + len(new)]
        else:  # one bit flipped per byte of ``new``
            for i, byte in enumerate(new):
                if at + i < len(data):
                    data[at + i] ^= 1 << (byte % 8)
    _read(folder, name, bytes(data))


_TEXT = sorted(n for n, d in SEEDS.items() if n.split("#")[0] not in (".npy", ".glb")
               and (n.endswith("#ascii") or "#" not in n or n.endswith("#cloud")))
_NUMBER = rb"-?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"


@READ
@given(name=st.sampled_from(_TEXT),
       swaps=st.lists(st.tuples(st.integers(0, 10**6), st.sampled_from(NASTY)),
                      min_size=1, max_size=4))
def test_numbers_of_a_text_file_replaced(folder, name, swaps):
    """Counts in headers (PLY ``element vertex 8``, OFF ``8 12 0``, a .pts count, glTF
    accessors' ``count``), coordinates and face indices replaced by nasty numbers."""
    data = SEEDS[name]
    spans = [m.span() for m in re.finditer(_NUMBER, data)]
    for index, value in swaps:
        start, stop = spans[index % len(spans)]
        data = data[:start] + value.encode().ljust(stop - start) + data[stop:]
        spans = [m.span() for m in re.finditer(_NUMBER, data)] or [(0, 0)]
    _read(folder, name, data)


@READ
@given(shape=st.lists(st.integers(0, 2**40), max_size=3).map(tuple),
       descr=st.sampled_from(["<f8", ">f4", "<i2", "|u1", "<f2", "|b1", "<c16", "|O",
                              "<U3", "<M8[s]", "<f16", "[('x', '<f8')]"]),
       fortran=st.booleans(), size=st.integers(0, 200), header=st.booleans())
@example(shape=(400_000_000, 3), descr="<f8", fortran=False, size=96, header=False)
def test_npy_header_against_its_data(folder, shape, descr, fortran, size, header):
    """A .npy header whose shape or dtype does not match the bytes that follow (a shape of
    4e8 x 3 once made NumPy allocate 9.6 GB before finding the file short)."""
    text = f"{{'descr': {descr if descr.startswith('[') else repr(descr)}, "
    text += f"'fortran_order': {fortran}, 'shape': {shape}, }}"
    text = text.ljust(118) + "\n"
    if header:
        text = text.replace("'shape'", "'shape': (1, 3), 'shape'")
    data = b"\x93NUMPY\x01\x00" + len(text).to_bytes(2, "little") + text.encode("latin1")
    _read(folder, ".npy", data + bytes(range(256))[:size])


# ----- what the fuzzing found in the readers (each failed before its fix) -------------------

def _ply(faces="3 0 1 2\n3 0 1 3\n", vertices=4, face_count=2):
    return (f"ply\nformat ascii 1.0\nelement vertex {vertices}\nproperty float x\n"
            "property float y\nproperty float z\n"
            f"element face {face_count}\nproperty list uchar int vertex_indices\nend_header\n"
            "0 0 0\n1 0 0\n0 1 0\n0 0 1\n" + faces).encode()


@pytest.mark.parametrize("faces", ["3 0 1 4\n3 0 1 3\n", "3 0 1 -1\n3 0 1 3\n"])
def test_a_face_index_outside_the_vertices_is_named(folder, faces):
    """(an IndexError from trimesh's area before; -1 silently took the last vertex)"""
    with pytest.raises(LoadError, match=r"1 of 2 faces .* outside 0\.\.\.3 \(first: face 0"):
        load_points(_written(folder, ".ply", _ply(faces)))


@pytest.mark.parametrize("name, data, message", [
    (".ply", _ply(vertices=10**12), r"promises \[1000000000000, 2\] elements"),
    (".ply", _ply(face_count=5), r"promises \[4, 5\] elements \(9 rows\).* 6 rows"),
    (".ply", _ply(vertices=-4), r"promises \[-4, 2\]"),
    (".off", b"OFF\n-3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n", r"promises \[-3, 1\]"),
    (".off", b"OFF\n3 9 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n", r"\[3, 9\].* 4 rows"),
])
def test_counts_beyond_the_data_are_named(folder, name, data, message):
    """Counts promising more rows than the file has: trimesh read face rows as vertices
    (a vertex count of 10**12 gave 6 points) or dropped the missing faces."""
    with pytest.raises(LoadError, match=message):
        load_points(_written(folder, name, data))


def test_npy_header_length_is_checked_before_reading(folder):
    """A version 2.0 header length of 4 GB: NumPy reads that much before checking it."""
    data = b"\x93NUMPY\x02\x00" + (2**32 - 1).to_bytes(4, "little") + b"{}" * 40
    assert _read(folder, ".npy", data) is None


def test_glb_chunk_longer_than_the_file(folder):
    data = bytearray(SEEDS[".glb"])
    json_length = int.from_bytes(data[12:16], "little")
    data[20 + json_length:24 + json_length] = (2**32 - 16).to_bytes(4, "little")
    with pytest.raises(LoadError, match="GLB chunk at byte .* claims 4294967280 bytes"):
        load_points(_written(folder, ".glb", bytes(data)))


def _obj(mesh, scale=1.0) -> bytes:
    text = "".join("v {!r} {!r} {!r}\n".format(*(float(c) * scale for c in v))
                   for v in mesh.vertices)
    return (text + "".join("f {} {} {}\n".format(*(f + 1)) for f in mesh.faces)).encode()


@pytest.mark.parametrize("scale", [1e-300, 1e-170, 1e160, 1e300, 5e307])
def test_a_mesh_is_sampled_at_any_scale(folder, scale):
    """trimesh's areas square the edges: under ~1e-160 they were 0 ("zero surface area"),
    over ~1e154 inf (IndexError, or non-finite samples). Now the samples are those of the
    unit mesh, scaled."""
    mesh = _mesh()
    points = _read(folder, ".obj", _obj(mesh, scale))
    assert points is not None
    unit = load_points(_written(folder, ".obj", _obj(mesh)), num_points=SAMPLES)
    np.testing.assert_allclose(points / scale, unit, rtol=1e-9, atol=1e-12)


def _written(folder, name, data: bytes):
    path = folder / ("case" + name)
    path.write_bytes(data)
    return path


# ----- fit and detect inputs -------------------------------------------------------------

#: Every fit's budget: one kernel call of the default batch size (which the rest of the
#: suite compiles too). Fixed for the module, like the shapes below.
FIT = {"max_hypotheses": 256}
#: Shapes whose fits run their kernels here (each compiles its own); every shape's input
#: checks are fuzzed with the kernels stubbed out (``_stopped_at_the_kernels``).
RUN_SHAPES = ("plane", "sphere")
#: Most points of a cloud that may reach the kernels: one point bucket (``MIN_BUCKET``)
#: and one row count of the local optimisation (``lo_rows``).
MAX_POINTS = 256
CHECK = settings(max_examples=300, deadline=None, derandomize=True, database=None,
                 suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                        HealthCheck.filter_too_much])
RUN = settings(CHECK, max_examples=40)

_BASE = np.random.default_rng(5).normal(size=(MAX_POINTS, 3))
_SPECIAL = [np.nan, np.inf, -np.inf, 1e300, -1e300, 2e150, 1e150, 1e-300, 5e-324, 0.0, 1.0]
_SCALES = [1e-300, 1e-160, 1e-6, 1.0, 1.0, 1.0, 1e6, 1e100, 1e151, 1e300]


def test_the_fuzzed_clouds_share_one_kernel_shape():
    from jaxfit.engine.cloud import bucket_size
    from jaxfit.engine.refine import lo_rows

    assert bucket_size(MAX_POINTS) == bucket_size(1) == MIN_BUCKET
    assert lo_rows(MAX_POINTS) == lo_rows(1)


def mostly(valid, anything):
    """Draws from ``valid`` three times in four, else from ``anything``: an example with
    five arguments then reaches the kernels (all valid) about once in four."""
    return st.sampled_from([True, True, True, False]).flatmap(
        lambda pick: valid if pick else anything)


@st.composite
def clouds(draw, sizes=(0, 1, 2, 3, 4, 5, 8, 64, MAX_POINTS), scales=_SCALES, plant=2):
    """(N, 3) float64 clouds of at most MAX_POINTS points: random, flat, collinear,
    coincident or on a coarse grid, at scales from 1e-300 to 1e300, offset, with up to
    ``plant`` special values (NaN, inf, 1e300, subnormal, ...) planted."""
    n = draw(st.sampled_from(sizes))
    kind = draw(st.sampled_from(["random", "random", "flat", "line", "same", "grid"]))
    scale = draw(st.sampled_from(scales))
    offset = draw(st.sampled_from([0.0, 0.0, 0.0, 1.0, 1e8, -1e149]))
    base = _BASE[:n].copy()
    if kind == "flat":
        base[:, 2] = 0.0
    elif kind == "line":
        base = np.outer(base[:, 0], [1.0, 2.0, 3.0])
    elif kind == "same":
        base[:] = base[:1]
    elif kind == "grid":
        base = np.round(base)  # many coincident points
    with np.errstate(over="ignore", under="ignore"):
        cloud = base * scale + offset
    planted = st.lists(st.tuples(st.integers(0, MAX_POINTS), st.integers(0, 2),
                                 st.sampled_from(_SPECIAL)), min_size=1, max_size=plant)
    for row, col, value in draw(mostly(st.just([]), planted) if plant else st.just([])):
        if n:
            cloud[row % n, col] = value
    return cloud


def _quiet(function):
    def quiet(*args):
        with np.errstate(all="ignore"):
            return function(*args)
    return quiet


_DTYPES = st.sampled_from([np.float64, np.float32, np.float16, np.int64, np.int8, np.uint8,
                           np.bool_, np.complex128, np.dtype("U3"), np.dtype("M8[s]"),
                           np.dtype("m8[s]"), np.dtype([("x", "<f8")])])
_OBJECTS = st.recursive(
    st.one_of(st.none(), st.booleans(), st.integers(), st.floats(), st.text(max_size=3),
              st.complex_numbers(), st.just(10**400)),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=2), inner,
                                                                max_size=2),
    max_leaves=12)
#: Anything as a cloud: mostly (N, 3) clouds (as arrays, lists, float32, in JAX), then
#: the wrong shape, arrays of any dtype and shape, nested Python objects.
POINTS = st.one_of(
    clouds(),
    clouds(),
    clouds(plant=0).map(lambda c: c.tolist()),
    clouds(plant=0).map(_quiet(lambda c: c.astype(np.float32))),
    clouds(plant=0).map(_quiet(lambda c: jax.numpy.asarray(c, jax.numpy.float32))),
    clouds().map(lambda c: c[:, :2]),
    clouds().map(lambda c: c[None]),
    hnp.arrays(_DTYPES, hnp.array_shapes(min_dims=0, max_dims=3, min_side=0, max_side=4)),
    _OBJECTS,
)
#: Thresholds: valid, zero, negative, NaN, huge, tiny, subnormal, of the wrong type.
THRESHOLDS = st.one_of(
    st.none(), st.floats(), st.integers(-3, 3), st.just(10**400),
    st.sampled_from([1e-320, 1e-300, 1e150, 2e150, 1e300, "0.1", b"1", [0.1], (0.1, 0.2), 1j,
                     True, np.array(0.1), np.array([0.1]), np.float32(0.05), np.int8(1),
                     np.array([[0.1]]), jax.numpy.float32(0.1), Fraction(1, 10),
                     Fraction(10**400), Decimal("0.1")]))
#: Keys: int seeds of any size, JAX keys (typed, raw, batched), and not keys at all.
KEYS = st.one_of(
    st.integers(), st.floats(), st.text(max_size=3), st.none(), st.booleans(),
    st.sampled_from([jax.random.key(1), jax.random.split(jax.random.key(1), 2),
                     jax.random.PRNGKey(2), np.uint32([1, 2]), np.int64(7),
                     np.uint64(2**64 - 1), jax.numpy.uint32([1, 2, 3]),
                     jax.numpy.zeros((), jax.numpy.uint32)]))
_COUNTS = st.one_of(st.integers(-2, 600), st.sampled_from([10**400, 2.5, 256.0, "256", True,
                                                           None, np.int64(256), np.float64(3)]))
#: Option keywords: valid values that compile nothing new (the batch size is only ever
#: the default or invalid, an estimator or a normal gate only invalid: each valid choice
#: compiles its own kernels) and invalid ones.
FIT_OPTIONS = {
    "confidence": st.one_of(st.floats(), st.sampled_from([0, 1, 0.5, "0.9", Fraction(1, 2),
                                                          True, None])),
    "max_hypotheses": _COUNTS,
    "batch_size": st.sampled_from([256, np.int64(256), 0, -256, 256.0, "256", True, None, 2.5]),
    "max_stall": _COUNTS,
    "min_hypotheses": _COUNTS,
    "refine": st.sampled_from([True, False, np.bool_(False), "no", 0, None]),
    "estimator": st.sampled_from([None, "nope", 3, ["thesis"], ""]),
    "radius_range": st.sampled_from([None, (0.1, 10.0), (0, np.inf), (2, 1), (np.nan, 1),
                                     (1,), "ab", 5, (1j, 2), (None, 2), (-1, 2), [0.5, 1e300]]),
    "axis_prior": st.sampled_from([None, ((0, 0, 1), 30), ((0, 0, 1e-320), 10), ((1, 2), 10),
                                   ((0, 0, 1), 0), ((0, 0, 1), "x"), ((0, 0, 1), np.nan),
                                   (("a", 0, 1), 10), ((0, 0, 1), 10, 3), 7]),
    "normal_angle": st.sampled_from([None, 0, -10, 91, np.nan, "30", True, 1e300]),
    "sampler": st.sampled_from(["uniform", None, 3]),
    "scorer": st.sampled_from(["msac", None]),
    "stopping": st.sampled_from([[], None]),
    "refiner": st.sampled_from([object(), None]),
    "options": st.sampled_from([None, 3, "fast", {"batch_size": 256}, jaxfit.FitOptions(),
                                jaxfit.FitOptions(batch_size=0)]),
    "colour": st.just("red"),
}
#: The options of fits that run: valid values (compiling nothing new) more often.
RUN_OPTIONS = {
    "confidence": st.sampled_from([0.5, 0.999999, Fraction(9, 10), 1.0]),
    "max_hypotheses": st.sampled_from([1, 256, 10**400, 0]),
    "max_stall": st.sampled_from([1, 256, 10**400]),
    "min_hypotheses": st.sampled_from([None, 0, 256, 10**400, -1]),
    "refine": st.booleans(),
    "radius_range": st.sampled_from([None, (0.1, 10.0), (0, np.inf), (50.0, 60.0)]),
    "axis_prior": st.sampled_from([None, ((0, 0, 1), 30), ((1e-300, 0, 0), 90)]),
    "options": st.sampled_from([None, jaxfit.FitOptions(refine=False)]),
}


def options(strategies, max_size=2):
    """Dictionaries of at most ``max_size`` of the keywords ``strategies`` draws for."""
    names = st.lists(st.sampled_from(sorted(strategies)), max_size=max_size, unique=True)
    return names.flatmap(lambda chosen: st.fixed_dictionaries(
        {name: strategies[name] for name in chosen}))


NORMALS = st.one_of(st.none(), st.none(), POINTS, clouds().map(_quiet(lambda c: c * 1e200)),
                    clouds().map(_quiet(lambda c: c * 1e-200)))
ANY_SHAPE = st.one_of(
    st.sampled_from(sorted(REGISTRY)),
    st.sampled_from([" Plane ", "CYLINDER", "torus", "", None, 3, ["plane"], jaxfit.Box,
                     jaxfit.Model, int, b"plane"]))


#: (``jaxfit.engine.fit`` and ``jaxfit.detect`` are the functions, shadowing the modules)
_FIT_MODULE = importlib.import_module("jaxfit.engine.fit")
_DETECT_MODULE = importlib.import_module("jaxfit.detect")


class _Reached(BaseException):
    """Raised where the kernels would start: the input was accepted. (A BaseException, so
    that no ``except Exception`` on the way can take it for a failure.)"""


@contextlib.contextmanager
def _stopped_at_the_kernels():
    """fit, fit_batch and detect up to the first kernel: normals estimation and the
    search raise _Reached (detect's fits do, through fit)."""
    def reached(*args, **kwargs):
        raise _Reached

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(_FIT_MODULE, "estimate_normals", reached)
        patch.setattr(_FIT_MODULE, "searches", reached)
        patch.setattr(_DETECT_MODULE, "estimate_normals", reached)
        try:
            yield
        except _Reached:
            event("reached the kernels")  # (--hypothesis-show-statistics)


def _outcome(call):
    """call()'s result, or None after a ValueError or TypeError (FitError and LoadError
    are ValueErrors) that has a message and was raised by jaxfit itself: not by JAX,
    NumPy or SciPy on input jaxfit let through."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            result = call()
        except (ValueError, TypeError) as err:
            event(f"{type(err).__name__}: {str(err)[:24]}")
            assert str(err).strip(), f"{type(err).__name__} without a message"
            where = traceback.extract_tb(err.__traceback__)[-1]
            assert f"{os.sep}jaxfit{os.sep}" in where.filename, (
                f"{type(err).__name__}: {err} raised at {where.filename}:{where.lineno}")
            return None
    event("a result")
    return result


def _finite_model(model):
    for name, value in model.to_dict().items():
        if name != "type" and value is not None:
            assert np.all(np.isfinite(value)), (name, value)


def _check_fit(result, points):
    assert isinstance(result, jaxfit.FitResult)
    n = len(points)
    assert result.inliers.shape == (n,) and result.inliers.dtype == bool
    assert 0 <= result.num_inliers == result.inliers.sum() <= n
    assert np.isfinite(result.cost) and result.cost >= 0
    assert np.isfinite(result.threshold) and result.threshold > 0
    _finite_model(result.model)


def _check_scene(scene, points):
    assert isinstance(scene, jaxfit.Scene)
    taken = np.concatenate([d.indices for d in scene.shapes] + [scene.unassigned])
    np.testing.assert_array_equal(np.sort(taken), np.arange(len(points)))  # a partition
    assert scene.labels().shape == (len(points),)
    for detection in scene.shapes:
        assert np.isfinite(detection.cost)
        _finite_model(detection.model)


@CHECK
@given(points=mostly(clouds(plant=1), POINTS), shape=mostly(st.sampled_from(sorted(REGISTRY)),
                                                           ANY_SHAPE),
       threshold=mostly(st.none() | st.floats(1e-3, 1), THRESHOLDS),
       key=mostly(st.integers(), KEYS),
       options=mostly(st.just({}), options({**FIT_OPTIONS, "thresholds": st.just(0.1)})),
       normals=mostly(st.none(), NORMALS), batch=st.booleans())
def test_fit_input_checks(points, shape, threshold, key, options, normals, batch):
    """Every shape, any input: a ValueError or TypeError from jaxfit, or the input is
    accepted and the kernels are reached (stubbed out here)."""
    with _stopped_at_the_kernels():
        if batch:  # (with its own thresholds, one per cloud)
            options = {name: v for name, v in options.items() if name != "thresholds"}
            _outcome(lambda: jaxfit.fit_batch(
                [points], shape, thresholds=threshold, key=key,
                normals=None if normals is None else [normals], **options))
        else:
            _outcome(lambda: jaxfit.fit(points, shape, threshold=threshold, key=key,
                                        normals=normals, **options))


#: Thresholds of fits that run: a fraction of the cloud's size, or (in a 1-tuple) one
#: beyond any cloud's. (Not far below its size: test_a_tiny_threshold_on_an_exact_plane.)
RUN_THRESHOLDS = mostly(st.none() | st.sampled_from([1e-3, 0.02, 0.3, 10.0]),
                        st.sampled_from([(1e150,), (2e150,), (np.float32(1e30),)]))


def _threshold(drawn, points):
    if drawn is None or isinstance(drawn, tuple):
        return drawn and drawn[0]
    finite = points[np.isfinite(points).all(axis=1)]
    side = float(np.ptp(finite, axis=0).max()) if len(finite) else 0.0
    return drawn * (side if 0 < side < np.inf else 1.0)


@RUN
@given(points=clouds(sizes=(3, 4, 5, 8, 64, MAX_POINTS), scales=_SCALES[1:-1], plant=1),
       shape=st.sampled_from(RUN_SHAPES), threshold=RUN_THRESHOLDS,
       key=mostly(st.integers(), st.sampled_from([jax.random.key(1), jax.random.PRNGKey(2),
                                                  np.uint64(2**64 - 1), -1, 10**30])),
       options=options(RUN_OPTIONS, max_size=1))
def test_fit_gives_a_result_or_a_clear_error(points, shape, threshold, key, options):
    """Clouds that get as far as the kernels: a finite model, or a clear error."""
    threshold = _threshold(threshold, points)
    result = _outcome(lambda: jaxfit.fit(points, shape, threshold=threshold, key=key,
                                         **{**FIT, **options}))
    if result is not None:
        _check_fit(result, points)


DETECT_OPTIONS = {
    "min_inliers": _COUNTS,
    "threshold": THRESHOLDS,
    "max_angle": st.one_of(st.floats(), st.sampled_from([0, 90, 91, "30", None])),
    "connect": st.one_of(st.floats(), st.sampled_from([0, 10**400, "4", None])),
    "tolerance": st.one_of(st.floats(), st.sampled_from([0, -1, 10**400, "0.1", None, True,
                                                         np.float64(0.1), np.int64(1)])),
    "fit_points": _COUNTS,
    "key": KEYS,
    "settle": st.booleans(),
    "batch_size": st.sampled_from([256, 0, "256"]),
    "estimator": st.sampled_from(["nope", 3]),
    "skip_failures": st.just(True),  # fit_batch's
    "thresholds": st.just(0.1),  # fit_batch's
    "options": st.sampled_from([jaxfit.FitOptions(), jaxfit.FitOptions(batch_size=0), 3]),
    "normals_angle": st.just(30),
}
DETECT_SHAPES = st.one_of(
    st.lists(st.sampled_from(sorted(REGISTRY)), min_size=1, max_size=3).map(tuple),
    st.sampled_from(["plane", jaxfit.Sphere, None, 3, "", (), ("plane", "plane"), ("torus",),
                     [jaxfit.Plane, "sphere"]]))


@CHECK
@given(points=mostly(clouds(plant=1), POINTS), shapes=mostly(st.just(RUN_SHAPES), DETECT_SHAPES),
       options=mostly(st.just({}), options(DETECT_OPTIONS)), normals=mostly(st.none(), NORMALS))
def test_detect_input_checks(points, shapes, options, normals):
    with _stopped_at_the_kernels():
        _outcome(lambda: jaxfit.detect(points, shapes, normals=normals, **options))


DETECT_RUN_OPTIONS = {
    "min_inliers": st.sampled_from([None, 4, 20, 10**400]),
    "threshold": RUN_THRESHOLDS,
    "tolerance": st.sampled_from([0.0, 0.05, np.inf]),
    "fit_points": st.sampled_from([4, 1024, 10**400]),
    "connect": st.sampled_from([1e-300, 4.0, 1e150]),
    "settle": st.booleans(),
    "key": st.integers(),
}


@settings(RUN, max_examples=12)
@given(points=clouds(sizes=(3, 8, 64, 64, MAX_POINTS, MAX_POINTS), scales=_SCALES[1:-1],
                   plant=1),
       shapes=st.sampled_from([("plane",), ("sphere",), RUN_SHAPES]),
       options=options(DETECT_RUN_OPTIONS, max_size=1))
def test_detect_gives_a_scene_or_a_clear_error(points, shapes, options):
    if "threshold" in options:
        options = {**options, "threshold": _threshold(options["threshold"], points)}
    scene = _outcome(lambda: jaxfit.detect(points, shapes, **{**FIT, **options}))
    if scene is not None:
        _check_scene(scene, points)


# ----- what the fuzzing found in fit's and detect's checks (each failed before its fix) ------

PLANE = np.c_[_BASE[:64, :2], 0.01 * _BASE[:64, 2]]


@pytest.mark.parametrize("points, kwargs, message", [
    (PLANE, {"threshold": 1e300}, "threshold must be at most 1e\\+150"),  # OverflowError
    (PLANE * 1e300, {}, r"coordinates up to 2.43e\+300 .*row 19.* at most 1e\+150"),  # "got inf"
    (np.zeros((8, 3), "M8[s]"), {}, "got dtype datetime64"),  # read as seconds
    (np.zeros((8, 3), [("x", "<f8")]), {}, "got dtype"),  # read as its one field
])
def test_fit_names_what_it_cannot_take(points, kwargs, message):
    with pytest.raises(ValueError, match=message):
        jaxfit.fit(points, "plane", **{**FIT, **kwargs})


@pytest.mark.parametrize("kwargs", [
    {"threshold": Fraction(1, 10)},  # TypeError from np.isfinite
    {"max_hypotheses": 10**400},  # TypeError from np.isfinite (a positive integer)
    {"max_stall": 10**400, "max_hypotheses": 256},
])
def test_fit_takes_any_real_number(kwargs):
    result = jaxfit.fit(PLANE, "plane", **{**FIT, **kwargs})
    _check_fit(result, PLANE)


@pytest.mark.parametrize("scale", [1e-200, 1e200])
def test_normals_of_any_length(scale):
    """(1e-200: "normals contain zero vectors"; 1e200: their norm overflowed, and they
    became zero vectors without a word)"""
    from jaxfit import _checks

    unit = _checks.normals_for(_BASE[:8], _BASE[:8])
    np.testing.assert_allclose(_checks.normals_for(_BASE[:8] * scale, _BASE[:8]), unit)


def test_detect_checks_its_fits_options_first():
    """An invalid fit option was only found at the first fit, after the normals, and
    fit_batch's skip_failures was let through (a failed fit then gave None: AttributeError)."""
    with _stopped_at_the_kernels():
        with pytest.raises(ValueError, match="batch_size must be a positive integer"):
            jaxfit.detect(PLANE, ("plane",), batch_size=0)
        with pytest.raises(TypeError, match="unknown fit option.*skip_failures"):
            jaxfit.detect(PLANE, ("plane",), skip_failures=True)


@pytest.mark.parametrize("tolerance, error", [
    (float("nan"), ValueError),  # IndexError in choose()
    (10**400, None),  # OverflowError in choose()
], ids=["nan", "1e400"])
def test_detect_tolerance(tolerance, error):
    call = lambda: jaxfit.detect(PLANE, ("plane",), tolerance=tolerance, **FIT)  # noqa: E731
    if error:
        with pytest.raises(error, match="tolerance must be a non-negative number"):
            call()
    else:
        _check_scene(call(), PLANE)


def test_a_tiny_cloud_is_refused_by_name_and_a_coincident_one_has_no_shape():
    """The default threshold squared the sides of the bounding box: 0 for a cloud 1e-200
    across ("threshold must be a positive finite number, got 0.0", though none was given);
    fit then found a sphere 1e-200 across with no inliers (its distances underflow)."""
    for call in (lambda p: jaxfit.detect(p, ("plane",), **FIT),
                 lambda p: jaxfit.fit(p, "plane", **FIT)):
        with pytest.raises(ValueError, match="the cloud spans only .*e-200"):
            call(PLANE * 1e-200)
    with pytest.raises(jaxfit.FitError, match="all points coincide"):
        jaxfit.detect(np.ones((20, 3)), ("plane",), **FIT)


def test_detect_shapes_may_be_one_shape():
    """(shapes="plane" was read as the shapes 'p', 'l', ...; None gave a bare TypeError)"""
    with _stopped_at_the_kernels():
        with pytest.raises(TypeError, match="shapes must be a sequence of shape names"):
            jaxfit.detect(PLANE, None)
    assert {d.shape for d in jaxfit.detect(PLANE, "plane", **FIT).shapes} == {"plane"}


def test_a_tiny_threshold_on_an_exact_plane():
    """shapes/_geometry.py main_interval made (extent / threshold) histogram bins: a
    threshold far below the cloud's size on points exactly on the surface overflowed
    int64 here, and at 1e-10 of the size allocated ~50 GB. It now counts only the
    occupied bins when there are far more bins than points."""
    points = np.c_[_BASE[:3, :2], np.zeros(3)] * 1e-100
    result = jaxfit.fit(points, "plane", threshold=1e-300, **FIT)
    assert result.num_inliers >= 3
    tracemalloc.start()
    try:
        exact = np.c_[np.random.default_rng(0).uniform(-1, 1, (200, 2)), np.zeros(200)]
        fine = jaxfit.fit(exact, "plane", threshold=1e-10, **FIT)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert fine.num_inliers == 200 and peak < 50e6


def test_fit_takes_only_fit_options_and_a_bounded_batch():
    """fit passed every keyword to fit_batch: skip_failures=True made it return None and
    thresholds= gave "multiple values"; batch_size=2**28 asked XLA for 151 GB."""
    for kwargs in ({"skip_failures": True}, {"thresholds": 0.1}):
        with pytest.raises(TypeError, match="unknown fit option"):
            jaxfit.fit(PLANE, "plane", **kwargs)
    with pytest.raises(ValueError, match="batch_size must be at most 65536"):
        jaxfit.fit(PLANE, "plane", batch_size=2**28)


def test_detect_on_fewer_points_than_normal_neighbours():
    """(estimate_normals' default k=16 raised "k = 16 is larger than the number of points")"""
    scene = jaxfit.detect(PLANE[:8], ("plane",), min_inliers=4, **FIT)
    assert sum(len(d.indices) for d in scene.shapes) + len(scene.unassigned) == 8
