"""Exceptions raised by recon3d.

Every error a user can cause by their input derives from :class:`Recon3dError` and
also from the builtin that describes it, so callers can catch either. The CLI turns a
``Recon3dError`` into one line on stderr and exit status 1.
"""


class Recon3dError(Exception):
    """Root of all recon3d errors."""


class InputError(Recon3dError, ValueError):
    """An input file or value is missing, unreadable or unusable.

    The message names the file (when there is one) and the problem.
    """


class CRSError(InputError):
    """A coordinate reference system is missing, unknown or inconsistent."""


class MemoryLimitError(Recon3dError, MemoryError):
    """The work asked for would need more memory than is available (or than ``--max-memory``
    allows); the message gives both figures and the setting to change. Raised before
    allocating, so nothing is half done."""


class DependencyError(Recon3dError, ImportError):
    """An optional dependency needed for the requested operation is not installed."""
