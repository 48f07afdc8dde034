"""The real-people check of benchmarks/experiments/scans.py (``--real``): the forms it scores carry the labels
of the scan vertices they come from, and its tallies count what they should.

A 642-vertex sphere labelled by octant stands in for a FAUST scan (whose files never enter the repository).
"""

import numpy as np
import trimesh
from meshes import icosphere
from scipy.spatial import cKDTree

from benchmarks.experiments.scans import EXTREMITIES, FORMS, REAL_PART_NAMES, FormTally, real_forms
from zernet.data.bodies.forms import closest_points


def _write_scan(root, number: int) -> np.ndarray:
    """A sphere as ``root/meshes/tr_reg_XXX.ply`` with 1-based octant labels in ``root/labels`` (FAUST's
    segmentation layout); returns the 0-based labels."""
    sphere = icosphere(subdivisions=3)
    octant = (sphere.vertices > 0) @ np.array([1, 2, 4])
    for kind in ("meshes", "labels"):
        (root / kind).mkdir(parents=True, exist_ok=True)
    trimesh.Trimesh(sphere.vertices, sphere.faces, process=False).export(root / "meshes" / f"tr_reg_{number:03d}.ply")
    np.savetxt(root / "labels" / f"tr_reg_{number:03d}.txt", octant + 1, fmt="%d")
    return octant


def test_each_form_of_a_scan_carries_the_labels_of_the_scan_vertices_it_comes_from(tmp_path):
    labels = _write_scan(tmp_path, 61)
    forms = real_forms(tmp_path, 61, FORMS)
    assert list(forms) == [*FORMS, "vertices"]
    scan, original_labels = forms["original"]
    np.testing.assert_array_equal(original_labels, labels)  # the files' 1-8 read as 0-7

    cloud, cloud_labels = forms["vertices"]
    assert cloud.faces is None
    np.testing.assert_array_equal(cloud.vertices, scan.vertices)
    np.testing.assert_array_equal(cloud_labels, labels)

    # A one-sided scan keeps scan vertices: each point's label is exactly its vertex's.
    partial, partial_labels = forms["partial"]
    assert 0.2 * scan.n_vertices < partial.n_vertices < scan.n_vertices
    distance, vertex = cKDTree(scan.vertices).query(partial.vertices)
    assert distance.max() < 1e-9
    np.testing.assert_array_equal(partial_labels, labels[vertex])

    # Points made anew (on the surface, no noise) take the label of a corner of the scan triangle they lie in;
    # several octants meet in most of the boundary triangles, so a wrong corner or an unmapped point shows.
    for form in ("remeshed", "decimated", "cloud"):
        surface, form_labels = forms[form]
        face, _, _, _ = closest_points(scan.vertices, scan.faces, surface.vertices)
        corner_labels = labels[scan.faces[face]]
        assert (corner_labels == form_labels[:, None]).any(axis=1).all(), form
        assert len(np.unique(form_labels)) == 8, form


def test_forms_are_seeded_by_the_scan_number(tmp_path):
    _write_scan(tmp_path, 60)
    _write_scan(tmp_path, 62)
    first, again, other = (real_forms(tmp_path, number, ["cloud"])["cloud"][0] for number in (60, 60, 62))
    np.testing.assert_array_equal(first.vertices, again.vertices)
    assert not np.allclose(first.vertices, other.vertices)


def test_form_tally_pools_points_overall_per_part_and_on_the_head_and_hands():
    head, hand, torso = (REAL_PART_NAMES.index(name) for name in ("head", "hand", "torso"))
    assert set(EXTREMITIES) == {head, hand}
    tally = FormTally()
    tally.add(np.array([head, hand, hand, hand, torso, torso]), np.array([head, head, hand, hand, torso, torso]), 2.0)
    tally.add(np.array([torso, head]), np.array([torso, torso]), 4.0)
    row = tally.row()
    assert row["accuracy"] == 6 / 8
    assert row["accuracy_head_and_hands"] == 3 / 4
    assert row["accuracy_elsewhere"] == 3 / 4
    assert row["head_and_hands_share"] == 4 / 8
    assert row["accuracy_per_part"]["head"] == 1 / 2
    assert row["accuracy_per_part"]["hand"] == 1.0
    assert row["accuracy_per_part"]["foot"] is None
    assert row["per_shape_min"] == 1 / 2
    assert row["vertices"] == 8
    assert row["seconds_per_shape_median"] == 3.0
