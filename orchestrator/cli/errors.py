"""What every ``drivebench`` subcommand shares: its error types and one table of exit codes.

A subcommand raises :class:`UsageError` (defined in ``protocol.deploy.runtime``, so that library code can raise it too)
for a mistake the user can fix by changing the command line or a file it names (exit 2), and
:class:`CommandFailed` when it could not do its job for another reason (exit 1). ``main`` prints either as one
line on stderr; nothing a user does wrong ends in a traceback.
"""

from __future__ import annotations

from pathlib import Path

from protocol.deploy.runtime import UsageError, UserError

__all__ = [
    "EXIT_FAILED",
    "EXIT_INTERRUPTED",
    "EXIT_OK",
    "EXIT_SOME_FAILED",
    "EXIT_USAGE",
    "CommandFailed",
    "UsageError",
    "UserError",
    "require_file",
]

EXIT_OK = 0  # it did what was asked (an episode that crashed the car is still a result)
EXIT_FAILED = 1  # the stack could not run, or the command could not do its job (one line says why)
EXIT_USAGE = 2  # a usage mistake: a bad option, file, name or value, or a missing extra (one line names it)
EXIT_SOME_FAILED = 3  # a matrix ran, but the stack failed some of its episodes (the report lists them)
EXIT_INTERRUPTED = 130  # Ctrl-C: what was finished is kept (the message says how to resume)


class CommandFailed(Exception):
    """The command could not do its job (nothing to view, a swap the stack refused): one line, exit
    :data:`EXIT_FAILED`. The message is printed as it is, after ``drivebench: ``."""


def require_file(path: Path, *, option: str) -> None:
    """:class:`UsageError` unless ``path`` is a regular file, saying what is there instead: a folder or a device
    is not "no such file", and a user who gave a run folder is told the file inside it."""
    if path.is_file():
        return
    if path.is_dir():
        inside = path / "config.yaml"
        hint = f" (did you mean {inside}?)" if option == "--config" and inside.is_file() else ""
        raise UsageError(f"{option} {path}: a folder, not a file{hint}")
    if path.exists():
        if path.is_char_device() or path.is_block_device():
            kind = "a device"
        else:
            kind = "a fifo" if path.is_fifo() else "a socket" if path.is_socket() else "something else"
        raise UsageError(f"{option} {path}: {kind}, not a file")
    raise UsageError(f"{option} {path}: no such file")
