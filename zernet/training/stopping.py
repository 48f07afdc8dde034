"""Model selection and early stopping: which epoch's model is kept, and when training stops.

The loop state is a plain dictionary stored in every checkpoint (:func:`initial_state`): the epoch, the
best validation metric and its epoch, the epochs since it improved, whether and why training stopped,
the seconds spent and one history entry per epoch.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["Monitor", "initial_state", "reopen_if_limits_raised", "record_epoch", "BUDGET"]

#: stop_reason of a run that used all of train.epochs.
BUDGET = "epoch budget"


@dataclass(frozen=True)
class Monitor:
    """The validation metric the model is selected on."""

    name: str  # val_accuracy | val_loss
    higher_is_better: bool

    @classmethod
    def for_task(cls, task: str) -> Monitor:
        classification = task == "classification"
        return cls("val_accuracy" if classification else "val_loss", classification)

    def better(self, value: float, best: float | None) -> bool:
        if best is None:
            return True
        return value > best if self.higher_is_better else value < best


def initial_state() -> dict:
    return {
        "epoch": 0,
        "best_metric": None,
        "best_epoch": 0,
        "bad_epochs": 0,
        "stopped": False,
        "stop_reason": "",
        "train_seconds": 0.0,
        "history": [],
    }


def reopen_if_limits_raised(state: dict, epochs: int, patience: int | None) -> None:
    """A stopped run continues on resume when what stopped it was raised: the epoch budget, or the patience
    of early stopping (None: no early stopping) beyond the epochs it has gone without a better model."""
    if not state["stopped"] or state["epoch"] >= epochs:
        return
    if state["stop_reason"] == BUDGET or (patience is None or state["bad_epochs"] < patience):
        state["stopped"], state["stop_reason"] = False, ""


def record_epoch(
    state: dict, entry: dict, monitor: Monitor, epochs: int, patience: int | None, has_validation: bool
) -> bool:
    """Add the finished epoch's ``entry`` to ``state``; returns whether its model is the best so far.

    Without validation the latest model is the model. Training stops after ``patience`` epochs without a
    better monitored metric (with validation), or at the last of ``epochs``.
    """
    epoch = entry["epoch"]
    state["train_seconds"] += entry["seconds"]
    state["history"].append(entry)
    state["epoch"] = epoch
    current = entry.get(monitor.name)
    improved = current is None or monitor.better(current, state["best_metric"])
    if improved:
        state["best_metric"] = current
        state["best_epoch"] = epoch
        state["bad_epochs"] = 0
    else:
        state["bad_epochs"] += 1
    if has_validation and patience is not None and state["bad_epochs"] >= patience:
        state["stopped"] = True
        state["stop_reason"] = f"early stopping (no better {monitor.name} for {patience} epochs)"
    elif epoch >= epochs:
        state["stopped"], state["stop_reason"] = True, BUDGET
    return improved
