"""The one error type a user can cause (bad path, format, dims, values, model file)."""


class ApmgsrnError(Exception):
    """A problem with the user's input: the message names the file and the fix.

    The command line prints it as one line, ``error: <message>``, and exits with code 2.
    Internal bugs raise ordinary Python exceptions instead.
    """
