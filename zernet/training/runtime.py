"""Where and how a model runs: the device, the autocast precision, the CPU allocator and denormals."""

from __future__ import annotations

import ctypes
import os

import torch

from zernet.training.config import ConfigError

__all__ = ["resolve_device", "precision_autocast", "keep_freed_memory", "flush_denormals"]


def resolve_device(name: str) -> torch.device:
    """``auto`` picks CUDA when available; anything else is handed to ``torch.device`` and checked."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError:
        raise ConfigError(f"train.device: {name!r} is not a device (use auto, cpu, cuda or cuda:N)") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"train.device is {name!r} but CUDA is not available on this machine")
    return device


def precision_autocast(precision: str, device_type: str):
    """The ``torch.autocast`` context of ``train.precision`` for a forward pass on ``device_type``.

    ``"bfloat16"``: linear layers run in bfloat16 (convolutions stay float32, see
    :func:`zernet.nn.conv.float32_forward`); ``"float32"``: a disabled context. Compute the loss on
    ``output.float()`` outside it.
    """
    return torch.autocast(device_type, dtype=torch.bfloat16, enabled=precision == "bfloat16")


def keep_freed_memory() -> bool:
    """Make glibc keep freed CPU memory for reuse instead of handing it back to the kernel.

    A training step on a FAUST-sized mesh allocates and frees tensors of hundreds of MB (the 6,890 x 6,890
    logits and their gradient). glibc serves such blocks with ``mmap`` and returns them with ``munmap``, so
    every step page-faults the same memory in again: about a quarter of a correspondence step on this
    2-core machine (benchmarks/bench_layers.py). Disabling ``mmap`` for large blocks and the heap trim keeps
    the peak footprint unchanged and the pages resident. Called by the ``zernet`` command and the
    benchmarks; a library user may call it too. Returns False where it does not apply (not glibc) and
    leaves the allocator alone when the user set ``MALLOC_MMAP_MAX_`` or ``MALLOC_TRIM_THRESHOLD_``.
    """
    if any(name in os.environ for name in ("MALLOC_MMAP_MAX_", "MALLOC_TRIM_THRESHOLD_")):
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    m_trim_threshold, m_mmap_max = -1, -4  # from glibc's malloc.h
    return bool(mallopt(m_mmap_max, 0)) and bool(mallopt(m_trim_threshold, 2**30))


def flush_denormals() -> bool:
    """Make the CPU treat denormal floats (below ~1.2e-38 in float32) as zero, for the whole process.

    Late in a correspondence run the softmax gives most of the 6,890 classes probabilities of ``e^-90`` and
    less, so the output layer's gradient fills with denormals, and x86 CPUs compute on them through a slow
    microcode path: a matrix product with denormal inputs took 160x its normal time on the 2-core
    development machine, and FAUST-sized epochs 8-11 took 1.6-2.1x the first ones. Zero is as good an
    answer for such values. Called at the start of every training run; returns False where the CPU has no
    such mode (the setting is then unchanged).

    The mode is a per-thread CPU flag that new threads take from the thread starting them, and the BLAS
    library keeps its threads once started: call this before the first matrix product of the process (the
    ``zernet`` command and the benchmarks do, first thing) so that every thread has it. Training calls it
    again for its own thread.
    """
    return bool(torch.set_flush_denormal(True))
