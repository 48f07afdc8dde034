"""The error of a configuration that cannot be used: :class:`ConfigError`.

It is raised where a value is read, and a run's values are read at two layers: a stored model's spec and
device here in :mod:`zernet.inference` (rebuilding a model, choosing where it runs), the rest of a run's
configuration in :mod:`zernet.training.config`, which raises the same class.
"""

from __future__ import annotations

__all__ = ["ConfigError"]


class ConfigError(ValueError):
    """A configuration that cannot be used; the message names the offending key."""
