"""The one project exception type.

Anything the user can cause (unknown task, invalid parameter, missing or corrupt
artifact, solver failure) raises :class:`SdpError`; the CLI layer turns it into a
single line on stderr and exit code 1.
"""


class SdpError(Exception):
    """A user-facing error with a one-line message."""
