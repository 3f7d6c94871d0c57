"""The one error type a user can cause (bad path, format, dims, values, model file)."""

from __future__ import annotations

from collections.abc import Iterable


class ApmgsrnError(Exception):
    """A problem with the user's input: the message names the file and the fix.

    The command line prints it as one line, ``error: <message>``, and exits with code 2.
    Internal bugs raise ordinary Python exceptions instead.

    Advice names the library's own arguments as ``name=VALUE`` (``pass fill_nonfinite=VALUE``), the words a
    Python caller types; ``arguments`` lists those names so that a front end can say them its own way (the
    command line writes ``--fill-nonfinite VALUE``).

    Args:
        message: one line naming the file or value and the fix.
        arguments: the library arguments the message names as ``name=``.
    """

    def __init__(self, message: str = "", *, arguments: Iterable[str] = ()) -> None:
        super().__init__(message)
        self.arguments = tuple(arguments)


class InvalidArgument(ApmgsrnError, ValueError):
    """An argument value outside what it may be (``batch_size=-5: must be an integer from 1 to ...``).

    Also a :class:`ValueError`, which is what a config given a bad value raises in Python.
    """


class ApmgsrnNote(UserWarning):
    """A note about the user's input that does not stop the work (a model file written before checksums).

    Issued with :func:`warnings.warn`; the command line prints it as one line, ``note: <message>``.
    """
