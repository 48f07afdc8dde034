"""Running a stored model on a prepared surface: what prediction needs, and training and matching read.

- :mod:`~zernet.inference.spec`: a model rebuilt from its spec (:func:`build_model_from_spec`);
- :mod:`~zernet.inference.model_file`: the one format of model files and its reader (:func:`read_model_file`);
- :mod:`~zernet.inference.batch`: one forward pass's input (:class:`~zernet.inference.batch.Batch`);
- :mod:`~zernet.inference.targets`: how inputs and targets are standardised for the network;
- :mod:`~zernet.inference.runtime`: the device and precision a model runs at;
- :func:`predict` ``(checkpoint, surface) -> per-vertex predictions`` (:mod:`~zernet.inference.predict`),
  refined by :mod:`~zernet.inference.refine` (rings) and :mod:`~zernet.inference.spectral_refine` (global),
  over the template graph of :mod:`~zernet.inference.template_graph`.

Nothing here imports :mod:`zernet.training` or :mod:`zernet.matching`: both build on it.
"""

from zernet.inference.model_file import checkpoint_path, load_checkpoint, read_model_file
from zernet.inference.predict import model_from_checkpoint, predict, predict_record
from zernet.inference.runtime import flush_denormals, keep_freed_memory, precision_autocast, resolve_device
from zernet.inference.spec import build_model_from_spec, model_spec

__all__ = [
    "read_model_file",
    "load_checkpoint",
    "checkpoint_path",
    "build_model_from_spec",
    "model_spec",
    "predict",
    "predict_record",
    "model_from_checkpoint",
    "resolve_device",
    "precision_autocast",
    "keep_freed_memory",
    "flush_denormals",
]
