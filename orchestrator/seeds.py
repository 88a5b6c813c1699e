"""Training seeds as an axis: one recipe trained once per seed, each run in its own folder, with a manifest.

``drivebench train --model M --data D -o OUT --seeds 0-4 [--workers 2]`` runs ``drivebench train ... --seed S -o
OUT/seed-S`` for every seed, side by side on ``--workers`` processes, and keeps ``OUT/training.json``: the recipe (the
command's options), the dataset's manifest hash, and per seed its folder, checkpoint, best epoch and wall time. Run
it again and finished seeds are kept, interrupted ones resume from their ``last.ckpt``, and the rest start; with
another recipe (or another dataset) it refuses, naming the difference (:func:`check_recipe`), as ``matrix --resume``
does, so every seed of a folder is one recipe's. A matrix then names every run with one glob:
``weights: OUT/seed-*/model.ckpt``.
"""

from __future__ import annotations

import hashlib
import json
import signal
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

MANIFEST_FILE = "training.json"
CHECKPOINT_FILE = "model.ckpt"
LAST_CHECKPOINT_FILE = "last.ckpt"
MAX_SEEDS = 1000
# A seed's training process told to stop (SIGTERM): how long it may take to exit before it is killed.
CHILD_STOP_WAIT_S = 10.0
# Exit codes of a training process that was stopped, not one that failed: Ctrl-C (130, or killed by SIGINT) and
# SIGTERM (143 through drivebench's handler, or killed by it).
INTERRUPTED_CODES = (130, -signal.SIGINT, 128 + signal.SIGTERM, -signal.SIGTERM)


class SeedsError(ValueError):
    """A seed list that cannot be trained (``--seeds 4-0``): one line."""


class RecipeChangedError(ValueError):
    """``--seeds`` over a folder whose seeds were trained with another recipe or dataset: one line."""


def parse_seeds(text: str) -> tuple[int, ...]:
    """``"0-4"`` -> (0, 1, 2, 3, 4); ``"0,2,7"``; ``"1-3,8"``. Seeds are integers >= 0, each once."""
    seeds: list[int] = []
    for part in (p.strip() for p in text.split(",")):
        first, dash, last = part.partition("-")
        try:
            low, high = int(first), int(last) if dash else int(first)
        except ValueError:
            raise SeedsError(f"--seeds {text}: {part!r} is not a seed or a range like 0-4") from None
        if low < 0 or high < 0:
            raise SeedsError(f"--seeds {text}: seeds are >= 0")
        if high < low:
            raise SeedsError(f"--seeds {text}: the range {part} is empty (write it low-high, e.g. {high}-{low})")
        seeds += range(low, high + 1)
        if len(seeds) > MAX_SEEDS:
            raise SeedsError(f"--seeds {text}: more than {MAX_SEEDS} seeds")
    if len(set(seeds)) != len(seeds):
        raise SeedsError(f"--seeds {text}: a seed is named twice")
    return tuple(seeds)


@dataclass(frozen=True)
class SeedRun:
    """One seed's training: where it lives and how it ended."""

    seed: int
    folder: Path
    status: str  # "done", "failed" (see log), "interrupted"
    best_epoch: int | None = None
    wall_s: float | None = None
    log: Path | None = None

    def to_dict(self, root: Path) -> dict[str, Any]:
        return {
            "seed": self.seed,
            "folder": str(self.folder.relative_to(root)),
            "checkpoint": str((self.folder / CHECKPOINT_FILE).relative_to(root)),
            "status": self.status,
            "best_epoch": self.best_epoch,
            "wall_s": self.wall_s,
        }


def manifest_base(*, seeds: tuple[int, ...], recipe: list[str], data: Path) -> dict[str, Any]:
    """What ``training.json`` says of the whole set, before any seed's entry: the recipe, the dataset and its
    manifest hash, the seeds."""
    return {"recipe": recipe, "data": str(data), "data_manifest_sha256": _manifest_hash(data), "seeds": list(seeds)}


def train_seeds(
    *,
    seeds: tuple[int, ...],
    output: Path,
    recipe: list[str],
    data: Path,
    workers: int,
    log=print,
) -> list[SeedRun]:
    """Train ``recipe`` (the train command's own options, without seed or output) once per seed into
    ``output/seed-N`` as local processes; returns every seed's run and writes ``output/training.json`` after each
    one ends. On a Ray cluster: :func:`orchestrator.seeds_ray.train_seeds_on_ray` (which builds on this module, so
    this module never imports it)."""
    output.mkdir(parents=True, exist_ok=True)
    runs: dict[int, SeedRun] = {}
    base = manifest_base(seeds=seeds, recipe=recipe, data=data)
    manifest_lock = threading.Lock()  # two seeds may end at once: one writer of training.json at a time

    children = _Children()

    def one(seed: int) -> SeedRun:
        run = _train_one(seed=seed, folder=seed_folder(output, seed), recipe=recipe, log=log, children=children)
        with manifest_lock:
            runs[seed] = run
            write_manifest(output, base, [runs[s] for s in seeds if s in runs])
        return run

    with ThreadPoolExecutor(max_workers=max(1, workers)) as pool:
        try:
            finished = list(pool.map(one, seeds))
        except BaseException:
            # SIGTERM (SystemExit) or Ctrl-C here: stop every seed's process too, or the pool would wait for
            # trainings that outlive us (a terminal's Ctrl-C reaches them, a SIGTERM to this process does not).
            pool.shutdown(wait=False, cancel_futures=True)
            children.stop(wait_s=CHILD_STOP_WAIT_S)
            raise
    return finished


class _Children:
    """The seeds' training processes now running, so that all of them stop when this process is told to."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._running: set[subprocess.Popen] = set()
        self._stopping = False

    def run(self, command: list[str], *, out) -> int:
        """Run ``command`` to its end (its exit code); once :meth:`stop` was called, start nothing (-SIGTERM)."""
        with self._lock:
            if self._stopping:
                return -signal.SIGTERM
            process = subprocess.Popen(command, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
            self._running.add(process)
        try:
            return process.wait()
        finally:
            with self._lock:
                self._running.discard(process)

    def stop(self, *, wait_s: float) -> None:
        """SIGTERM to every running process (each saves nothing beyond its last epoch's ``last.ckpt``), and
        SIGKILL to any still running ``wait_s`` later."""
        with self._lock:
            self._stopping = True
            running = list(self._running)
        for process in running:
            process.terminate()
        deadline = time.monotonic() + wait_s
        for process in running:
            try:
                process.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()


def seed_folder(output: Path, seed: int) -> Path:
    return output / f"seed-{seed}"


def _train_one(*, seed: int, folder: Path, recipe: list[str], log, children: _Children) -> SeedRun:
    if finished(folder):
        log(f"seed {seed}: already trained ({folder / CHECKPOINT_FILE}), kept")
        return done_run(seed, folder)
    resume = ["--resume"] if (folder / LAST_CHECKPOINT_FILE).is_file() else []
    folder.mkdir(parents=True, exist_ok=True)
    log_path = folder / "train.log"
    log(f"seed {seed}: {'resuming' if resume else 'training'} -> {folder} (log: {log_path})")
    command = [sys.executable, "-P", "-m", "orchestrator.cli", "train", *recipe, "--seed", str(seed)]
    command += ["-o", str(folder), *resume]
    with open(log_path, "ab") as out:
        returncode = children.run(command, out=out)
    if returncode == 0 and finished(folder):
        run = done_run(seed, folder)
        log(f"seed {seed}: done in {_wall_text(run)}, best epoch {run.best_epoch}")
        return run
    status = "interrupted" if returncode in INTERRUPTED_CODES else "failed"
    log(f"seed {seed}: {status} (exit {returncode}); see {log_path}")
    return SeedRun(seed=seed, folder=folder, status=status, log=log_path)


def _wall_text(run: SeedRun) -> str:
    """The training's own wall time (every session of it, as ``training.json``'s ``wall_s``): one definition, so the
    console and the manifest agree; the process's start-up (imports, loading the dataset) is not in it."""
    return "?" if run.wall_s is None else f"{run.wall_s:.1f} s"


def finished(folder: Path) -> bool:
    """A run is finished once its checkpoint is written and no partial training state is newer."""
    checkpoint = folder / CHECKPOINT_FILE
    last = folder / LAST_CHECKPOINT_FILE
    return checkpoint.is_file() and (not last.is_file() or checkpoint.stat().st_mtime >= last.stat().st_mtime)


def done_run(seed: int, folder: Path) -> SeedRun:
    from brains.neural.checkpoint import load_checkpoint

    checkpoint = load_checkpoint(folder / CHECKPOINT_FILE)
    wall = checkpoint.training.get("wall_s")
    return SeedRun(
        seed=seed,
        folder=folder,
        status="done",
        best_epoch=checkpoint.metrics.get("best_epoch"),
        wall_s=float(wall) if isinstance(wall, (int, float)) else None,
    )


def check_recipe(output: Path, *, recipe: list[str], data: Path) -> None:
    """Refuse (:class:`RecipeChangedError`, one line naming each difference) to train into ``output`` with another
    recipe or dataset than its ``training.json`` records: kept seeds and new ones would differ in more than the seed,
    and the manifest would describe runs it did not make. An unchanged recipe, with seeds added or not, passes."""
    path = output / MANIFEST_FILE
    if not path.is_file():
        return
    try:
        before = json.loads(path.read_text())
    except (OSError, ValueError) as error:
        raise RecipeChangedError(f"{path}: not a training manifest ({error}); train into another -o folder") from None
    differences = recipe_differences(before.get("recipe") or [], recipe, same_data=_same_data(before, data))
    stored_hash, hash_now = before.get("data_manifest_sha256"), _manifest_hash(data)
    if stored_hash and hash_now and stored_hash != hash_now:
        differences.append(f"the dataset's manifest.json changed (sha256 {stored_hash[:12]}, now {hash_now[:12]})")
    if differences:
        raise RecipeChangedError(
            f"{path}: these seeds were trained with another recipe ({'; '.join(differences)}); train with the "
            "recipe as it was, or into another -o folder"
        )


def recipe_differences(before: list[str], now: list[str], *, same_data: bool = False) -> list[str]:
    """Each option that differs between two recipes, as ``--epochs was 1, now 3`` / ``--no-augment was absent, now
    given``; ``--data`` is left out when ``same_data`` (the same folder written another way)."""
    old, new = _options(before), _options(now)
    differences = []
    for flag in dict.fromkeys([*old, *new]):
        if old.get(flag) == new.get(flag) or (flag == "--data" and same_data):
            continue
        differences.append(f"{flag} was {_shown(old.get(flag))}, now {_shown(new.get(flag))}")
    return differences


def _options(recipe: list[str]) -> dict[str, tuple[str, ...]]:
    """``["--epochs", "3", "--hyper=a=1", "--no-augment"]`` -> {"--epochs": ("3",), "--hyper": ("a=1",),
    "--no-augment": ()}: repeated options keep every value, in order."""
    options: dict[str, tuple[str, ...]] = {}
    index = 0
    while index < len(recipe):
        flag, equals, value = recipe[index].partition("=")
        if equals:
            options[flag] = (*options.get(flag, ()), value)
        elif index + 1 < len(recipe) and not recipe[index + 1].startswith("--"):
            options[flag] = (*options.get(flag, ()), recipe[index + 1])
            index += 1
        else:
            options[flag] = ()
        index += 1
    return options


def _shown(values: tuple[str, ...] | None) -> str:
    if values is None:
        return "absent"
    return " ".join(values) if values else "given"


def _same_data(before: dict[str, Any], data: Path) -> bool:
    """The recorded ``--data`` is this folder: the same path, resolved (a Ray run records it absolute)."""
    recorded = before.get("data")
    return isinstance(recorded, str) and Path(recorded).resolve() == data.resolve()


def _manifest_hash(data: Path) -> str | None:
    manifest = data / "manifest.json"
    return hashlib.sha256(manifest.read_bytes()).hexdigest() if manifest.is_file() else None


def write_manifest(output: Path, base: dict[str, Any], runs: list[SeedRun]) -> None:
    document = {**base, "runs": [run.to_dict(output) for run in sorted(runs, key=lambda r: r.seed)]}
    temporary = output / f".{MANIFEST_FILE}.partial"
    temporary.write_text(json.dumps(document, indent=2) + "\n")
    temporary.replace(output / MANIFEST_FILE)
