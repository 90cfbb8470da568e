"""The one exception type the CLI turns into a single clear error line and exit code 1."""


class SekdError(Exception):
    """A user-facing error: the message names the file, what is wrong and what to do."""


class Interrupted(SekdError):
    """Ctrl-C or SIGTERM stopped a command after it saved its work; the message says how to resume.

    Loops that survive one failing item (a benchmark's methods) must let this one through.
    """
