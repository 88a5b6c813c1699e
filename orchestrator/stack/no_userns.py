"""The last step into a sandbox: run a command that can make no user namespace.

    python -P -m orchestrator.stack.no_userns COMMAND [ARG ...]

Why: the kernel lets any process make a user namespace (``unshare -U``). Inside one, a sandboxed brain is root with
every capability over the namespaces it makes, which opens kernel code that an unprivileged process never reaches
(netfilter tables, mounts of some file systems): the usual first step of a kernel exploit, and a sandbox that shares
the kernel should not hand it out. As root, bubblewrap runs without a user namespace of its own (the process limit
needs the sandbox's uid: ``orchestrator.stack.sandbox``), so its ``--disable-userns`` does not apply.

So this installs a seccomp filter, then replaces itself with COMMAND, which inherits the filter with everything it
starts (a filter can never be removed). The filter refuses ``unshare`` and ``clone`` with ``CLONE_NEWUSER`` (EPERM);
refuses ``clone3`` with ENOSYS, since its flags lie behind a pointer a filter cannot read (glibc then falls back to
``clone``, as it does on kernels before 5.3); and kills a process that makes another architecture's system calls
(i386 on x86-64, x32) to go around it. Standard library only: it runs before anything else inside.
"""

from __future__ import annotations

import ctypes
import os
import platform
import struct
import sys
from dataclasses import dataclass

CLONE_NEWUSER = 0x10000000


@dataclass(frozen=True)
class Architecture:
    audit_arch: int  # AUDIT_ARCH_*: what seccomp reports a system call's ABI as
    clone: int
    unshare: int
    clone3: int
    x32_bit: int = 0  # x86-64: the bit that marks an x32 system call (0: no such ABI)


ARCHITECTURES = {
    "x86_64": Architecture(audit_arch=0xC000003E, clone=56, unshare=272, clone3=435, x32_bit=0x40000000),
    "aarch64": Architecture(audit_arch=0xC00000B7, clone=220, unshare=97, clone3=435),
}

# Classic BPF, as seccomp runs it over ``struct seccomp_data`` {int nr; u32 arch; u64 ip; u64 args[6]}.
_LOAD_WORD = 0x20  # BPF_LD | BPF_W | BPF_ABS
_JUMP_EQUAL, _JUMP_AT_LEAST, _JUMP_ANY_BIT = 0x15, 0x35, 0x45  # BPF_JMP | BPF_JEQ / BPF_JGE / BPF_JSET, BPF_K
_RETURN = 0x06  # BPF_RET | BPF_K
_NR, _ARCH, _FIRST_ARGUMENT_LOW = 0, 4, 16  # offsets (the argument's low 32 bits: little-endian)
_ALLOW, _KILL_PROCESS, _ERRNO = 0x7FFF0000, 0x80000000, 0x00050000
EPERM, ENOSYS = 1, 38


def supported() -> bool:
    """Whether this machine's architecture has a filter here (elsewhere the sandbox runs without one, and says so)."""
    return platform.machine() in ARCHITECTURES


def filter_program(arch: Architecture) -> list[tuple[int, int, int, int]]:
    """The filter as (code, jump if true, jump if false, constant) instructions; jumps count the instructions
    skipped after the next one."""
    program = [(_LOAD_WORD, 0, 0, _ARCH), (_JUMP_EQUAL, 1, 0, arch.audit_arch), (_RETURN, 0, 0, _KILL_PROCESS)]
    program += [(_LOAD_WORD, 0, 0, _NR)]
    if arch.x32_bit:
        program += [(_JUMP_AT_LEAST, 0, 1, arch.x32_bit), (_RETURN, 0, 0, _ERRNO | EPERM)]
    program += [
        (_JUMP_EQUAL, 0, 1, arch.clone3),
        (_RETURN, 0, 0, _ERRNO | ENOSYS),
        (_JUMP_EQUAL, 1, 0, arch.unshare),
        (_JUMP_EQUAL, 0, 3, arch.clone),
        (_LOAD_WORD, 0, 0, _FIRST_ARGUMENT_LOW),  # the flags of unshare and clone alike
        (_JUMP_ANY_BIT, 0, 1, CLONE_NEWUSER),
        (_RETURN, 0, 0, _ERRNO | EPERM),
        (_RETURN, 0, 0, _ALLOW),
    ]
    return program


class _SockFprog(ctypes.Structure):
    _fields_ = [("len", ctypes.c_ushort), ("filter", ctypes.c_void_p)]


def install(arch: Architecture) -> None:
    """Install the filter on this process (single-threaded: prctl sets it on the calling thread only); OSError when
    the kernel refuses."""
    program = filter_program(arch)
    code = b"".join(struct.pack("HBBI", *instruction) for instruction in program)
    buffer = ctypes.create_string_buffer(code, len(code))
    fprog = _SockFprog(len(program), ctypes.cast(buffer, ctypes.c_void_p))
    libc = ctypes.CDLL(None, use_errno=True)
    pr_set_no_new_privs, pr_set_seccomp, seccomp_mode_filter = 38, 22, 2
    if libc.prctl(pr_set_no_new_privs, 1, 0, 0, 0) != 0:  # what lets an unprivileged process install a filter
        raise OSError(ctypes.get_errno(), "prctl(PR_SET_NO_NEW_PRIVS)")
    if libc.prctl(pr_set_seccomp, seccomp_mode_filter, ctypes.byref(fprog), 0, 0) != 0:
        raise OSError(ctypes.get_errno(), "prctl(PR_SET_SECCOMP)")


def main(argv: list[str]) -> int:
    if not argv:
        print("usage: python -P -m orchestrator.stack.no_userns COMMAND [ARG ...]", file=sys.stderr)
        return 2
    arch = ARCHITECTURES.get(platform.machine())
    if arch is None:
        print(f"no_userns: no filter for {platform.machine()}", file=sys.stderr)
        return 2
    try:
        install(arch)
    except OSError as error:
        print(f"no_userns: the kernel refused the filter: {error}", file=sys.stderr)
        return 2
    os.execv(argv[0], argv)  # the command, in this process: the filter stays


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
