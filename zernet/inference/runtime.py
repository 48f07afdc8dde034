"""Where and how a model runs: the device, the autocast precision, the CPU allocator and denormals."""

from __future__ import annotations

import contextlib
import ctypes
import os

import torch

from zernet.inference.errors import ConfigError

__all__ = ["resolve_device", "precision_autocast", "keep_freed_memory", "flush_denormals"]


def resolve_device(name: str) -> torch.device:
    """``auto`` picks CUDA when available; anything else is handed to ``torch.device`` and checked."""
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    try:
        device = torch.device(name)
    except RuntimeError:
        raise ConfigError(f"train.device: {name!r} is not a device (use auto, cpu, cuda or cuda:N)") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"train.device is {name!r} but CUDA is not available on this machine")
    if device.type == "cuda" and device.index is None:  # as tensors report it: cuda is cuda:0
        device = torch.device("cuda", torch.cuda.current_device())
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
    2-core machine (benchmarks/speed/bench_layers.py). Disabling ``mmap`` for large blocks and the heap trim keeps
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


@contextlib.contextmanager
def flush_denormals():
    """Within the block, the CPU reads and writes denormal floats (below ~1.2e-38 in float32) as zero.

    Late in a correspondence run the softmax gives most of the 6,890 classes probabilities of ``e^-90`` and
    less, so the output layer's gradient fills with denormals, and x86 CPUs compute on them through a slow
    path: a matrix product with denormal inputs took 160x its normal time on the 2-core development machine,
    and training steps with a converged model's weights 3.1x theirs (``benchmarks/speed/bench_denormals.py``).
    Training runs its epochs inside this block. Only there: the flag is process-wide for the calling thread,
    and some compiled geometry code (the shape features) crashes under it, so it is switched off again on
    leaving. The flag is per thread; BLAS threads started before the block keep theirs, so at several threads
    part of the gain remains. Does nothing where the CPU has no such mode.
    """
    supported = torch.set_flush_denormal(True)
    try:
        yield supported
    finally:
        if supported:
            torch.set_flush_denormal(False)
