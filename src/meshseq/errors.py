"""The one exception type for a user's mistake (bad file, bad option).

The command line prints ``meshseq: error: <message>`` for it, with no traceback, and exits 2.
Messages are one line and name the file, frame or option that is wrong.
"""


class MeshseqError(Exception):
    """A user-facing error: bad input data, bad option, or an output that would be overwritten."""


class MeshseqWarning(UserWarning):
    """Something in the user's data was repaired or looks suspicious (the CLI prints it on one line)."""
