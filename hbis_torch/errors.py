"""The one exception type that means "the input was wrong" (the CLI turns it into exit code 2)."""


class HbisInputError(ValueError):
    """Bad input: wrong shape, non-finite value, out-of-range parameter, corrupt file, ...

    The message says what was wrong in one line; the CLI prints it and exits with status 2.
    """
