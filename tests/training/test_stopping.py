"""Early stopping and what a resume may reopen: a run stopped by a limit continues when that limit is raised."""

from zernet.training.stopping import BUDGET, Monitor, initial_state, record_epoch, reopen_if_limits_raised

ACCURACY = Monitor.for_task("classification")


def _run(accuracies, epochs, patience):
    state = initial_state()
    for epoch, accuracy in enumerate(accuracies, start=1):
        record_epoch(
            state, {"epoch": epoch, "seconds": 1.0, "val_accuracy": accuracy}, ACCURACY, epochs, patience, True
        )
        if state["stopped"]:
            break
    return state


def test_training_stops_after_patience_epochs_without_a_better_model_and_keeps_the_best():
    state = _run([0.5, 0.7, 0.6, 0.65, 0.69, 0.9], epochs=10, patience=3)
    assert state["stopped"] and state["epoch"] == 5 and state["best_epoch"] == 2 and state["bad_epochs"] == 3
    assert state["stop_reason"].startswith("early stopping")
    assert _run([0.5, 0.7], epochs=2, patience=3)["stop_reason"] == BUDGET


def test_a_resume_reopens_a_run_only_when_the_limit_that_stopped_it_was_raised():
    early = _run([0.5, 0.7, 0.6, 0.65, 0.69], epochs=10, patience=3)
    for patience, reopened in ((3, False), (2, False), (4, True), (None, True)):
        state = {**early}
        reopen_if_limits_raised(state, 10, patience)
        assert state["stopped"] is not reopened, patience
        assert (state["stop_reason"] == "") is reopened
    state = {**early}
    reopen_if_limits_raised(state, 5, None)  # no epochs left: nothing to reopen
    assert state["stopped"]
    budget = _run([0.5, 0.7], epochs=2, patience=3)
    for epochs, reopened in ((2, False), (4, True)):
        state = {**budget}
        reopen_if_limits_raised(state, epochs, 3)
        assert state["stopped"] is not reopened
    # A reopened run goes on counting from where it was: one more epoch without a better model, patience 4.
    state = {**early}
    reopen_if_limits_raised(state, 10, 4)
    record_epoch(state, {"epoch": 6, "seconds": 1.0, "val_accuracy": 0.6}, ACCURACY, 10, 4, True)
    assert state["stopped"] and state["bad_epochs"] == 4 and state["best_epoch"] == 2
