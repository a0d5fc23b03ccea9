"""The one exception type that reaches the user as a single line and exit status 2."""


class SeamapError(Exception):
    """Bad input from outside: a missing or malformed file, a wrong key, an unreachable device.

    The message names the thing and the reason in one line; the CLI prints it and exits 2.
    """
