class D2TurbError(Exception):
    """A user-facing error: bad input, impossible parameters, missing weights.

    The CLI prints its message as one line (``error: ...``) and exits with status 2.
    """
