"""Seeded bodies of one topology and pose mode: :class:`BodyGenerator`, :class:`Body`, :func:`generate_bodies`.

Body ``i`` of split ``s`` comes from its own random stream ``numpy.random.SeedSequence([seed, s, i])``
(s = 0 train, 1 test). With ``people``, bodies share phenotypes FAUST's way (a few people in several poses
each): the people's phenotypes come from the stream ``SeedSequence([seed, 2])`` (:func:`spread_phenotypes`,
over the pose mode's phenotype ranges) and body ``number`` is person ``number // (count // people)``; poses
stay each body's own. The topology and every body are cached under ``<cache_dir>/bodies/`` (keys in
:meth:`BodyGenerator.body_key`); the anny model is built only on a cache miss.
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib.metadata
import io
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from zernet.data.bodies.pose import (
    POSE_MODES,
    bone_rotations,
    draw_phenotype,
    draw_pose,
    phenotype_ranges,
    spread_phenotypes,
)
from zernet.data.bodies.topology import TOPOLOGIES, TOPOLOGY_ARRAYS, BodyTopology, build_topology, import_anny
from zernet.data.dataset import DatasetError
from zernet.geometry import Surface
from zernet.io_utils import atomic_write_bytes

__all__ = [
    "GENERATOR_VERSION",
    "SPLIT_CODES",
    "Body",
    "BodyGenerator",
    "generate_bodies",
    "split_of",
    "check_counts",
    "person_of",
    "package_version",
    "npz_bytes",
]

#: Bumped whenever a change alters generated bodies, so cached bodies of older versions are not reused
#: (2: the mouth and eye sockets closed, :data:`zernet.data.bodies.topology.CAVITIES`).
GENERATOR_VERSION = 2
#: Split name -> the second element of a body's SeedSequence.
SPLIT_CODES = {"train": 0, "test": 1}
# Second element of the SeedSequence of the people's phenotypes (``people=``): a stream no body draws from.
_PEOPLE_STREAM = 2
# Rotation by -90 degrees about x: (x, y, z) -> (x, z, -y). anny is z-up facing -y; FAUST's scans (and
# zernet.viz's default view) are y-up facing +z.
_Z_UP_TO_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def package_version(name: str) -> str:
    """The installed version of a distribution, or "unknown"."""
    try:
        return importlib.metadata.version(name)
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


def npz_bytes(**arrays) -> bytes:
    """An uncompressed ``.npz`` file's bytes (written atomically by the caller)."""
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    return buffer.getvalue()


@dataclass(frozen=True)
class Body:
    """A generated body: vertices (N, 3) in metres (y up, facing +z), shared faces, per-vertex parts,
    its phenotype and pose (joint angles in degrees)."""

    name: str
    split: str
    vertices: np.ndarray
    faces: np.ndarray
    parts: np.ndarray
    phenotype: dict = field(default_factory=dict)
    pose: dict = field(default_factory=dict)
    person: int | None = None  # with ``generate_bodies(people=...)``: whose body this is (same phenotype)

    @property
    def correspondence(self) -> np.ndarray:
        """The class of each vertex: its template index."""
        return np.arange(len(self.vertices), dtype=np.int64)

    def surface(self) -> Surface:
        return Surface(self.vertices, self.faces, name=self.name)


class BodyGenerator:
    """Seeded bodies of one topology and pose mode, cached under ``<cache_dir>/bodies`` (None: no cache).

    ``generator.body(index, split)`` returns the same :class:`Body` for the same arguments on any machine
    with the same anny version; the anny model is built on the first cache miss only.
    """

    def __init__(
        self,
        topology: str = "faust",
        poses: str = "varied",
        seed: int = 0,
        cache_dir: str | os.PathLike | None = ".zernet-cache",
    ):
        if topology not in TOPOLOGIES:
            raise DatasetError(f"unknown body topology {topology!r}; choose one of {', '.join(TOPOLOGIES)}")
        if poses not in POSE_MODES:
            raise DatasetError(f"unknown pose mode {poses!r}; choose one of {', '.join(POSE_MODES)}")
        self.topology_name, self.poses, self.seed = topology, poses, int(seed)
        self.cache = None if cache_dir is None else Path(os.path.expanduser(os.fspath(cache_dir))) / "bodies"
        self._model = None
        self._topology = None
        self.version = f"g{GENERATOR_VERSION}-anny{package_version('anny')}"
        if topology == "faust":
            self.version += f"-fs{package_version('fast-simplification')}"

    @property
    def model(self):
        """The anny model of this topology's base (built on first use; slow the very first time)."""
        if self._model is None:
            anny = import_anny()
            self._model = anny.Anny(topology=TOPOLOGIES[self.topology_name])
        return self._model

    def topology(self) -> BodyTopology:
        """The shared topology (read from the cache, else built on the model and cached)."""
        if self._topology is None:
            path = None if self.cache is None else self.cache / f"topology-{self.topology_name}-{self.version}.npz"
            if path is not None and path.is_file():
                with np.load(path) as stored:
                    self._topology = BodyTopology(self.topology_name, *(stored[key] for key in TOPOLOGY_ARRAYS))
            else:
                self._topology = build_topology(self.topology_name, self.model)
                if path is not None:
                    atomic_write_bytes(
                        path, npz_bytes(**{key: getattr(self._topology, key) for key in TOPOLOGY_ARRAYS})
                    )
        return self._topology

    def draws(self, index: int, split: str = "train") -> tuple[dict[str, float], dict[str, float]]:
        """(phenotype, pose in degrees) of body ``index`` of ``split``: its own random stream."""
        if split not in SPLIT_CODES:
            raise DatasetError(f"body split must be 'train' or 'test', got {split!r}")
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, SPLIT_CODES[split], int(index)]))
        return draw_phenotype(rng, phenotype_ranges(self.poses)), draw_pose(rng, self.poses)

    def body_key(self, index: int, split: str = "train", phenotype: dict[str, float] | None = None) -> str:
        """What body ``index`` of ``split`` depends on: topology, poses, seed, split, index, versions, and a
        phenotype given instead of the body's own draw."""
        key = f"{self.topology_name}-{self.poses}-seed{self.seed}-{split}{int(index)}-{self.version}"
        if phenotype is not None:
            key += "-phenotype-" + ",".join(f"{name}={value!r}" for name, value in sorted(phenotype.items()))
        return key

    def body(
        self, index: int, split: str = "train", name: str | None = None, phenotype: dict[str, float] | None = None
    ) -> Body:
        """Body ``index`` of ``split`` (named ``name``, default ``<split>_<index>``), from the cache if there;
        ``phenotype`` replaces the body's own phenotype draw (its pose stays its own)."""
        drawn, pose = self.draws(index, split)
        given, phenotype = phenotype, drawn if phenotype is None else dict(phenotype)
        topology = self.topology()
        name = name or f"{split}_{index:03d}"
        path = None
        if self.cache is not None:
            digest = hashlib.sha256(self.body_key(index, split, given).encode()).hexdigest()[:24]
            path = self.cache / self.topology_name / (digest + ".npz")
        if path is not None and path.is_file():
            with np.load(path) as stored:
                vertices = stored["vertices"]
        else:
            vertices = topology.place(self.pose_model(phenotype, pose)) @ _Z_UP_TO_Y_UP.T
            if path is not None:
                atomic_write_bytes(path, npz_bytes(vertices=vertices))
        return Body(name, split, vertices, topology.faces, topology.parts, phenotype, pose)

    def pose_model(self, phenotype: dict[str, float], pose: dict[str, float]) -> np.ndarray:
        """The model's posed vertices (V, 3), anny's frame, for a phenotype and joint angles in degrees."""
        model = self.model
        with torch.no_grad():
            rest = model(phenotype_kwargs=phenotype)
            heads = rest["rest_bone_heads"][0].detach().cpu().numpy().astype(np.float64)
            deltas = {
                bone: torch.as_tensor(matrix, dtype=model.dtype, device=model.device)[None]
                for bone, matrix in bone_rotations(list(model.bone_labels), heads, pose).items()
            }
            posed = model(pose_parameters=deltas or None, phenotype_kwargs=phenotype)
        return posed["vertices"][0].detach().cpu().numpy().astype(np.float64)


def split_of(number: int, count: int, n_test: int) -> tuple[str, int]:
    """(split, index within it) of body ``number`` of ``count``: the last ``n_test`` are test bodies."""
    n_train = count - n_test
    return ("train", number) if number < n_train else ("test", number - n_train)


def check_counts(count: int, n_test: int, people: int | None = None) -> None:
    """DatasetError unless ``count >= 1``, ``0 <= n_test < count`` and, with ``people``, the bodies split into
    that many people of equal pose counts with the test bodies whole people."""
    if count < 1 or not 0 <= n_test < count:
        raise DatasetError(f"bodies: need count >= 1 and 0 <= n_test < count, got count={count}, n_test={n_test}")
    if people is None:
        return
    if people < 1 or count % people:
        raise DatasetError(f"bodies: {count} bodies do not split into {people} people with equally many poses")
    if n_test % (count // people):
        raise DatasetError(
            f"bodies: the {n_test} test bodies must be whole people ({count // people} poses each), so that "
            "the test people are never seen in training"
        )


def person_of(number: int, count: int, people: int) -> int:
    """The person of body ``number`` of ``count`` bodies of ``people`` people: consecutive bodies, one person."""
    return number // (count // people)


def generate_bodies(
    count: int = 100,
    seed: int = 0,
    topology: str = "faust",
    poses: str = "varied",
    n_test: int = 20,
    cache_dir: str | os.PathLike | None = ".zernet-cache",
    progress: bool = False,
    people: int | None = None,
) -> list[Body]:
    """``count`` bodies named ``body_000`` ...: the first ``count - n_test`` train, the rest test. With
    ``people``, consecutive bodies are one person's poses (:func:`person_of`; FAUST's structure: 100 bodies
    of 10 people, the last 2 people the test split), each body with its ``person``."""
    check_counts(count, n_test, people)
    generator = BodyGenerator(topology, poses, seed, cache_dir)
    generator.topology()  # builds the model if needed: a missing extra is reported before any progress bar
    phenotypes = None
    if people is not None:
        rng = np.random.default_rng(np.random.SeedSequence([seed, _PEOPLE_STREAM]))
        phenotypes = spread_phenotypes(rng, people, phenotype_ranges(poses))
    bodies = []
    for number in tqdm(range(count), desc=f"bodies ({topology})", unit="body", disable=not progress):
        split, index = split_of(number, count, n_test)
        if phenotypes is None:
            bodies.append(generator.body(index, split, name=f"body_{number:03d}"))
            continue
        person = person_of(number, count, people)
        body = generator.body(index, split, name=f"body_{number:03d}", phenotype=phenotypes[person])
        bodies.append(dataclasses.replace(body, person=person))
    return bodies
