"""Matrices on a Ray cluster: ``drivebench matrix FILE --ray ADDRESS``.

The driver (this process) plans the matrix, keeps ``results.sqlite``, the resume semantics, the progress display and
the report exactly as a local run (:class:`orchestrator.matrix.runner.MatrixRunner`); only the dispatch differs.
Every pending episode becomes one Ray task (:func:`run_episode_task`) that, on whichever node Ray places it:

- starts the episode's own stack: a Zenoh router on a free loopback port of that node, simulator, noise injector,
  brain(s), scorer and, with ``--record``, a recorder, every process in one new process group;
- enforces the wall-clock guard inside the task (the stack's own guard, and a watchdog above it);
- always kills its process group before it returns (grandchildren included);
- returns the result row, the node it ran on and the episode folder's small files (score, config, trajectory,
  logs). Recordings are written straight to ``--artifacts DIR``, a folder every node mounts: never through Ray's
  object store.

Placement: each task asks for one ``episode_slot`` (a custom resource every worker node declares:
``ray start --resources '{"episode_slot": 2}'``) plus any ``--ray-resource NAME=AMOUNT`` (a GPU share for a neural
brain). Before anything is submitted, a demand that no node can meet fails at once with one line (Ray itself would
wait forever). At most as many tasks as the cluster has slots are in flight, so the progress lanes are episodes that
run, not a queue.

Failures are typed. A task lost with its node or its worker process (``NodeDiedError``, ``WorkerCrashedError``, ...)
is submitted again, elsewhere if Ray can, at most ``--node-retries`` times; each lost attempt is recorded in the
episode's row (``lost_attempts``), and only the attempt that finishes is a result, so nothing is counted twice. An
episode that failed on its own (a brain died, off track, the time limit, the wall-clock guard) comes back as a
result like on a local run and is never retried.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import os
import re
import shutil
import signal
import socket
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path

from orchestrator.matrix.load import Matrix, PlannedEpisode
from orchestrator.matrix.ray_options import EPISODE_SLOT, ClusterError, RayOptions, import_ray
from orchestrator.matrix.results import EpisodeResult, ResultStore
from orchestrator.matrix.runner import (
    MatrixProgress,
    MatrixRunner,
    RunOptions,
)

log = logging.getLogger("drivebench.ray")

RECORDING_NAME = "recording.mcap"
SMALL_FILE_BYTES = 4 * 1024 * 1024  # a log longer than this comes back as its last 4 MiB
WATCHDOG_SLACK_S = 60.0  # above the stack's own guards: start-up, the episode, the recorder's stop grace
POLL_S = 0.25
LIVE_PERIOD_S = 0.5  # how often a running episode sends its live metrics to the driver


# -- the cluster --


def connect(address: str) -> None:
    """Join the cluster at ``address`` as a driver (nothing when this process already is one)."""
    ray = import_ray()
    if ray.is_initialized():
        return
    _probe(address)
    try:
        ray.init(address=address, logging_level=logging.WARNING, log_to_driver=False)
    except ImportError as error:  # ray:// without Ray Client's packages
        raise ClusterError(f"{address!r} needs Ray Client: pip install 'ray[client]' ({error})") from None
    except (ConnectionError, RuntimeError, ValueError) as error:
        first = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        raise ClusterError(f"no Ray cluster at {address!r}: {first}") from None


def _probe(address: str, *, timeout_s: float = 5.0) -> None:
    """A ``HOST:PORT`` where nothing listens, as one line at once (Ray itself would retry for minutes)."""
    if address == "auto" or "://" in address:
        return
    host, _, port = address.rpartition(":")
    if not host or not port.isdigit():
        raise ClusterError(f"--ray {address!r}: expected auto, HOST:PORT or ray://HOST:10001")
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s).close()
    except OSError as error:
        raise ClusterError(
            f"no Ray cluster at {address!r}: nothing answers there ({error.strerror or error})"
        ) from None


def alive_nodes() -> list[dict]:
    return [node for node in import_ray().nodes() if node.get("Alive")]


def slots_of(node: dict, resources: dict) -> int:
    """How many episodes asking for ``resources`` fit on ``node`` at once."""
    offered = node.get("Resources", {})
    return int(min(offered.get(name, 0.0) / amount for name, amount in resources.items()) + 1e-9)


def capacity(resources: dict) -> int:
    """Episodes the cluster can run at once; :class:`ClusterError` (one line) when no node can run one."""
    nodes = alive_nodes()
    total = sum(slots_of(node, resources) for node in nodes)
    if total < 1:
        wanted = ", ".join(f"{name}={amount:g}" for name, amount in resources.items())
        offered = "; ".join(_offer(node) for node in nodes) or "no node alive"
        raise ClusterError(
            f"no node of the Ray cluster has what one episode asks for ({wanted}); the nodes offer: "
            f"{offered} (start workers with `ray start --address HEAD:6379 --resources "
            f"'{{\"{EPISODE_SLOT}\": N}}'`)"
        )
    return total


def _offer(node: dict) -> str:
    shown = {
        name: amount
        for name, amount in node.get("Resources", {}).items()
        if not name.startswith(("node:", "memory", "object_store_memory", "accelerator_type"))
    }
    return f"{node.get('NodeManagerAddress', '?')} " + (
        ", ".join(f"{name}={amount:g}" for name, amount in sorted(shown.items())) or "nothing"
    )


def task_resources(resources: dict) -> dict:
    """Ray task options for what one episode asks for: CPU and GPU are Ray's own fields (Ray refuses them among
    custom resources); the rest, episode_slot first, are custom resources. No CPU unless asked: the slot is the cap.
    A GPU share makes Ray set CUDA_VISIBLE_DEVICES for the task, which the stack's brain inherits."""
    custom = dict(resources)
    return {"num_cpus": custom.pop("CPU", 0), "num_gpus": custom.pop("GPU", 0), "resources": custom}


def node_label(*, ip: str, node_id: str) -> str:
    """How a results row names a Ray node: ``<ip>/<first 8 hex of its node id>`` (several nodes may share a host)."""
    return f"{ip}/{node_id[:8]}"


# -- the driver --


class RayMatrixRunner(MatrixRunner):
    """A :class:`MatrixRunner` whose episodes run as Ray tasks; results, resume and progress are the local ones."""

    def __init__(self, matrix: Matrix, out_dir: Path, options: RunOptions, *, ray_options: RayOptions, on_change=None):
        super().__init__(matrix, out_dir, options, on_change=on_change)
        self.ray_options = ray_options
        self._capacity = 1

    def run(self) -> MatrixProgress:
        connect(self.ray_options.address)
        self._capacity = capacity(self.ray_options.resources)  # before anything is submitted: fail at once
        return super().run()

    def _lanes(self) -> int:
        return self._capacity

    def _dispatch(self, todo: list[PlannedEpisode], store: ResultStore, progress: MatrixProgress) -> None:
        ray = import_ray()
        task = ray.remote(run_episode_task).options(
            **task_resources(self.ray_options.resources),
            max_retries=0,  # node deaths: retried here, recorded
            name="drivebench-episode",
        )
        shared = dataclasses.replace(self.matrix, text="", episodes=())  # what a task needs: name and shadows
        waiting = collections.deque((episode, ()) for episode in todo)
        running: dict = {}  # ObjectRefGenerator -> (episode, lost attempts so far, lane)
        free_lanes = list(range(len(progress.workers)))
        try:
            while waiting or running:
                while waiting and free_lanes and len(running) < self._window():
                    episode, lost = waiting.popleft()
                    lane = free_lanes.pop(0)
                    stream = task.remote(
                        matrix=shared, episode=episode, options=self.options, artifacts=self._artifacts_text()
                    )
                    running[stream] = (episode, lost, lane)
                    with progress.lock:
                        progress.workers[lane].episode, progress.workers[lane].live = episode, None
                ready, _ = ray.wait(list(running), num_returns=1, timeout=POLL_S)
                for stream in ready:  # its next item is there: live metrics, the result, or the task's error
                    episode, lost, lane = running[stream]
                    item = self._next_item(stream)
                    if "live" in item:
                        with progress.lock:
                            progress.workers[lane].live = item["live"]
                        continue
                    del running[stream]
                    with progress.lock:
                        progress.workers[lane].episode, progress.workers[lane].live = None, None
                    free_lanes.append(lane)
                    result = self._collect(item, episode, lost, waiting)
                    if result is not None:
                        self._finish(result, store, progress)
                self._on_change(progress)
        except BaseException:
            self.stop()
            for stream in running:  # Ctrl-C, SIGTERM: stop them now (force: a plain cancel waits for a sleeping task)
                ray.cancel(stream, force=True)
            raise

    def _window(self) -> int:
        """Tasks in flight: the cluster's slots now (nodes come and go), at least one."""
        try:
            return max(1, sum(slots_of(node, self.ray_options.resources) for node in alive_nodes()))
        except Exception:  # noqa: BLE001 - a GCS hiccup must not end the matrix; keep going one at a time
            return 1

    def _artifacts_text(self) -> str | None:
        return None if self.ray_options.artifacts is None else str(self.ray_options.artifacts)

    @staticmethod
    def _next_item(stream) -> dict:
        """The next item of a task's stream: ``{"live": LiveMetrics}``, ``{"result", "files"}``, or
        ``{"error": exception}`` when the task failed (Ray raises it where the item would be)."""
        ray = import_ray()
        try:
            value = ray.get(next(stream))
        except StopIteration:
            return {"error": RuntimeError("the episode's task ended without a result")}
        except ray.exceptions.RayError as error:
            return {"error": error}
        if "live" in value:
            from protocol import codec
            from protocol.messages import LiveMetrics

            return {"live": codec.decode(value["live"], LiveMetrics)}
        return value

    def _collect(
        self, item: dict, episode: PlannedEpisode, lost: tuple, waiting: collections.deque
    ) -> EpisodeResult | None:
        """The result of a finished task; None when its node was lost and it is submitted again."""
        ray = import_ray()
        try:
            if "error" in item:
                raise item["error"]
            outcome = item
        except _lost_errors() as error:
            attempt = {"node": _node_in(error), "error": f"{type(error).__name__}: {_first_line(error)}"}
            lost = (*lost, attempt)
            log.warning("episode %s: attempt %d lost (%s)", episode.key, len(lost), attempt["error"])
            if len(lost) <= self.ray_options.node_retries:
                waiting.appendleft((episode, lost))
                return None
            return self._lost_result(episode, lost)
        except (ray.exceptions.RayError, RuntimeError) as error:  # the task itself broke, not the episode: not retried
            return self._lost_result(episode, lost, failure=f"error: {type(error).__name__}: {_first_line(error)}")
        return self._land(episode, outcome, lost)

    def _land(self, episode: PlannedEpisode, outcome: dict, lost: tuple) -> EpisodeResult:
        """A task's outcome into the output folder: its small files, its row with the node and lost attempts."""
        result: EpisodeResult = outcome["result"]
        folder = self.out_dir / "episodes" / f"{episode.index:04d}"
        if not _same_folder(self.ray_options.artifacts, self.out_dir):
            if folder.exists():
                shutil.rmtree(folder)
            for relative, data in outcome["files"].items():
                path = folder / relative
                path.parent.mkdir(parents=True, exist_ok=True)
                path.write_bytes(data)
        recording = result.recording
        if recording is not None and self.ray_options.artifacts is not None:
            recording = self._relative_or_absolute(self.ray_options.artifacts / recording)
        return dataclasses.replace(result, recording=recording, lost_attempts=lost)

    def _relative_or_absolute(self, path: Path) -> str:
        try:
            return str(path.resolve().relative_to(self.out_dir.resolve()))
        except ValueError:
            return str(path.resolve())

    def _lost_result(self, episode: PlannedEpisode, lost: tuple, *, failure: str | None = None) -> EpisodeResult:
        now = time.time()
        if failure is None:
            failure = f"node_died: lost {len(lost)} time(s), last: {lost[-1]['error']}"
        return EpisodeResult.of(
            episode,
            status="failed",
            run_id="-",
            started_at=now,
            ended_at=now,
            failure=failure,
            node=lost[-1]["node"] if lost else None,
            lost_attempts=lost,
        )


def _lost_errors() -> tuple[type, ...]:
    """Ray's errors for a task lost with its node or worker process (infrastructure, not the episode)."""
    exceptions = import_ray().exceptions
    names = (
        "NodeDiedError",
        "WorkerCrashedError",
        "ObjectLostError",
        "LocalRayletDiedError",
        "OutOfMemoryError",
        "TaskUnschedulableError",
        "RaySystemError",
    )
    return tuple(getattr(exceptions, name) for name in names if hasattr(exceptions, name))


def _first_line(error: BaseException) -> str:
    text = str(error).strip()
    return text.splitlines()[0][:300] if text else ""


def _node_in(error: BaseException) -> str | None:
    """The node a Ray error names (``node id: <hex>`` / ``address: <ip>``), as :func:`node_label` writes it."""
    text = str(error)
    node_id = re.search(r"node(?:[ _]id)?[:=]?\s*([0-9a-f]{16,})", text, re.IGNORECASE)
    ip = re.search(r"(?:address|ip)[:=]?\s*([0-9]+(?:\.[0-9]+){3})", text, re.IGNORECASE)
    if node_id is None:
        return None
    return node_label(ip=ip.group(1) if ip else "?", node_id=node_id.group(1))


def _same_folder(artifacts: Path | None, out_dir: Path) -> bool:
    return artifacts is not None and artifacts.resolve() == out_dir.resolve()


# -- one episode, on a node --


class _NodeRunner(MatrixRunner):
    """The local runner's episode code (:meth:`MatrixRunner._run_one`), run inside a Ray task: the stack in one
    process group, rows naming this node."""

    def __init__(self, matrix: Matrix, out_dir: Path, options: RunOptions, *, node: str):
        super().__init__(matrix, out_dir, options)
        self.node = node
        self.stack = None

    def _make_stack(self, **settings):
        from orchestrator.stack.launcher import LocalStack

        self.stack = LocalStack(one_group=True, **settings)
        return self.stack

    def _node_name(self) -> str:
        return self.node

    def kill_group(self) -> None:
        """SIGKILL whatever of the stack's process group is left (grandchildren included)."""
        group = None if self.stack is None else self.stack.process_group
        if group is not None:
            try:
                os.killpg(group, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                pass  # every member already gone


def run_episode_task(
    *, matrix: Matrix, episode: PlannedEpisode, options: RunOptions, artifacts: str | None
) -> Iterator[dict]:
    """One episode on this node (a Ray generator task's body): ``{"live": <LiveMetrics, encoded>}`` twice a
    second while it drives (the driver's progress lanes), then ``{"result": EpisodeResult, "files": {path: bytes}}``.

    The episode folder is ``<artifacts>/episodes/<index>`` (recording included) or, without artifacts, a temporary
    folder removed before returning; ``files`` holds its small files (not the recording), paths relative to it.
    """
    import ray

    context = ray.get_runtime_context()
    node = node_label(ip=ray.util.get_node_ip_address(), node_id=context.get_node_id())
    scratch = None if artifacts is not None else Path(tempfile.mkdtemp(prefix="drivebench-episode-"))
    try:
        yield from _drive(matrix=matrix, episode=episode, options=options, node=node, work=Path(artifacts or scratch))
    finally:
        if scratch is not None:
            shutil.rmtree(scratch, ignore_errors=True)


def _drive(*, matrix: Matrix, episode: PlannedEpisode, options: RunOptions, node: str, work: Path) -> Iterator[dict]:
    """:func:`run_episode_task` in the folder ``work``: the stack in one process group, under a watchdog."""
    from orchestrator.matrix.runner import WorkerState
    from orchestrator.stack.launcher import free_loopback_port, wall_guard_s
    from protocol import codec
    from protocol.bus import Bus, BusConfig

    runner = _NodeRunner(matrix, work, options, node=node)
    guard_s = options.startup_timeout_s + wall_guard_s(max_sim_seconds=episode.spec.max_sim_seconds) + WATCHDOG_SLACK_S
    fired = threading.Event()

    def watchdog() -> None:  # the stack's own guards failed to end it: abandon it and kill its processes
        fired.set()
        runner.stop()
        runner.kill_group()

    timer = threading.Timer(guard_s, watchdog)
    timer.daemon = True
    router = Bus(BusConfig(mode="router", listen=[f"tcp/127.0.0.1:{free_loopback_port()}"]), name="episode-router")
    started_at = time.time()
    state = WorkerState()
    outcome: dict = {}

    def drive() -> None:
        try:
            outcome["result"] = runner._run_one(episode, router.config.listen[0], state)
        except BaseException as error:  # noqa: BLE001 - raised again in the task, where Ray reports it
            outcome["error"] = error

    thread = threading.Thread(target=drive, name="episode", daemon=True)
    try:
        timer.start()
        thread.start()
        sent = None
        while thread.is_alive():
            thread.join(timeout=LIVE_PERIOD_S)
            if state.live is not None and state.live is not sent:
                sent = state.live
                yield {"live": codec.encode(sent)}
    finally:
        timer.cancel()
        if thread.is_alive():  # the task itself was cancelled: abandon the episode
            runner.stop()
        runner.kill_group()
        thread.join(timeout=10.0)
        router.close()
    if "error" in outcome:
        raise outcome["error"]
    result = outcome.get("result")
    if result is None or fired.is_set():
        result = _timed_out(episode, node=node, started_at=started_at, guard_s=guard_s, result=result)
    yield {"result": result, "files": _small_files(work / "episodes" / f"{episode.index:04d}")}


def _timed_out(
    episode: PlannedEpisode, *, node: str, started_at: float, guard_s: float, result: EpisodeResult | None
) -> EpisodeResult:
    failure = f"wall_timeout: the episode's task ran past its {guard_s:.0f} s guard; its processes were killed"
    if result is not None:
        return dataclasses.replace(result, status="failed", failure=failure)
    return EpisodeResult.of(
        episode,
        status="failed",
        run_id="-",
        started_at=started_at,
        ended_at=time.time(),
        failure=failure,
        node=node,
    )


def _small_files(folder: Path) -> dict[str, bytes]:
    """Every file of an episode folder but the recording, relative paths to bytes (a long log: its tail)."""
    files = {}
    for path in sorted(folder.rglob("*")) if folder.is_dir() else ():
        if not path.is_file() or path.name == RECORDING_NAME:
            continue
        size = path.stat().st_size
        with path.open("rb") as handle:
            if size > SMALL_FILE_BYTES:
                handle.seek(size - SMALL_FILE_BYTES)
            files[str(path.relative_to(folder))] = handle.read()
    return files


__all__ = ["RayMatrixRunner", "capacity", "connect", "run_episode_task", "slots_of", "task_resources"]
