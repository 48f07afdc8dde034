"""Training and evaluation: one loop for every model, data set and task.

- :func:`train` ``(config, run_dir, resume=False, progress=True) -> metrics`` (:mod:`~zernet.training.loop`);
- :func:`evaluate` ``(run_dir or checkpoint, dataset=None, split="test") -> metrics``
  (:mod:`~zernet.training.evaluation`);
- the run configuration: :func:`load_config`, :func:`apply_overrides`, :func:`parse_config` ->
  :class:`RunConfig` (:mod:`~zernet.training.config`).
"""

from zernet.training.build import build_dataset, check_model_config, load_data
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
from zernet.training.run_dir import write_json
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
    "train",
    "evaluate",
    "summary_line",
    "write_json",
    "epoch_order",
    "epoch_learning_rate",
    "step_groups",
    "check_model_config",
    "RESUME_CHANGEABLE",
]
