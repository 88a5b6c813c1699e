"""How a sandboxed brain host says why it stopped: one exit code per kind of wall it hit.

Inside the sandbox (``orchestrator.stack.sandbox``) the kernel refuses what a brain may not do, and the refusal comes
back to the brain's own code as an exception: ``MemoryError`` past its address space, ``EAGAIN`` from ``fork`` past
its processes, ``EFBIG`` past its file size, ``EROFS``/``EACCES`` for a write outside its scratch, a refused or
unreachable connection for the network it does not have. A host started with ``sandboxed: true`` exits with the code
of that wall instead of a generic traceback, so that the launcher types the failure from the code (never from the
log's words). Standard library only: the brain host imports it.
"""

from __future__ import annotations

import errno
from enum import IntEnum


class SandboxExit(IntEnum):
    """Exit codes of a sandboxed brain host that hit a wall (chosen clear of Python's 1, 2 and 128+signal)."""

    MEMORY = 90  # MemoryError: the address-space limit
    PROCESSES = 91  # fork/clone refused (EAGAIN): the process limit
    FILE_SIZE = 92  # EFBIG: the file-size limit
    REFUSED = 93  # the sandbox refused an operation: a write outside the scratch, the network

    @property
    def is_limit(self) -> bool:
        """A resource limit (else a refused operation: a sandbox violation)."""
        return self is not SandboxExit.REFUSED


# errno of an OSError that, inside the sandbox, can only mean the brain reached for what it may not touch: a
# read-only or hidden file system, or a network that is not there (the only interface is an empty loopback).
_REFUSED = {
    errno.EROFS,
    errno.EACCES,
    errno.EPERM,
    errno.ENETUNREACH,
    errno.EHOSTUNREACH,
    errno.ECONNREFUSED,
    errno.EADDRNOTAVAIL,
}


def exit_for(error: BaseException) -> SandboxExit | None:
    """The wall ``error`` means inside the sandbox, or None for an ordinary error of the brain's (a crash)."""
    if isinstance(error, MemoryError):
        return SandboxExit.MEMORY
    if isinstance(error, OSError):
        if error.errno == errno.EAGAIN:
            return SandboxExit.PROCESSES
        if error.errno == errno.EFBIG:
            return SandboxExit.FILE_SIZE
        if error.errno in _REFUSED:
            return SandboxExit.REFUSED
    return None
