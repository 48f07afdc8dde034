"""Bad-input sweep: random and malformed meshes, label files and value files fed to every loader and to
preprocessing. Each input must give either a clear error (SurfaceError / DatasetError whose message names
the file) or a valid result that says exactly what the file says — never a hang (pytest-timeout), a crash
or a silent wrong answer.
"""

from __future__ import annotations

import os
import struct
import warnings

import numpy as np
import pytest
import scipy.io
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from meshes import tetrahedron

from zernet.data.dataset import DatasetError
from zernet.data.preprocess import prepare_record
from zernet.data.regression import load_mat_field, read_values
from zernet.data.segmentation import load_labelled_mesh, read_labels
from zernet.geometry import Surface, SurfaceError, SurfaceWarning, load_surface
from zernet.operators import PatchConfig

pytestmark = pytest.mark.timeout(120)

SWEEP = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])

# Coordinates: ordinary values mixed with the troublemakers.
SPECIAL = [float("nan"), float("inf"), -float("inf"), 1e300, -1e300, 1e-300, 0.0]
coordinate = st.one_of(st.floats(-10, 10, allow_nan=False), st.sampled_from(SPECIAL))


def _unique_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("bad")


def _expect_clear_error_or(loader, path, check=None):
    """Call ``loader(path)``: a SurfaceError/DatasetError naming the file, or a result passed to ``check``."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            result = loader(path)
        except (SurfaceError, DatasetError) as error:
            assert os.path.basename(str(path)) in str(error), f"error does not name the file: {error}"
            return None
    if check is not None:
        check(result)
    return result


def _valid_surface(surface: Surface) -> None:
    assert surface.n_vertices > 0
    assert np.isfinite(surface.vertices).all()
    if surface.faces is not None:
        assert surface.faces.dtype == np.int64 and len(surface.faces)
        assert surface.faces.min() >= 0 and surface.faces.max() < surface.n_vertices


# ------------------------------------------------------------------------------- writers
def _obj(vertices, faces) -> str:
    lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    return "\n".join(lines) + "\n"


def _off(vertices, faces) -> str:
    lines = ["OFF", f"{len(vertices)} {len(faces)} 0"]
    lines += [f"{x!r} {y!r} {z!r}" for x, y, z in vertices]
    lines += [f"3 {a} {b} {c}" for a, b, c in faces]
    return "\n".join(lines) + "\n"


def _ply_ascii(vertices, faces) -> str:
    header = [
        "ply",
        "format ascii 1.0",
        f"element vertex {len(vertices)}",
        "property float64 x",
        "property float64 y",
        "property float64 z",
        f"element face {len(faces)}",
        "property list uchar int vertex_indices",
        "end_header",
    ]
    lines = [f"{x!r} {y!r} {z!r}" for x, y, z in vertices] + [f"3 {a} {b} {c}" for a, b, c in faces]
    return "\n".join(header + lines) + "\n"


def _ply_binary(vertices, faces) -> bytes:
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(vertices)}\nproperty double x\nproperty double y\nproperty double z\n"
        f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n"
    ).encode()
    body = b"".join(struct.pack("<3d", *v) for v in vertices)
    body += b"".join(struct.pack("<B3i", 3, *f) for f in faces)
    return header + body


WRITERS = {".obj": _obj, ".off": _off, ".ply": _ply_ascii}


@st.composite
def meshes(draw):
    """Small meshes with random coordinates (incl. NaN/inf/1e300) and indices (incl. negative, too large)."""
    n = draw(st.integers(0, 6))
    vertices = draw(st.lists(st.tuples(coordinate, coordinate, coordinate), min_size=n, max_size=n))
    index = st.integers(-2, n + 2)
    faces = draw(st.lists(st.tuples(index, index, index), min_size=0, max_size=6))
    return vertices, faces


def _matches_file(vertices, faces):
    """A loaded surface must be exactly what was written (nothing dropped, clipped or renumbered)."""

    def check(surface):
        _valid_surface(surface)
        np.testing.assert_array_equal(surface.vertices, np.asarray(vertices, dtype=np.float64))
        np.testing.assert_array_equal(surface.faces, np.asarray(faces, dtype=np.int64).reshape(-1, 3))

    return check


@pytest.mark.parametrize("extension", sorted(WRITERS))
@SWEEP
@given(mesh=meshes())
def test_random_meshes_load_exactly_or_fail_clearly(tmp_path_factory, extension, mesh):
    vertices, faces = mesh
    path = _unique_dir(tmp_path_factory) / f"mesh{extension}"
    path.write_text(WRITERS[extension](vertices, faces))
    has_negative = any(i < 0 for face in faces for i in face)
    # OBJ's negative indices are relative (legal), and a file without faces is a point cloud.
    check = _valid_surface if (extension == ".obj" and has_negative) or not faces else _matches_file(vertices, faces)
    _expect_clear_error_or(load_surface, path, check)


@pytest.mark.parametrize("extension", [".obj", ".off", ".ply", ".stl", ".mat", ".npy", ".txt", ".xyz"])
@SWEEP
@given(
    data=st.one_of(
        st.binary(max_size=300),
        st.text(max_size=200).map(lambda t: t.encode("utf-8")),
        st.sampled_from(
            [
                b"\xff\xfe\x00garbage",
                b"ply\nformat ascii 1.0\nend_header\n",
                b"OFF\n3 1 0\n0 0 0\n1 0 0\n",
                b"v 1 2\nf 1 2 3\n",
                "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n".encode("utf-16"),
            ]
        ),
    )
)
def test_garbage_bytes_fail_clearly_for_every_format(tmp_path_factory, extension, data):
    path = _unique_dir(tmp_path_factory) / f"garbage{extension}"
    path.write_bytes(data)
    _expect_clear_error_or(load_surface, path, _valid_surface)


def _tetrahedron():
    """The shared tetrahedron as plain Python lists, for the file writers above."""
    surface = tetrahedron()
    return surface.vertices.tolist(), surface.faces.tolist()


@SWEEP
@given(cut=st.integers(0, 200))
def test_truncated_binary_ply_is_an_error_never_a_partial_mesh(tmp_path_factory, cut):
    vertices, faces = _tetrahedron()
    data = _ply_binary(vertices, faces)
    cut = min(cut, len(data) - 1)
    path = _unique_dir(tmp_path_factory) / "cut.ply"
    path.write_bytes(data[: len(data) - 1 - cut])
    _expect_clear_error_or(load_surface, path, _matches_file(vertices, faces))


@pytest.mark.parametrize("scale", [1e300, 1e160, 1e-160, 1e-300])
def test_coordinates_whose_areas_overflow_ask_for_rescaling(tmp_path, scale):
    vertices, faces = _tetrahedron()
    path = tmp_path / "scaled.off"
    path.write_text(_off([tuple(scale * c for c in v) for v in vertices], faces))
    with pytest.raises(SurfaceError, match="scaled.off: coordinates reach .* rescale the file"):
        load_surface(path)


def test_fractional_or_nan_mat_face_indices_are_not_truncated(tmp_path):
    vertices, faces = _tetrahedron()
    one_based = np.asarray(faces, dtype=np.float64) + 1
    for bad in (1.5, float("nan")):
        broken = one_based.copy()
        broken[2, 1] = bad
        scipy.io.savemat(tmp_path / "tet.mat", {"X": np.asarray(vertices), "F": broken})
        with pytest.raises(SurfaceError, match=r"tet.mat: face 2 = .* is not a whole vertex index"):
            load_surface(tmp_path / "tet.mat")


def test_non_manifold_and_empty_meshes_name_the_file(tmp_path):
    fan = [(0.0, 0, 0), (1.0, 0, 0), (0, 1.0, 0), (0, -1.0, 0), (0, 0, 1.0)]
    path = tmp_path / "fan.off"
    path.write_text(_off(fan, [(0, 1, 2), (0, 1, 3), (0, 1, 4)]))
    with pytest.warns(SurfaceWarning, match="fan.off: 1 non-manifold edges"):
        assert load_surface(path).n_faces == 3  # kept: the backends work on it
    empty = tmp_path / "empty.obj"
    empty.write_text("# nothing here\n")
    with pytest.raises(SurfaceError, match="empty.obj"):
        load_surface(empty)


# ---------------------------------------------------------------------------------- .mat files
@SWEEP
@given(
    x=st.lists(st.tuples(coordinate, coordinate, coordinate), min_size=0, max_size=5),
    f=st.lists(
        st.tuples(*[st.one_of(st.integers(-1, 7), st.sampled_from([1.5, float("nan"), 1e300]))] * 3),
        min_size=0,
        max_size=4,
    ),
    field_length=st.integers(0, 6),
)
def test_random_mat_files_load_exactly_or_fail_clearly(tmp_path_factory, x, f, field_length):
    path = _unique_dir(tmp_path_factory) / "shape.mat"
    content = {"X": np.asarray(x, dtype=np.float64).reshape(-1, 3), "J2m": np.arange(float(field_length))}
    if f:
        content["F"] = np.asarray(f, dtype=np.float64)
    scipy.io.savemat(path, content)

    def check(surface):
        _valid_surface(surface)
        np.testing.assert_array_equal(surface.vertices, content["X"])
        if f:
            np.testing.assert_array_equal(surface.faces + 1, content["F"])  # 1-based in the file, exactly

    _expect_clear_error_or(load_surface, path, check)
    if len(x) == field_length:

        def check_field(result):
            surface, target = result
            np.testing.assert_array_equal(target, content["J2m"])

        _expect_clear_error_or(lambda p: load_mat_field(str(p), "J2m"), path, check_field)


# ------------------------------------------------------------------------- label and value files
label_text = st.one_of(
    st.lists(
        st.one_of(
            st.integers(-5, 10), st.sampled_from(["nan", "inf", "1e300", "2.5", "-0", "x", "", "9223372036854775808"])
        ),
        max_size=8,
    ).map(lambda items: "\n".join(map(str, items))),
    st.text(max_size=50),
)


@SWEEP
@given(text=label_text)
def test_label_files_parse_exactly_or_fail_clearly(tmp_path_factory, text):
    path = _unique_dir(tmp_path_factory) / "labels.txt"
    path.write_text(text, encoding="utf-8")

    def check(labels):
        assert labels.dtype == np.int64 and labels.ndim == 1 and len(labels)
        expected = [float(token) for token in text.split()]
        np.testing.assert_array_equal(labels.astype(np.float64), expected)  # nothing clipped or wrapped

    _expect_clear_error_or(read_labels, path, check)


@SWEEP
@given(
    values=st.lists(st.one_of(st.floats(-1e3, 1e3), st.sampled_from(SPECIAL)), max_size=6),
    kind=st.sampled_from(["txt", "npy", "npy-str", "npy-2d", "bytes"]),
)
def test_value_files_parse_exactly_or_fail_clearly(tmp_path_factory, values, kind):
    folder = _unique_dir(tmp_path_factory)
    if kind == "txt":
        path = folder / "values.txt"
        path.write_text("\n".join(repr(v) for v in values))
    elif kind == "bytes":
        path = folder / "values.txt"
        path.write_bytes(b"\x00\xff" + repr(values).encode("utf-16"))
    else:
        path = folder / "values.npy"
        array = np.asarray(values, dtype=np.float64)
        if kind == "npy-str":
            array = array.astype(str)
        elif kind == "npy-2d":
            array = np.stack([array, array], axis=1) if len(array) else array.reshape(0, 2)
        np.save(path, array)
    for reader in (read_values, read_labels):

        def check(result):
            assert result.ndim == 1 and np.isfinite(result).all()
            assert np.abs(result).max(initial=0) < 1e150  # huge values would overflow the standardisation

        _expect_clear_error_or(reader, path, check)


def test_label_count_mismatch_names_both_files(tmp_path):
    vertices, faces = _tetrahedron()
    mesh = tmp_path / "tet.off"
    mesh.write_text(_off(vertices, faces))
    labels = tmp_path / "tet.txt"
    labels.write_text("0\n1\n0\n")  # 3 labels: neither 4 vertices nor 4 faces
    with pytest.raises(DatasetError, match=r"tet\.txt: has 3 labels but .*tet\.off has 4 vertices"):
        load_labelled_mesh(str(mesh), str(labels), "auto", 0, 2, False)
    labels.write_text("0\n1\n0\n7\n")  # right count, label outside the classes
    with pytest.raises(DatasetError, match=r"tet\.txt: label 7 is outside the 2 classes"):
        load_labelled_mesh(str(mesh), str(labels), "auto", 0, 2, False)


# ------------------------------------------------------------------------ preprocessing odd meshes
ODD = {
    "single triangle": ([(0, 0, 0), (1, 0, 0), (0, 1, 0)], [(0, 1, 2)]),
    "two disjoint triangles": (
        [(0, 0, 0), (1, 0, 0), (0, 1, 0), (5, 5, 5), (6, 5, 5), (5, 6, 5)],
        [(0, 1, 2), (3, 4, 5)],
    ),
    "needle triangle": ([(0, 0, 0), (1, 0, 0), (0.5, 1e-7, 0)], [(0, 1, 2)]),
    "tetrahedron": _tetrahedron(),
    "point cloud of 3": ([(0, 0, 0), (1, 0, 0), (0, 1, 0)], None),
}


@pytest.mark.parametrize("name", sorted(ODD))
def test_operators_of_tiny_odd_meshes_are_finite_or_a_clear_error(name):
    vertices, faces = ODD[name]
    surface = Surface(np.asarray(vertices, dtype=np.float64), None if faces is None else np.asarray(faces), name=name)
    config = PatchConfig(r0=0.8, n_samples=60, patch_size=8, n_max=2)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            record = prepare_record(surface, [config], cache_dir=None, target_area=1.0)
    except (SurfaceError, DatasetError, ValueError) as error:
        assert name in str(error), error
        return
    operator = record.geometry.operators[0]
    assert operator.matrix.shape == (len(vertices) * operator.k, len(vertices))
    assert np.isfinite(operator.matrix.data).all()
    assert np.isfinite(record.features).all()


@pytest.mark.parametrize("extension, face_line, first", [(".obj", "f 1 2 9", 1), (".off", "3 0 1 8", 0)])
def test_a_face_past_the_vertex_count_names_the_face_and_its_line(tmp_path, extension, face_line, first):
    vertices, faces = _tetrahedron()
    if extension == ".obj":
        lines = [
            "# a tetrahedron",
            *(f"v {x} {y} {z}" for x, y, z in vertices),
            *(f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces),
        ]
        lines[1 + 4 + 2] = face_line  # face 2, on line 8
    else:
        lines = [
            "OFF",
            f"{len(vertices)} {len(faces)} 0",
            *(f"{x} {y} {z}" for x, y, z in vertices),
            *(f"3 {a} {b} {c}" for a, b, c in faces),
        ]
        lines[2 + 4 + 2] = face_line  # face 2, on line 9
    path = tmp_path / f"mesh{extension}"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(SurfaceError) as caught:
        load_surface(path)
    line = 8 if extension == ".obj" else 9
    vertex = face_line.split()[-1]
    assert str(caught.value) == (
        f"{path}: face 2 (line {line}) refers to vertex {vertex}, but the file has 4 vertices ({first}-based indices)"
    )


def test_a_binary_obj_is_unreadable_not_empty(tmp_path):
    path = tmp_path / "binary.obj"
    path.write_bytes(bytes(np.random.default_rng(1).integers(128, 256, 2000).astype(np.uint8)))
    with pytest.raises(SurfaceError, match=r"binary.obj: unreadable: not a text OBJ file \(binary or not UTF-8"):
        load_surface(path)
    path.write_bytes(b"v 0 0 0\x00\x01\x02" * 50)
    with pytest.raises(SurfaceError, match="unreadable: not a text OBJ file"):
        load_surface(path)


def test_text_in_label_and_value_files_is_named_by_file_and_1_based_line(tmp_path):
    path = tmp_path / "labels.txt"
    path.write_text("# part labels\n0\n1\n\n2 3\nhead\n")
    with pytest.raises(DatasetError, match=r"labels.txt: line 6: 'head' is not a number"):
        read_labels(path)
    path.write_text("0\n1\n2.5\n")
    with pytest.raises(DatasetError, match=r"labels.txt: line 3: label 2.5 is not an integer class label"):
        read_labels(path)
    path.write_text("1.0\n\n2.0\nnan\n")
    with pytest.raises(DatasetError, match=r"labels.txt: line 4: value nan is not finite"):
        read_values(path)
    path.write_bytes(b"\xff\xfe1\n2\n")
    with pytest.raises(DatasetError, match="unreadable: not a text file of labels"):
        read_labels(path)
