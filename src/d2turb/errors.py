class D2TurbError(ValueError):
    """A user-facing error: bad input, impossible parameters, missing weights.

    A ``ValueError``, so callers that already catch bad values catch it too. The CLI prints its message as
    one line (``error: ...``) and exits with status 2; library code raises it ``from`` the underlying
    exception so the cause stays in the traceback.
    """
