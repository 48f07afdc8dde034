"""Where each step's shapes come from: the residency levels of ``data.residency``.

A step reads a record's features, target and geometry; what costs is the geometry's patch operators, which
the layers read in their compact form (:mod:`zernet.operators.pairs`: vertex pairs with ``k`` values each,
float16 by default, fitted from the cache file's sample geometry when it is read; the backward reads the same
pairs; about 20 MB for a FAUST-size surface, against 170 MB
for the float32 CSR matrix and transpose of cache format 4). The levels say where those prepared operators
live between steps:

``device``
    Every training and validation record is read once, when the run starts, and its operators are
    prepared on the run's device and kept there: a step does no file I/O, no scipy and no host-to-device
    copy of operators (only its features and targets, a few hundred kB, are copied).
``host``
    The same, prepared in host memory (page-locked on CUDA); for each step the read-ahead thread copies the
    next step's operators to the device (asynchronously, on a copy stream of its own) while the current step
    computes. On a CPU the host is the device: ``host`` and ``device`` both hold the prepared operators in
    memory and copy nothing. ``auto`` takes at most :data:`MEMORY_FRACTION` of the available memory, so a
    program started beside the run still finds room (FAUST's 80 scans hold 1.7 GB).
``stream``
    Records are read from the cache for every step on the read-ahead thread, as data sets too large to
    hold need (reading a cache file fits its patches again: about 0.4 s for a FAUST-size surface at two
    threads, while the current step computes).
``auto``
    On CUDA ``device`` when the prepared operators of the training and validation shapes fit in
    :data:`MEMORY_FRACTION` of the GPU's free memory, else ``host`` when they fit in that fraction of the
    available RAM, else ``stream``; on a CPU ``host`` or ``stream`` by the same rule. The size is that of the first training record's prepared
    operators times the number of shapes held.

Every level computes the same numbers: the same records, prepared by the same code; only where the
prepared tensors are kept differs (``tests/training/test_residency.py``). Test shapes are always streamed:
they are read once, after training. Direction-preserving models build their harmonic matrices in their
first product and keep them on the held record (``device``); under ``host`` on CUDA and under ``stream``
they are rebuilt for every step.
"""

from __future__ import annotations

import dataclasses
import os
import time
from collections.abc import Sequence

import torch
from tqdm.auto import tqdm

from zernet.inference.batch import with_directional
from zernet.training.config import RESIDENCY_LEVELS

__all__ = [
    "RESIDENCY_LEVELS",
    "MEMORY_FRACTION",
    "ShapeStore",
    "choose_residency",
    "available_memory",
    "prepared_bytes",
]

#: The share of the free device memory (or available RAM) that ``auto`` lets the held operators take; the
#: rest is for activations, the optimiser and everything else.
MEMORY_FRACTION = 0.5


def available_memory(device: torch.device) -> int:
    """Bytes free for new tensors on ``device``: CUDA's free memory, or the host's available RAM."""
    if device.type == "cuda":
        return int(torch.cuda.mem_get_info(device)[0])
    try:
        with open("/proc/meminfo") as handle:
            for line in handle:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return int(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))


def prepared_bytes(record) -> int:
    """Bytes of the prepared tensors a record's patch operators hold (:meth:`PatchOperator.to`)."""
    return sum(int(getattr(op, "prepared_nbytes", 0)) for op in record.geometry.operators)


def choose_residency(
    level: str, shape_bytes: int, n_shapes: int, device: torch.device, free: dict[str, int] | None = None
) -> tuple[str, str]:
    """``(level, reason)``: ``level`` itself unless it is ``auto`` (module docstring). ``free`` (bytes per
    ``"device"`` / ``"host"``) stands in for :func:`available_memory`."""
    if level not in RESIDENCY_LEVELS:
        raise ValueError(f"data.residency must be one of {', '.join(RESIDENCY_LEVELS)}, got {level!r}")
    total = shape_bytes * n_shapes
    size = f"{n_shapes} shapes x {shape_bytes / 1e6:.0f} MB = {total / 1e9:.2f} GB of prepared operators"
    if level != "auto":
        return level, f"data.residency {level}; {size}"
    free = free or {}
    places = (("device", device), ("host", torch.device("cpu"))) if device.type == "cuda" else (("host", device),)
    for name, place in places:
        room = free[name] if name in free else available_memory(place)
        if total <= MEMORY_FRACTION * room:
            where = str(place) if name == "device" else "host memory"
            return name, f"auto: {size} fit in {MEMORY_FRACTION:.0%} of the {room / 1e9:.1f} GB free in {where}"
    return "stream", f"auto: {size} do not fit in {MEMORY_FRACTION:.0%} of the free memory: read for every step"


class ShapeStore:
    """A run's training and validation shapes at one residency level: ``store[i]`` is the record a step
    reads, its geometry prepared on the run's device (``stream``: read from the data set for this step).

    Args:
        dataset: the :class:`~zernet.data.ShapeDataset`.
        indices: the shapes to hold (training and validation); others are always read from ``dataset``.
        level: one of :data:`RESIDENCY_LEVELS`.
        device: the run's device.
        directional_order, basis_orders: what the model reads (:func:`zernet.inference.batch.model_directional_order`,
            :func:`~zernet.inference.batch.model_basis_orders`): the operators are prepared for it.
        free: bytes free per place, for tests (see :func:`choose_residency`).

    Attributes:
        level: the level chosen (never ``auto``); ``reason``: why, with the sizes (for the log).
        held_bytes: bytes of the prepared operators held; ``seconds``: time taken to read and prepare them.
    """

    def __init__(
        self,
        dataset,
        indices: Sequence[int],
        level: str,
        device: torch.device,
        directional_order: int | None = None,
        basis_orders: Sequence[tuple] = (),
        progress: bool = False,
        free: dict[str, int] | None = None,
    ):
        self.dataset = dataset
        self.device = torch.device(device)
        self.directional_order = directional_order
        self.basis_orders = tuple(basis_orders)
        indices = list(dict.fromkeys(int(i) for i in indices))
        started = time.perf_counter()
        first = self._prepared(dataset[indices[0]], torch.device("cpu")) if indices else None
        self.level, self.reason = choose_residency(
            level, prepared_bytes(first) if first else 0, len(indices), self.device, free
        )
        self._held: dict[int, object] = {}
        self._copy_stream = None
        if self.level != "stream":
            place = self.device if self.level == "device" else torch.device("cpu")
            for i in tqdm(
                indices, desc=f"holding shapes ({self.level})", unit="shape", leave=False, disable=not progress
            ):
                record = first if i == indices[0] else dataset[i]
                record = self._prepared(record, place)
                if self.level == "host" and self.device.type == "cuda":
                    record.geometry.pin_memory()
                self._held[i] = record
            if self.level == "host" and self.device.type == "cuda":
                self._copy_stream = torch.cuda.Stream(self.device)
        self.held_bytes = sum(prepared_bytes(record) for record in self._held.values())
        self.seconds = time.perf_counter() - started

    def _prepared(self, record, place: torch.device):
        """``record`` with its directional operators built and its geometry prepared on ``place``."""
        with_directional(record, self.directional_order)
        record.geometry = record.geometry.to(place, self.basis_orders)
        return record

    def __getitem__(self, index: int):
        record = self._held.get(int(index))
        if record is None:  # stream, or a shape not held (read as it comes)
            return self.dataset[index]
        if self._copy_stream is None:  # held where the step runs (on a CPU, host memory is the device)
            return record
        # host on CUDA: this step's copy, made on the copy stream while the default stream computes
        with torch.cuda.stream(self._copy_stream):
            geometry = record.geometry.copy_to(self.device, non_blocking=True)
        self._copy_stream.synchronize()  # only this (read-ahead) thread waits
        default = torch.cuda.default_stream(self.device)
        for tensor in _geometry_tensors(geometry):
            tensor.record_stream(default)  # made on the copy stream, freed after the step's use on the default
        return dataclasses.replace(record, geometry=geometry)

    def describe(self) -> str:
        """One line for the banner and ``train.log``."""
        held = (
            (
                f"; holding {len(self._held)} shapes, {self.held_bytes / 1e9:.2f} GB, read and prepared in "
                f"{self.seconds:.1f} s"
            )
            if self._held
            else ""
        )
        return f"data residency: {self.level} ({self.reason}{held})"


def _geometry_tensors(geometry):
    """The tensors a geometry's step copy consists of (for ``record_stream``)."""
    for op in geometry.operators:
        for part in getattr(op, "_parts", None) or [op]:
            for tensors in getattr(part, "_devices", {}).values():  # a patch operator's pairs as tensors
                yield from tensors.values()
    for op in geometry.directional:
        for matrices in getattr(op, "_torch", {}).values():
            for m in matrices:
                if m is not None:  # a transpose not built (forward-only use)
                    yield from (m.crow_indices(), m.col_indices(), m.values())
    for tensor in (geometry.edge_index, geometry.batch):
        if tensor is not None:
            yield tensor
