"""The project's error hierarchy.

Every error a user can cause is a :class:`RigError` whose message is one line that names the input
and the fix; the CLI prints it and exits with code 2, never with a traceback.
"""


class RigError(Exception):
    """Root of all errors raised deliberately by the rig. The message stays one line: line breaks
    that come in with user input (a YAML key, a CSV cell) are shown escaped."""

    def __init__(self, *args: object) -> None:
        super().__init__(
            *(
                a.replace("\r", "\\r").replace("\n", "\\n") if isinstance(a, str) else a
                for a in args
            )
        )


class UserInputError(RigError):
    """Bad input from the user (file, column, option): fixable by changing the input."""


class CalibrationError(RigError):
    """The data cannot support the requested calibration (singular, rank deficient, diverged)."""


class StoreWriteError(RigError):
    """The run's database cannot be written (disk full, I/O error); what was committed stays."""


class RunAborted(RigError):  # noqa: N818 - an outcome, not a fault
    """The operator (Ctrl-C, SIGTERM, a declined prompt) stopped the run."""


class StoredResultError(RigError):
    """A stored step result cannot be read as its kind's record: a key is missing or holds a
    value of the wrong type (a run folder written by hand, or damaged)."""
