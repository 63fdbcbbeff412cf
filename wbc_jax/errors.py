"""User-facing error types.

Every error a user can cause (bad spec file, CLI argument, factor value, input table)
is raised as a subclass of :class:`WbcJaxError`; the CLI prints its message on one line
and exits with code 2 instead of showing a traceback.
"""


class WbcJaxError(Exception):
    """Base class of errors caused by user input."""


class SceneError(WbcJaxError):
    """A scene file is missing or does not contain what wbc_jax needs."""


class FactorError(WbcJaxError):
    """A factor value (object mass, size, friction, ...) is outside its physical range."""


class SpecError(WbcJaxError):
    """A sweep/spec file has an unknown key, a wrong type or an out-of-range value."""


class InputError(WbcJaxError):
    """An input table (e.g. a results CSV) is malformed."""


class OutputError(WbcJaxError):
    """An output folder cannot be used: not empty and not this command's, an input inside it, not writable, ..."""


class CheckpointError(WbcJaxError):
    """A campaign checkpoint is damaged or belongs to another run (spec, gains, versions, backend)."""


class LimitError(WbcJaxError):
    """A request is beyond what the machine can do (memory, time) or beyond a bounded argument's range."""


class ReportError(WbcJaxError):
    """The statistics of a finished campaign failed; its results.csv and manifest.json were kept."""


class UsageError(WbcJaxError):
    """A command line argparse cannot read (unknown flag, wrong type); ``prog``: the command, e.g. ``wbc-jax demo``."""

    def __init__(self, message: str, prog: str = "wbc-jax"):
        super().__init__(message)
        self.prog = prog
