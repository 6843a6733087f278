"""The one base class of the errors fmusa reports to its user.

The ``fmusa`` command prints a :class:`FmusaError` as one line, ``fmusa <command>: message``, and exits
with its ``exit_code``; any other exception is a bug in fmusa (or in a library under it) and keeps its
traceback, so that it is not mistaken for a mistake in the input. Each subclass keeps the builtin base it
had before (``StudyError(FmusaError, ValueError)``…), so ``except ValueError`` in older code still works.

Base layer: this module imports nothing from fmusa (and only the standard library), so every layer and
the command line's top can import it cheaply.
"""
from __future__ import annotations

__all__ = ["FmusaError", "UsageError"]


class FmusaError(Exception):
    """An error in the user's input (study file, FMU, data) whose message names the input and the fix.

    ``exit_code`` is the status the ``fmusa`` command exits with: 2 for input that is wrong (the default),
    1 for input that could not be used (an FMU that fails to build or to run, a file that is missing).

    Fix: read the one line the ``fmusa`` command printed: it names the input (a file and line, an option, a
    variable) and what to change. Any other exception, printed with a traceback, is a bug in fmusa: report it
    with the traceback.
    """

    exit_code: int = 2


class UsageError(FmusaError, ValueError):
    """An argument out of range: a command-line option or a keyword argument of the Python API (e.g. a
    non-positive ``stop_time``, an unknown ``--causality``).

    Fix: change the option or argument the message names to a value in the range it gives (``fmusa <command>
    --help`` lists the options).
    """
