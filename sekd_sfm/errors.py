"""The one exception type the CLI turns into a single clear error line and exit code 1."""


class SekdError(Exception):
    """A user-facing error: the message names the file, what is wrong and what to do."""
