"""Training, evaluation and prediction: one loop for every model, data set and task.

- :func:`train` ``(config, run_dir, resume=False, progress=True) -> metrics`` (:mod:`~zernet.training.loop`);
- :func:`evaluate` ``(run_dir or checkpoint, dataset=None, split="test") -> metrics``
  (:mod:`~zernet.training.evaluation`);
- :func:`predict` ``(checkpoint, surface) -> per-vertex predictions`` (:mod:`~zernet.training.predict`);
- the run configuration: :func:`load_config`, :func:`apply_overrides`, :func:`parse_config` ->
  :class:`RunConfig` (:mod:`~zernet.training.config`).
"""

from zernet.training.build import build_dataset, build_model_from_spec, check_model_config, load_data, model_spec
from zernet.training.checkpoint import CHECKPOINT_FORMAT, checkpoint_path, load_checkpoint
from zernet.training.config import (
    DEFAULT_CONFIG,
    ConfigError,
    RunConfig,
    apply_overrides,
    load_config,
    parse_config,
    read_config,
    resolve_config,
)
from zernet.training.evaluation import evaluate, summary_line
from zernet.training.loop import RESUME_CHANGEABLE, train
from zernet.training.predict import predict
from zernet.training.run_dir import write_json
from zernet.training.runtime import flush_denormals, keep_freed_memory, precision_autocast, resolve_device
from zernet.training.schedule import epoch_learning_rate, epoch_order, step_groups

__all__ = [
    "ConfigError",
    "DEFAULT_CONFIG",
    "RunConfig",
    "load_config",
    "apply_overrides",
    "parse_config",
    "read_config",
    "resolve_config",
    "build_dataset",
    "load_data",
    "model_spec",
    "build_model_from_spec",
    "train",
    "evaluate",
    "predict",
    "summary_line",
    "write_json",
    "load_checkpoint",
    "checkpoint_path",
    "CHECKPOINT_FORMAT",
    "epoch_order",
    "epoch_learning_rate",
    "step_groups",
    "precision_autocast",
    "keep_freed_memory",
    "flush_denormals",
    "resolve_device",
    "check_model_config",
    "RESUME_CHANGEABLE",
]
