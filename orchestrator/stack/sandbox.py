"""A brain host inside bubblewrap: for brains nobody vouches for (a challenge's submissions).

What the sandbox of one brain host is (``docs/guides/sandbox.md`` says what it guards and what it does not):

* namespaces (``bwrap``): its own network namespace with only an empty loopback, so the network is not there; its
  own PID, IPC and UTS namespaces; a new session (no terminal to inject into); it dies with the launcher;
* a file system made of read-only binds of what the host needs to run (the system's ``/usr``, the Python install,
  the project, the brain's own file or module and its weights), a fresh ``/tmp``, ``/proc`` and ``/dev``, and one
  writable folder, its scratch (``/scratch``, its working directory); nothing else exists in it, and a path to hide
  (``hidden_paths``) that lies under a bound folder is covered by an empty tmpfs;
* the bus: Zenoh over a Unix socket bound into it (``/bus.sock``), the stack's only way in or out. The router's
  access control lets a link over a Unix socket publish nothing but the command key of the stack's sandboxed brains
  (and declare their own token and control queryable): :func:`access_control`;
* limits by ``setrlimit`` on bubblewrap and everything it starts: address space, CPU seconds (each process), file
  size; processes and threads (``RLIMIT_NPROC``, counted per user: the host runs as its own unprivileged uid, since
  root is exempt from it); its output through a pipe read by the launcher, which keeps ``output_bytes`` at most and
  stops the host past them. cgroups v2 are detected but not used (:func:`limits_in_force` says which apply).
"""

from __future__ import annotations

import functools
import importlib.util
import io
import json
import logging
import os
import platform
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from brains.sandbox_exit import SandboxExit
from orchestrator.stack import no_userns, processes
from orchestrator.stack.failures import FailureKind
from protocol import environment, keys
from protocol.bus import BUS_ENV, Bus, BusConfig

log = logging.getLogger("drivebench.sandbox")

SCRATCH_INSIDE = "/scratch"
SOCKET_INSIDE = "/bus.sock"
NOBODY_UID = 65534
PROJECT = Path(__file__).resolve().parents[2]  # the folder that holds brains/, protocol/, circuits/
CGROUP_V2_CONTROLLERS = Path("/sys/fs/cgroup/cgroup.controllers")
OUTPUT_CHUNK_BYTES = 65536
PROBE_TIMEOUT_S = 10.0
MIB = 1 << 20

# Every message kind of Zenoh's access control: what the rest of the stack (links that are not a Unix socket) may do.
_ALL_MESSAGES = (
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "declare_queryable",
    "reply",
    "liveliness_token",
    "declare_liveliness_subscriber",
    "liveliness_query",
)


class SandboxUnavailable(RuntimeError):
    """No sandbox can be made here (no bubblewrap, or it cannot create namespaces): one line says why."""


@dataclass(frozen=True, kw_only=True)
class Sandbox:
    """How one brain host is confined. Sizes in bytes, times in seconds.

    scratch_dir: the host's only writable folder (created; seen inside as ``/scratch``, its working directory).
    memory_bytes: address space of each process (``RLIMIT_AS``): virtual, so it counts what a process maps, not
        what it touches.
    max_processes: processes and threads of the sandbox's user (``RLIMIT_NPROC``); Zenoh and numpy start threads.
    cpu_seconds: CPU seconds of each process (``RLIMIT_CPU``): SIGXCPU past it.
    file_size_bytes: the largest file it may write (``RLIMIT_FSIZE``).
    output_bytes: what is kept of its stdout and stderr (its log); past it the host is stopped.
    start_timeout_s: how long its token may take to appear (a brain that sleeps in ``__init__`` fails typed).
    hidden_paths: paths it must not see (a challenge's data folder): covered when under a folder bound in.
    uid: the unprivileged user it runs as when the launcher is root (else it runs as the launcher's user).
    """

    scratch_dir: Path
    memory_bytes: int = 8 << 30  # torch alone maps ~2 GiB of address space; a neural brain needs headroom
    max_processes: int = 256
    cpu_seconds: int = 3600
    file_size_bytes: int = 256 * MIB
    output_bytes: int = 4 * MIB
    start_timeout_s: float = 60.0
    hidden_paths: tuple[Path, ...] = ()
    uid: int = NOBODY_UID

    def __post_init__(self) -> None:
        for name in ("memory_bytes", "max_processes", "cpu_seconds", "file_size_bytes", "output_bytes"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"sandbox {name} must be >= 1, got {getattr(self, name)}")

    @classmethod
    def default(cls, *, scratch_dir: Path, hidden_paths: Iterable[Path] = ()) -> Sandbox:
        """The limits a challenge runs with (the defaults above)."""
        return cls(scratch_dir=Path(scratch_dir), hidden_paths=tuple(Path(p) for p in hidden_paths))


# The limits a user may set (``drivebench run --sandbox-limit KEY=VALUE``): Sandbox fields.
LIMIT_KEYS = ("memory_bytes", "max_processes", "cpu_seconds", "file_size_bytes", "output_bytes", "start_timeout_s")


def parse_limits(settings: Iterable[str]) -> dict[str, Any]:
    """``KEY=VALUE`` settings as Sandbox fields (an int each, a float for ``start_timeout_s``); ValueError naming the
    setting for a key not in :data:`LIMIT_KEYS` or a value that is not a number."""
    limits: dict[str, Any] = {}
    for setting in settings:
        key, equals, value = setting.partition("=")
        if not equals or key not in LIMIT_KEYS:
            raise ValueError(f"{setting}: expected KEY=VALUE with KEY one of {', '.join(LIMIT_KEYS)}")
        try:
            limits[key] = float(value) if key == "start_timeout_s" else int(value)
        except ValueError:
            raise ValueError(f"{setting}: {value!r} is not a number") from None
    return limits


def _as_root() -> bool:
    return os.geteuid() == 0


@functools.cache
def _probe() -> str | None:
    """Why bubblewrap cannot make this sandbox here (None: it can), tried once per process."""
    bwrap = shutil.which("bwrap")
    if bwrap is None:
        return "bubblewrap is not installed (Debian: apt-get install bubblewrap)"
    for tool in ("prlimit", "setpriv") if _as_root() else ("prlimit",):
        if shutil.which(tool) is None:
            return f"{tool} (util-linux) is not installed: the sandbox sets its limits (and, as root, its uid) with it"
    argv = [bwrap, *_namespaces(), "--ro-bind", "/", "/", "--proc", "/proc", "--dev", "/dev", "true"]
    try:
        done = subprocess.run(argv, capture_output=True, text=True, timeout=PROBE_TIMEOUT_S)
    except (OSError, subprocess.TimeoutExpired) as error:
        return f"bubblewrap could not run: {error}"
    if done.returncode != 0:
        last = (done.stderr.strip().splitlines() or [f"exit code {done.returncode}"])[-1]
        return f"bubblewrap cannot create a sandbox here: {last}"
    return None


def require_bubblewrap() -> None:
    """Raise :class:`SandboxUnavailable` (one line) unless a sandbox can be made on this machine."""
    if (reason := _probe()) is not None:
        raise SandboxUnavailable(reason)


def cgroup_v2() -> bool:
    """Whether this machine has a cgroups v2 hierarchy (containers often do not, or do not let us write it)."""
    return CGROUP_V2_CONTROLLERS.is_file()


def limits_in_force(sandbox: Sandbox) -> str:
    """One line: each limit, its value and what enforces it."""
    user = f"uid {sandbox.uid}" if _as_root() else f"uid {os.geteuid()}"
    groups = "cgroups v2 present, not used" if cgroup_v2() else "no cgroups v2 here"
    userns = "refused (seccomp)" if no_userns.supported() else f"allowed (no filter for {platform.machine()})"
    return (
        f"setrlimit: address space {sandbox.memory_bytes // MIB} MiB, {sandbox.max_processes} processes ({user}), "
        f"{sandbox.cpu_seconds} CPU s per process, files {sandbox.file_size_bytes // MIB} MiB; output kept "
        f"{sandbox.output_bytes} bytes (pipe); {groups}; new user namespaces {userns}"
    )


def _namespaces() -> list[str]:
    # --unshare-all also makes a user namespace, which run by root maps the host to root outside, where the process
    # limit does not apply: root unshares the rest and drops to the sandbox's own uid inside (setpriv) instead.
    if not _as_root():
        return ["--unshare-all", "--die-with-parent", "--new-session"]
    namespaces = ["--unshare-ipc", "--unshare-pid", "--unshare-net", "--unshare-uts", "--unshare-cgroup-try"]
    return [*namespaces, "--die-with-parent", "--new-session"]


def _minimal(paths: Iterable[Path]) -> list[Path]:
    """The paths without those inside another of them, sorted."""
    kept: list[Path] = []
    for path in sorted(set(paths), key=lambda p: (len(p.parts), str(p))):
        if not any(path.is_relative_to(parent) for parent in kept):
            kept.append(path)
    return sorted(kept)


def python_paths() -> list[Path]:
    """What this Python needs to run the brain host: its installs (a venv and the interpreter it is made of) and
    every existing folder on ``sys.path`` (the project, site-packages), as real paths; the current folder is not."""
    paths = {Path(os.path.realpath(p)) for p in (sys.prefix, sys.base_prefix, sys.exec_prefix)}
    paths.add(Path(os.path.realpath(sys.executable)).parent.parent)
    for entry in sys.path:
        if entry and os.path.isdir(entry) and os.path.realpath(entry) != os.path.realpath(os.getcwd()):
            paths.add(Path(os.path.realpath(entry)))
    return _minimal(paths)


def interpreter() -> str:
    """This Python's path with its folders' links resolved but not the file's: a venv's ``bin/python`` links to the
    interpreter it is made of, and Python finds its venv (``pyvenv.cfg``) from the path it was started by; a folder
    link on the way (a project's ``.venv`` linked elsewhere) would lead to a folder the sandbox does not have."""
    return str(Path(os.path.realpath(os.path.dirname(sys.executable))) / os.path.basename(sys.executable))


def module_root(target: str) -> Path | None:
    """The ``sys.path`` folder that holds the top-level module of a ``package.module:Class`` brain, found without
    running the module (the current folder is searched too, as the brain host does); None when not found."""
    top = target.partition(":")[0].split(".")[0]
    added = os.getcwd() not in sys.path
    if added:
        sys.path.append(os.getcwd())
    try:
        spec = importlib.util.find_spec(top)
    except (ImportError, ValueError):
        spec = None
    finally:
        if added:
            sys.path.remove(os.getcwd())
    if spec is None or not spec.origin or spec.origin in ("built-in", "frozen"):
        return None
    origin = Path(spec.origin).resolve()
    return origin.parent.parent if origin.name == "__init__.py" else origin.parent


def brain_paths(brain: str, options: Iterable[str]) -> tuple[list[Path], list[Path]]:
    """(files and folders to bind read-only, folders to put on PYTHONPATH) for one brain and its options: a brain
    file, the folder of a ``module:Class`` brain's module, and its ``weights`` file. No other option's path: an
    option is a string the brain may read anything from."""
    readable: list[Path] = []
    importable: list[Path] = []
    if brain.endswith(".py") and Path(brain).is_file():
        readable.append(Path(brain).resolve())
    elif ":" in brain and (root := module_root(brain)) is not None:
        readable.append(root)
        importable.append(root)
    for option in options:
        key, _, value = option.partition("=")
        if key.strip() != "weights":
            continue
        try:
            value = json.loads(value)
        except ValueError:
            pass
        if isinstance(value, str) and os.path.isabs(value) and os.path.exists(value):
            readable.append(Path(value).resolve())
    return readable, importable


def _system_binds() -> list[str]:
    """The system's programs and libraries, read-only; the merged-/usr links (``/lib -> usr/lib``) as links."""
    argv = ["--ro-bind", "/usr", "/usr"]
    for name in ("bin", "sbin", "lib", "lib32", "lib64"):
        path = Path("/", name)
        if path.is_symlink():
            argv += ["--symlink", os.readlink(path), str(path)]
        elif path.is_dir():
            argv += ["--ro-bind", str(path), str(path)]
    for name in ("/etc/ld.so.cache", "/etc/localtime"):
        if os.path.exists(name):
            argv += ["--ro-bind", name, name]
    return argv


def _folders_above(paths: Iterable[Path]) -> list[str]:
    """``--dir`` for each folder above a bound path, made 0755: bubblewrap makes them 0700, which the sandbox's
    own uid could not cross."""
    above = sorted(
        {parent for path in paths for parent in path.parents if parent != Path("/")}, key=lambda p: len(p.parts)
    )
    argv: list[str] = []
    for folder in above:
        if not folder.is_relative_to("/usr"):
            argv += ["--perms", "0755", "--dir", str(folder)]
    return argv


def bwrap_argv(
    sandbox: Sandbox,
    *,
    command: Sequence[str],
    socket_path: Path | None,
    readable: Iterable[Path],
    importable: Iterable[Path] = (),
    env: Mapping[str, str] = {},
) -> list[str]:
    """The command line that runs ``command`` in ``sandbox``: bubblewrap, then (as root) setpriv to its uid.
    ``socket_path``: the bus's Unix socket, bound in as its only way out (None: no bus, no way out at all)."""
    bwrap = shutil.which("bwrap")
    if bwrap is None:
        raise SandboxUnavailable("bubblewrap is not installed (Debian: apt-get install bubblewrap)")
    hidden = [Path(os.path.realpath(p)) for p in sandbox.hidden_paths]
    # Nothing inside a hidden path is bound, even when asked for.
    readable = [*readable, PROJECT]  # the filter's module runs first (no_userns_argv)
    binds = [
        p for p in _minimal(Path(os.path.realpath(p)) for p in readable) if not any(p.is_relative_to(h) for h in hidden)
    ]
    # /tmp first: a folder bound in under /tmp (a test's) then lands on the fresh tmpfs instead of under it.
    argv = [bwrap, *_namespaces(), *_system_binds(), "--proc", "/proc", "--dev", "/dev", "--tmpfs", "/tmp"]
    argv += _folders_above(binds)
    for path in binds:
        if not path.is_relative_to("/usr"):
            argv += ["--ro-bind", str(path), str(path)]
    # A hidden path inside a bound folder: an empty tmpfs over a folder; over a file, /dev/null, which its bind
    # (no devices) makes unreadable.
    for path in hidden:
        if any(path.is_relative_to(bound) for bound in binds):
            if path.is_dir():
                argv += ["--tmpfs", str(path)]
            elif path.exists():
                argv += ["--ro-bind", "/dev/null", str(path)]
    argv += ["--bind", str(sandbox.scratch_dir.resolve()), SCRATCH_INSIDE, "--chdir", SCRATCH_INSIDE]
    if socket_path is not None:
        argv += ["--bind", str(socket_path), SOCKET_INSIDE]
    argv += ["--clearenv"]
    inside = {
        "PATH": "/usr/bin:/bin",
        "HOME": SCRATCH_INSIDE,
        "TMPDIR": "/tmp",
        "LANG": "C.UTF-8",
        "PYTHONDONTWRITEBYTECODE": "1",  # everything is read-only but the scratch
        "PYTHONUNBUFFERED": "1",
        "MALLOC_ARENA_MAX": "2",  # glibc reserves 64 MiB of address space per thread arena otherwise
        # The project first: the filter's module (orchestrator.stack.no_userns) runs before the command.
        "PYTHONPATH": ":".join(dict.fromkeys(str(Path(os.path.realpath(p))) for p in [PROJECT, *importable])),
        **env,
    }
    for name, value in inside.items():
        argv += ["--setenv", name, value]
    if _as_root():
        argv += ["--cap-add", "CAP_SETUID", "--cap-add", "CAP_SETGID", "--", shutil.which("setpriv") or "setpriv"]
        argv += [f"--reuid={sandbox.uid}", f"--regid={sandbox.uid}", "--clear-groups"]
        argv += ["--inh-caps=-all", "--bounding-set=-all"]
    return [*argv, "--", *no_userns_argv(), *command]


def no_userns_argv() -> list[str]:
    """What runs ``command`` with no way to make a user namespace (``orchestrator.stack.no_userns``: a seccomp
    filter), or nothing on an architecture it has no filter for (``limits_in_force`` says which)."""
    if not no_userns.supported():
        return []
    return [interpreter(), "-P", "-m", "orchestrator.stack.no_userns"]


def limits_argv(sandbox: Sandbox) -> list[str]:
    """``prlimit`` (util-linux) setting the limits on itself, then running what follows: bubblewrap and all it
    starts inherit them (no ``preexec_fn``: the launcher runs Zenoh's threads, and forking a threaded process into
    Python code is unsafe)."""
    return [
        shutil.which("prlimit") or "prlimit",
        f"--as={sandbox.memory_bytes}",
        f"--nproc={sandbox.max_processes}",
        # SIGXCPU at the soft limit ends Python (it does not catch it); the hard limit one second later is SIGKILL.
        f"--cpu={sandbox.cpu_seconds}:{sandbox.cpu_seconds + 1}",
        f"--fsize={sandbox.file_size_bytes}",
        "--core=0",
        "--",
    ]


def prepare_scratch(sandbox: Sandbox) -> None:
    """Create the scratch folder, owned by the sandbox's uid when it runs as another."""
    sandbox.scratch_dir.mkdir(parents=True, exist_ok=True)
    if _as_root():
        os.chown(sandbox.scratch_dir, sandbox.uid, sandbox.uid)


@dataclass
class SandboxedProcess:
    """A sandboxed process and the thread that copies its output into its log, up to ``output_bytes``."""

    sandbox: Sandbox
    process: subprocess.Popen
    log_path: Path
    output_exceeded: threading.Event = field(default_factory=threading.Event)

    def __post_init__(self) -> None:
        self._reader = threading.Thread(target=self._copy_output, name=f"sandbox-log-{self.process.pid}", daemon=True)
        self._reader.start()

    def _copy_output(self) -> None:
        pipe = self.process.stdout
        assert isinstance(pipe, io.BufferedReader), "started with stdout=PIPE, buffered"
        kept = 0
        with open(self.log_path, "ab") as log_file:
            while chunk := pipe.read1(OUTPUT_CHUNK_BYTES):
                if kept < self.sandbox.output_bytes:
                    room = self.sandbox.output_bytes - kept
                    log_file.write(chunk[:room])
                    log_file.flush()
                kept += len(chunk)
                if kept > self.sandbox.output_bytes and not self.output_exceeded.is_set():
                    self.output_exceeded.set()
                    log_file.write(f"\n[sandbox: output past {self.sandbox.output_bytes} bytes: stopped]\n".encode())
                    self.process.kill()  # bubblewrap's death ends everything inside (--die-with-parent)
        pipe.close()

    def failure(self) -> tuple[FailureKind, str] | None:
        """The sandbox's reason for this process's end (a limit or a refused operation), or None: it is not over,
        or it ended as any process may (then it is typed as its role's death)."""
        code = self.process.poll()
        if code is None:
            return None
        self._reader.join(timeout=1.0)
        if self.output_exceeded.is_set():
            return FailureKind.LIMIT_EXCEEDED, f"output: printed more than {self.sandbox.output_bytes} bytes"
        return classify_exit(code, sandbox=self.sandbox)


def classify_exit(code: int, *, sandbox: Sandbox) -> tuple[FailureKind, str] | None:
    """What a sandboxed host's exit code means: its own :class:`SandboxExit`, or a limit's signal (bubblewrap
    exits with 128 + the signal that ended what it ran)."""
    signal_number = -code if code < 0 else code - 128 if code > 128 else 0
    if signal_number == signal.SIGXCPU:
        return FailureKind.LIMIT_EXCEEDED, f"cpu: more than {sandbox.cpu_seconds} CPU seconds"
    if signal_number == signal.SIGXFSZ:
        return FailureKind.LIMIT_EXCEEDED, f"file size: a file past {sandbox.file_size_bytes} bytes"
    try:
        wall = SandboxExit(code)
    except ValueError:
        return None
    what = {
        SandboxExit.MEMORY: f"memory: address space past {sandbox.memory_bytes} bytes",
        SandboxExit.PROCESSES: f"processes: more than {sandbox.max_processes}",
        SandboxExit.FILE_SIZE: f"file size: a file past {sandbox.file_size_bytes} bytes",
        SandboxExit.REFUSED: "the sandbox refused an operation (a write outside its scratch, or the network)",
    }[wall]
    return (FailureKind.LIMIT_EXCEEDED if wall.is_limit else FailureKind.SANDBOX_VIOLATION), what


def spawn(
    sandbox: Sandbox,
    *,
    command: Sequence[str],
    log_path: Path,
    socket_path: Path,
    readable: Iterable[Path],
    importable: Iterable[Path] = (),
    env: Mapping[str, str] = {},
) -> SandboxedProcess:
    """Start ``command`` in ``sandbox``, its output (bounded) appended to ``log_path``."""
    prepare_scratch(sandbox)
    argv = bwrap_argv(
        sandbox, command=command, socket_path=socket_path, readable=readable, importable=importable, env=env
    )
    log_path.parent.mkdir(parents=True, exist_ok=True)
    log.info("sandbox for %s: %s", log_path.name, limits_in_force(sandbox))
    process = subprocess.Popen(
        [*limits_argv(sandbox), *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        stdin=subprocess.DEVNULL,
        start_new_session=True,
    )
    return SandboxedProcess(sandbox=sandbox, process=process, log_path=log_path)


def open_router(*, run_id: str, endpoint: str, brain_names: frozenset[str], env: Mapping[str, str]) -> tuple[Bus, Path]:
    """A sandboxed brain's stack's own router (embedded), listening on ``endpoint`` and on a Unix socket for the
    sandboxed brains ``brain_names``, with the access control that lets a Unix-socket link publish only their
    command keys (:func:`access_control`): the bus, and the socket's path. SandboxUnavailable without bubblewrap."""
    require_bubblewrap()
    # A short path of our own: a Unix socket's path is at most 107 bytes, and a run folder may be longer.
    socket_path = Path(tempfile.mkdtemp(prefix="drivebench-bus-")) / "bus.sock"
    control = access_control(run_id=run_id, brain_names=brain_names)
    listen = [endpoint, f"unixsock-stream/{socket_path}"]
    bus = Bus(BusConfig(mode="router", listen=listen), name="launcher", env=env, extra={"access_control": control})
    socket_path.parent.chmod(0o755)  # the sandbox's own uid connects through it
    socket_path.chmod(0o666)
    return bus, socket_path


def spawn_brain(
    sandbox: Sandbox,
    *,
    brain: str,
    options: Sequence[str],
    host_argv: Sequence[str],
    run_id: str,
    socket_path: Path,
    log_path: Path,
) -> SandboxedProcess:
    """Start one brain host (``python -m brains`` with ``host_argv``) inside ``sandbox``, a client of the stack's
    router through the Unix socket ``socket_path`` only; ``brain`` and its ``options`` say which files it may read
    and import (:func:`brain_paths`)."""
    joins = ["--router", f"unixsock-stream/{SOCKET_INSIDE}", "--run-id", run_id]
    # A client with no listener and no shared memory: the socket is its one link (nothing is shared with it).
    confined = ["--set", "bus.mode=client", "--set", "bus.shared_memory=false", "--set", "sandboxed=true"]
    readable, importable = brain_paths(brain, options)
    project = PROJECT
    env = {k: v for k, v in os.environ.items() if k.startswith("DRIVEBENCH_") and k not in BUS_ENV}
    for name in (environment.RUN_ID.name, environment.PARENT_PID.name):  # bubblewrap dies with us instead
        env.pop(name, None)
    return spawn(
        sandbox,
        command=[interpreter(), *processes.python_module("brains")[1:], *joins, *host_argv, *confined],
        log_path=log_path,
        socket_path=socket_path,
        readable=[*python_paths(), project, *readable],
        importable=[project, *importable],
        env=env,
    )


def command_argv(
    sandbox: Sandbox, *, command: Sequence[str], readable: Iterable[Path], importable: Iterable[Path] = ()
) -> list[str]:
    """The limits and bubblewrap around a Python ``command`` that needs no bus (a submitted brain's contract
    check): the project and this Python readable, ``readable`` too, ``importable`` on its path; the scratch
    created. ``command`` starts with :func:`interpreter`."""
    prepare_scratch(sandbox)
    project = PROJECT
    readable = [*python_paths(), project, *readable]
    inside = bwrap_argv(
        sandbox, command=command, socket_path=None, readable=readable, importable=[project, *importable]
    )
    return [*limits_argv(sandbox), *inside]


def brain_reads(run_id: str) -> list[tuple[str, tuple[str, ...], tuple[str, ...]]]:
    """What a sandboxed brain may read of run ``run_id``: the camera streams, the brains' episode events (the START's
    seed and mode, without the episode's conditions: ``keys.brain_events``), and liveliness. Not the simulator's
    episode events (their START carries the whole spec: a hidden condition's circuit, world, start), its ground-truth
    poses, the scorer's live metrics (cross-track error is enough to steer blind), the other brains' commands or the
    simulator's status: a stack's own processes may read everything (``protocol.deploy.security.COMMON``), an
    untrusted brain may not.
    Both the subscription and every put it would get are checked, so a subscription on a wildcard gets no more."""
    from protocol.deploy.security import ALL_ALIVE, EVERYTHING

    readable = (keys.camera_raw(run_id), keys.camera_perturbed(run_id), keys.brain_events(run_id))
    return [
        ("ingress", ("declare_subscriber",), readable),
        ("egress", ("put",), readable),
        ("egress", ("declare_subscriber",), (EVERYTHING,)),  # who listens: a client publishes only where someone does
        ("ingress", ("declare_liveliness_subscriber", "liveliness_query"), (ALL_ALIVE,)),
        ("egress", ("liveliness_token", "reply"), (ALL_ALIVE,)),
    ]


def access_control(*, run_id: str, brain_names: Iterable[str]) -> dict[str, Any]:
    """Zenoh's ``access_control`` section of a stack's router with sandboxed brains: every link that is not a Unix
    socket (the rest of the stack) may do anything; a Unix-socket link (a sandboxed brain) may read only what a
    brain host reads (:func:`brain_reads`), publish only the command keys of ``brain_names``, declare only their
    liveliness tokens and serve only their control keys."""
    names = sorted(brain_names)
    own: list[tuple[str, tuple[str, ...], tuple[str, ...]]] = [
        ("ingress", ("put",), tuple(keys.command(run_id, n) for n in names)),
        ("ingress", ("declare_queryable", "reply"), tuple(keys.brain_control(run_id, n) for n in names)),
        ("egress", ("query",), tuple(keys.brain_control(run_id, n) for n in names)),
        ("ingress", ("liveliness_token",), tuple(keys.alive(run_id, "brain", n) for n in names)),
    ]
    rules = [
        {"id": "stack", "messages": list(_ALL_MESSAGES), "flows": ["ingress", "egress"], "permission": "allow"}
        | {"key_exprs": ["**"]}
    ]
    for index, (flow, messages, key_exprs) in enumerate([*brain_reads(run_id), *own]):
        rules.append(
            {
                "id": f"sandboxed-{index}",
                "messages": list(messages),
                "flows": [flow],
                "permission": "allow",
                "key_exprs": list(key_exprs),
            }
        )
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": [
            {"id": "stack", "link_protocols": ["tcp", "udp", "tls", "quic", "ws", "unixpipe", "serial", "vsock"]},
            {"id": "sandboxed", "link_protocols": ["unixsock-stream"]},
        ],
        "policies": [
            {"id": "stack", "rules": ["stack"], "subjects": ["stack"]},
            {"id": "sandboxed", "rules": [r["id"] for r in rules[1:]], "subjects": ["sandboxed"]},
        ],
    }
