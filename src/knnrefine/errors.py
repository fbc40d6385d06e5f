"""The project's exception types."""


class KnnRefineError(Exception):
    """Base class of every error knnrefine raises on purpose."""


class InputError(KnnRefineError, ValueError):
    """The input cannot be refined as given; the message says what was wrong and what to do."""


class BudgetError(KnnRefineError, RuntimeError):
    """A run hit ``max_vertices`` or ``time_limit`` before it finished.

    ``progress`` holds how far it got (vertices, moves, seconds)."""

    def __init__(self, message, progress):
        super().__init__(message)
        self.progress = progress


class EngineError(KnnRefineError, RuntimeError):
    """A broken internal invariant: a bug in knnrefine. Please report it with the input."""


class FloorWarning(UserWarning):
    """Most of the input lies where d_{P,k} is below the resolution floor ``min_size``, where
    the guarantee is not claimed (the default floor is relative to the box, not the data)."""


class LargeRunWarning(UserWarning):
    """A run is expected to need a lot of memory (estimated before it starts)."""


class WrapWarning(UserWarning):
    """Points span more than a period of the box along a periodic axis: wrapping them into the
    box lays points from different periods over each other (a box smaller than the data?)."""
