"""The data kind ``"bodies"``: generated human bodies trained on directly, without writing files first.

``load_dataset("bodies", task="segmentation", count=40, topology="coarse-615", n_test=8, ...)`` generates
(or reads from the body cache) ``count`` bodies with :class:`~zernet.data.bodies.generator.BodyGenerator`,
then preprocesses them like any other shape: each body's patch operators are cached under ``cache_dir``
with a key made of everything the body depends on (generator and anny versions, topology, poses, seed,
split, index) and the task, so a second run neither poses bodies nor rebuilds operators.

Tasks:

- ``"segmentation"``: 8-part labels (:data:`~zernet.data.segmentation.HUMAN_PART_NAMES`, left and right
  merged) from the body model's skinning weights;
- ``"correspondence"``: the class of a vertex is its index in the shared topology (``num_classes`` = vertex
  count, ``dataset.correspondence`` True), as for FAUST.

Split: the first ``count - n_test`` bodies are the training bodies (body ``i`` of the train stream), the
last ``n_test`` the test bodies (independent draws from the test stream, see :mod:`zernet.data.bodies`);
``options.n_val`` validation bodies (default 0.1) are carved from the training ones, seeded by
``options.seed``. The bodies themselves are seeded by ``body_seed`` (default: ``options.seed``, i.e. the
configuration's ``data.seed``).
"""

from __future__ import annotations

import json
from functools import partial

import numpy as np
from tqdm.auto import tqdm

from zernet.data.bodies.generator import BodyGenerator, check_counts, split_of
from zernet.data.dataset import DatasetError, ShapeDataset
from zernet.data.faust import FAUST_AREA, faust_patch_configs
from zernet.data.options import LoaderOptions
from zernet.data.preprocess import build_dataset
from zernet.data.segmentation import HUMAN_PART_NAMES
from zernet.data.source import ShapeSource
from zernet.geometry import Surface

__all__ = ["BODY_TASKS", "load_bodies", "body_shape"]

BODY_TASKS = ("segmentation", "correspondence")


def body_shape(name: str, vertices: np.ndarray, faces: np.ndarray, target: np.ndarray) -> tuple[Surface, np.ndarray]:
    """ShapeSource loader of one generated body (module level, so workers can unpickle it)."""
    return Surface(vertices, faces, name=name), target


def load_bodies(
    task: str = "segmentation",
    count: int = 40,
    n_test: int = 8,
    topology: str = "coarse-615",
    poses: str = "varied",
    body_seed: int | None = None,
    area: float | None = FAUST_AREA,
    options: LoaderOptions = LoaderOptions(),
) -> ShapeDataset:
    """``count`` generated bodies as a data set (see the module docstring).

    Args:
        task: "segmentation" (8 parts) or "correspondence" (class = vertex index).
        count, n_test: bodies in all, and of them test bodies (the last ones).
        topology, poses: see :mod:`zernet.data.bodies` (``coarse-369`` / ``coarse-615`` / ``coarse-1229`` /
            ``faust`` / ``full``; ``rest`` / ``mild`` / ``varied``).
        body_seed: seed of the bodies (None: ``options.seed``).
        area: surface area every body is scaled to (default FAUST's 15000; None keeps metres).
        options: the shared :class:`~zernet.data.options.LoaderOptions`; defaults ``patch_configs``
            :func:`~zernet.data.faust.faust_patch_configs` (made for area 15000), ``n_val`` 0.1. Bodies are
            cached under ``options.cache_dir/bodies`` with the preprocessed shapes.
    """
    options = options.with_defaults(n_val=0.1, patch_configs=faust_patch_configs())
    if task not in BODY_TASKS:
        raise DatasetError(f"bodies: task must be one of {', '.join(BODY_TASKS)}, got {task!r}")
    check_counts(int(count), int(n_test))
    seed = options.seed if body_seed is None else int(body_seed)
    generator = BodyGenerator(topology, poses, seed, options.cache_dir)
    generator.topology()  # builds the model if needed: a missing extra is reported before any progress bar
    sources, splits = [], {"train": [], "test": []}
    for number in tqdm(range(int(count)), desc=f"bodies ({topology})", unit="body", disable=not options.progress):
        split, index = split_of(number, int(count), int(n_test))
        body = generator.body(index, split, name=f"body_{number:03d}")
        target = body.parts if task == "segmentation" else body.correspondence
        sources.append(
            ShapeSource(
                name=body.name,
                load=partial(body_shape, body.name, body.vertices, body.faces, target),
                key=json.dumps({"body": generator.body_key(index, split), "task": task}),
            )
        )
        splits[split].append(body.name)
    n_vertices = generator.topology().n_vertices
    segmentation = task == "segmentation"
    return build_dataset(
        sources,
        target_area=None if area is None else float(area),
        task="classification",
        num_classes=len(HUMAN_PART_NAMES) if segmentation else n_vertices,
        split_names=splits,
        correspondence=not segmentation,
        info={
            "kind": "bodies",
            "task": task,
            "topology": topology,
            "poses": poses,
            "body_seed": seed,
            "n_vertices": n_vertices,
            "class_names": list(HUMAN_PART_NAMES) if segmentation else None,
            "generator": generator.version,
        },
        **options.build_arguments(),
    )
