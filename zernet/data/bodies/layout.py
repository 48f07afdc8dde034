"""Generated bodies written as files, in the layouts the segmentation and FAUST loaders read.

Layout (also described by the README.txt written into the output folder)::

    out_dir/segmentation/meshes/{train,test}/body_XXX.ply
    out_dir/segmentation/labels/{train,test}/body_XXX.txt   (one 0-based part label per vertex)
    out_dir/segmentation/labels/class_names.txt             (one part name per line, label order)
    out_dir/correspondence/training/registrations/tr_reg_XXX.ply  (the same meshes, FAUST's names)

and, with ``forms`` (:mod:`zernet.data.bodies.forms`), for the test bodies (``forms_split="test"``) or all::

    out_dir/forms/<form>/meshes/{train,test}/body_XXX.ply          (a mesh, or a point cloud: no faces)
    out_dir/forms/<form>/labels/{train,test}/body_XXX.txt          (one 0-based part per vertex or point)
    out_dir/forms/<form>/labels/class_names.txt
    out_dir/forms/<form>/correspondence/{train,test}/body_XXX.txt  (template vertex per vertex or point)
    out_dir/forms/details.json                                     (per form and body: counts, draws)
"""

from __future__ import annotations

import os
import textwrap
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from zernet.data.bodies.forms import BodyForm, check_form_dependencies, make_forms, resolve_forms
from zernet.data.bodies.generator import GENERATOR_VERSION, SPLIT_CODES, Body, generate_bodies, package_version
from zernet.data.dataset import DatasetError
from zernet.data.segmentation import HUMAN_PART_NAMES
from zernet.io_utils import atomic_write_bytes, write_json

__all__ = ["BodiesLayout", "FormsLayout", "FORM_SPLITS", "write_bodies", "write_forms"]

#: Which bodies get forms: the test split only (the default) or every body.
FORM_SPLITS = ("test", "all")
# Fourth element of a body's SeedSequence for its forms: a stream the body's own draws never use.
_FORMS_STREAM = 1


@dataclass(frozen=True)
class FormsLayout:
    """Where :func:`write_forms` put the forms of the bodies (module docstring), and what they hold.

    ``summary[form][body_name]``: ``n_vertices`` (vertices or points), ``n_faces`` (None for a cloud) and the
    form's details (:class:`~zernet.data.bodies.forms.BodyForm`), also written to ``details``."""

    root: Path
    forms: tuple[str, ...]
    split: str
    details: Path
    summary: dict = field(default_factory=dict)

    def meshes(self, form: str) -> Path:
        return self.root / form / "meshes"

    def labels(self, form: str) -> Path:
        return self.root / form / "labels"

    def correspondence(self, form: str) -> Path:
        return self.root / form / "correspondence"


@dataclass(frozen=True)
class BodiesLayout:
    """Where :func:`write_bodies` put things (see the README.txt it writes)."""

    root: Path
    meshes: Path
    labels: Path
    class_names: Path
    registrations: Path
    readme: Path
    topology: str
    n_vertices: int
    n_train: int
    n_test: int
    forms: FormsLayout | None = None


def _ply_bytes(body: Body) -> bytes:
    import trimesh  # here, not at start-up

    return trimesh.Trimesh(body.vertices, body.faces, process=False).export(file_type="ply")


def _form_ply_bytes(form: BodyForm) -> bytes:
    """A form as PLY: a mesh exactly as made (nothing merged or dropped), or vertices only for a cloud."""
    import trimesh  # here, not at start-up

    if form.faces is None:
        return trimesh.PointCloud(form.vertices).export(file_type="ply")
    return trimesh.Trimesh(form.vertices, form.faces, process=False, validate=False).export(file_type="ply")


def _lines(values: np.ndarray) -> bytes:
    return ("\n".join(str(int(value)) for value in values) + "\n").encode()


def write_bodies(
    out_dir: str | os.PathLike,
    count: int = 100,
    seed: int = 0,
    topology: str = "faust",
    poses: str = "varied",
    n_test: int = 20,
    cache_dir: str | os.PathLike | None = ".zernet-cache",
    progress: bool = True,
    forms: str | Sequence[str] | None = None,
    forms_split: str = "test",
    people: int | None = None,
) -> BodiesLayout:
    """Generate bodies (:func:`~zernet.data.bodies.generator.generate_bodies`) and write them in the layout
    of the module docstring; with ``forms`` (names, a comma-separated string or ``"all"``), also those forms
    of the test bodies (``forms_split="test"``) or of every body (``"all"``), by :func:`write_forms`. With
    ``people``, the bodies are that many people in several poses each (FAUST's structure) and
    ``people.json`` says whose each body is, with the phenotypes. Returns where everything went."""
    forms = resolve_forms(forms)  # a bad name or a missing package fails before any body is made
    check_form_dependencies(forms)
    _check_forms_split(forms_split)
    root = Path(os.path.expanduser(os.fspath(out_dir)))
    bodies = generate_bodies(count, seed, topology, poses, n_test, cache_dir, progress, people)
    forms_layout = write_forms(root, bodies, forms, seed, forms_split, progress) if forms else None
    layout = BodiesLayout(
        root,
        root / "segmentation" / "meshes",
        root / "segmentation" / "labels",
        root / "segmentation" / "labels" / "class_names.txt",
        root / "correspondence" / "training" / "registrations",
        root / "README.txt",
        topology,
        len(bodies[0].vertices),
        count - n_test,
        n_test,
        forms_layout,
    )
    for number, body in enumerate(bodies):
        mesh = _ply_bytes(body)
        atomic_write_bytes(layout.meshes / body.split / f"{body.name}.ply", mesh)
        labels = "\n".join(str(int(label)) for label in body.parts) + "\n"
        atomic_write_bytes(layout.labels / body.split / f"{body.name}.txt", labels.encode())
        atomic_write_bytes(layout.registrations / f"tr_reg_{number:03d}.ply", mesh)
    atomic_write_bytes(layout.class_names, ("\n".join(HUMAN_PART_NAMES) + "\n").encode())
    atomic_write_bytes(layout.readme, _readme(layout, seed, poses, people).encode())
    if people is not None:
        write_json(
            root / "people.json",
            {
                "people": people,
                "bodies": {body.name: {"person": body.person, "split": body.split} for body in bodies},
                "phenotypes": {str(body.person): body.phenotype for body in bodies},
            },
        )
    return layout


def _check_forms_split(split: str) -> None:
    if split not in FORM_SPLITS:
        raise DatasetError(f"forms split must be one of {', '.join(FORM_SPLITS)}, got {split!r}")


def write_forms(
    out_dir: str | os.PathLike,
    bodies: Sequence[Body],
    forms: str | Sequence[str] | None = "all",
    seed: int = 0,
    split: str = "test",
    progress: bool = False,
) -> FormsLayout:
    """Write the forms (:func:`~zernet.data.bodies.forms.make_forms`) of ``bodies`` under ``out_dir/forms``.

    ``bodies`` are in :func:`~zernet.data.bodies.generator.generate_bodies` order (the train bodies, then the
    test ones); ``split="test"`` makes forms of the test bodies only, ``"all"`` of every body. The forms of
    body ``i`` of split ``s`` come from the stream ``numpy.random.SeedSequence([seed, s, i, 1])`` (s = 0
    train, 1 test): the same for a given seed and body whatever ``count`` and the other forms asked for.
    Every file is written atomically. Returns a :class:`FormsLayout` with each form's counts and details.
    """
    names = resolve_forms(forms)
    _check_forms_split(split)
    root = Path(os.path.expanduser(os.fspath(out_dir))) / "forms"
    layout = FormsLayout(root, names, split, root / "details.json", {name: {} for name in names})
    index_in_split: dict[str, int] = {}
    chosen = []
    for body in bodies:
        index = index_in_split.get(body.split, 0)
        index_in_split[body.split] = index + 1
        if split == "all" or body.split == "test":
            chosen.append((body, index))
    for body, index in tqdm(chosen, desc=f"forms ({', '.join(names)})", unit="body", disable=not progress):
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), SPLIT_CODES[body.split], index, _FORMS_STREAM]))
        for name, form in make_forms(body, names, rng).items():
            atomic_write_bytes(layout.meshes(name) / body.split / f"{body.name}.ply", _form_ply_bytes(form))
            atomic_write_bytes(layout.labels(name) / body.split / f"{body.name}.txt", _lines(form.labels))
            atomic_write_bytes(
                layout.correspondence(name) / body.split / f"{body.name}.txt", _lines(form.template_vertex)
            )
            layout.summary[name][body.name] = {
                "n_vertices": len(form.vertices),
                "n_faces": None if form.faces is None else len(form.faces),
                **form.details,
            }
    for name in names:
        atomic_write_bytes(layout.labels(name) / "class_names.txt", ("\n".join(HUMAN_PART_NAMES) + "\n").encode())
    write_json(layout.details, {"seed": int(seed), "split": split, "forms": layout.summary})
    return layout


def _readme(layout: BodiesLayout, seed: int, poses: str, people: int | None) -> str:
    last = layout.n_train + layout.n_test - 1
    if people is None:
        who = """set; test phenotypes and poses are independent draws from a random stream the training bodies do not use."""
    else:
        per_person = (last + 1) // people
        who = f"""set. The bodies are {people} people in {per_person} poses each (FAUST's structure): body_XXX is person
XXX // {per_person}, so the test bodies are people never seen in training (people.json: whose each body is, with
the phenotypes). The people's phenotypes are spread over every range of the model (a Latin hypercube)."""
    return f"""Human bodies generated by zernet (zernet.data.bodies, generator version {GENERATOR_VERSION}) with the
parametric body model anny {package_version("anny")}: seed {seed}, poses "{poses}", topology "{layout.topology}"
({layout.n_vertices} vertices, one connectivity shared by every body). Metres, y up, facing +z (as FAUST).
Bodies body_000 ... body_{layout.n_train - 1:03d} are the training set, the rest (up to body_{last:03d}) the test
{who}

segmentation/meshes/train/body_XXX.ply, segmentation/meshes/test/body_XXX.ply
segmentation/labels/train/body_XXX.txt, segmentation/labels/test/body_XXX.txt
    one part label per vertex (0-based), in the order of segmentation/labels/class_names.txt:
    {", ".join(f"{i} {name}" for i, name in enumerate(HUMAN_PART_NAMES))}
    (the 8 parts of the human-segmentation benchmark of Maron et al. 2017, left and right merged).
correspondence/training/registrations/tr_reg_XXX.ply
    the same meshes under FAUST's names (tr_reg_XXX = body_XXX): the correspondence class of a vertex is
    its index. Split: 000-{layout.n_train - 1:03d} train, {layout.n_train:03d}-{last:03d} test.
Read them with zernet's configs bodies_segmentation.yaml and bodies_correspondence.yaml (this folder's
split: --set data.train_indices=0:{layout.n_train} data.test_indices={layout.n_train}:{last + 1}).
""" + ("" if layout.forms is None else _forms_readme(layout.forms))


# What each form is, for the README.txt (docs/BODIES.md and zernet.data.bodies.forms say more).
_FORM_TEXT = {
    "remeshed": "remeshed isotropically (MeshLab), its own triangulation and vertex count per body, vertices on "
    "the surface",
    "decimated": "quadric decimation to half the faces (fast-simplification), left as the simplifier returns it: "
    "non-manifold edges and near-duplicate faces are kept on purpose",
    "cloud": "points uniform on the surface (area-weighted), as many as the body has vertices; PLY without faces",
    "cloud-noisy": "half as many points, density varying smoothly over the body (a factor 3), Gaussian noise "
    "of 2 mm per coordinate; PLY without faces",
    "partial": "the faces one camera sees (front-facing, not occluded; orthographic, a random direction around "
    "the vertical axis per body), vertices renumbered",
}


def _count_range(values: list) -> str:
    if not values:
        return "0"
    return f"{min(values)}" if min(values) == max(values) else f"{min(values)}-{max(values)}"


def _forms_readme(forms: FormsLayout) -> str:
    which = "the test bodies" if forms.split == "test" else "every body"
    text = [
        f"""
forms/<form>/meshes/<split>/body_XXX.ply        {which} in the forms a scan comes in (below)
forms/<form>/labels/<split>/body_XXX.txt        one part label per vertex or point (0-based, as above)
forms/<form>/correspondence/<split>/body_XXX.txt  the template vertex (= vertex of the body's own mesh above)
                                                of each vertex or point
forms/details.json                              per form and body: counts and what was drawn
    Ground truth: the position of each vertex or point on the original body (the sampled point, without
    noise, for clouds; the closest point of the body's surface for remeshed and decimated meshes) in
    barycentric coordinates of one of its triangles; the corner with the largest weight is the template
    vertex, and its part the label. Same seed and body: the same forms.
    Read a form with the segmentation loader: data.meshes=forms/<form>/meshes data.labels=forms/<form>/labels.
"""
    ]
    for name in forms.forms:
        bodies = forms.summary[name]
        vertices = [entry["n_vertices"] for entry in bodies.values()]
        line = f"{len(bodies)} bodies, {_count_range(vertices)} " + (
            "points" if name.startswith("cloud") else "vertices"
        )
        faces = [entry["n_faces"] for entry in bodies.values() if entry["n_faces"] is not None]
        if faces:
            line += f", {_count_range(faces)} faces"
        if name == "decimated":
            counts = [entry["nonmanifold_edges"] for entry in bodies.values()]
            duplicates = [entry["duplicate_faces"] for entry in bodies.values()]
            line += (
                f"; non-manifold edges (shared by more than 2 faces) per body: {_count_range(counts)} "
                f"({sum(counts)} in all), duplicate faces: {_count_range(duplicates)}"
            )
        text.append(
            textwrap.fill(f"{name}: {_FORM_TEXT[name]}.", 110, initial_indent="  ", subsequent_indent="    ") + "\n"
        )
        text.append(textwrap.fill(line + ".", 110, initial_indent="    ", subsequent_indent="    ") + "\n")
    return "".join(text)
