"""Training seeds on a Ray cluster: ``drivebench train ... --seeds 0-4 --ray ADDRESS [--ray-resource GPU=1]``.

One Ray task per seed runs the same ``drivebench train ... --seed S`` process a local run does, on whichever node has
what it asks for (one CPU, plus each ``--ray-resource``: ``GPU=1`` makes Ray hand the task a GPU, which the training
process sees through CUDA_VISIBLE_DEVICES). The task returns the run folder's files; this process writes them into
``OUT/seed-S`` and keeps ``OUT/training.json`` as a local run does. What a node needs: drivebench installed, and the
dataset at the same path (a shared mount; a dataset travels badly through Ray's object store). A seed whose node dies
is retried elsewhere (Ray's task retries); a seed that failed says why in ``OUT/seed-S/train.log``.
"""

from __future__ import annotations

import socket
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

from orchestrator.matrix.ray_options import connect, import_ray, task_resources
from orchestrator.seeds import SeedRun, done_run, finished, seed_folder, write_manifest

NODE_RETRIES = 2
LOG_FILE = "train.log"


def train_seeds_on_ray(
    *,
    seeds: tuple[int, ...],
    output: Path,
    recipe: list[str],
    base: dict[str, Any],
    address: str,
    resources: dict[str, float],
    log=print,
) -> list[SeedRun]:
    """Train every seed of ``seeds`` not finished in ``output`` as a task on the cluster at ``address``."""

    ray = import_ray()
    connect(address)
    runs = {seed: done_run(seed, seed_folder(output, seed)) for seed in seeds if finished(seed_folder(output, seed))}
    for seed in runs:
        log(f"seed {seed}: already trained ({seed_folder(output, seed)}), kept")
    task = ray.remote(max_retries=NODE_RETRIES, **task_resources({"CPU": 1.0, **resources}))(train_on_node)
    pending = {task.remote(seed=seed, recipe=recipe): seed for seed in seeds if seed not in runs}
    for seed in pending.values():
        log(f"seed {seed}: submitted to the cluster at {address}")
    while pending:
        ready, _ = ray.wait(list(pending), num_returns=1)
        seed = pending.pop(ready[0])
        runs[seed] = _land(seed, seed_folder(output, seed), _outcome(ray, ready[0]), log=log)
        write_manifest(output, base, [runs[s] for s in seeds if s in runs])
    write_manifest(output, base, [runs[s] for s in seeds])
    return [runs[seed] for seed in seeds]


def train_on_node(*, seed: int, recipe: list[str]) -> dict[str, Any]:
    """On a node: ``drivebench train RECIPE --seed SEED`` into a temporary folder; its files and exit code back."""
    with tempfile.TemporaryDirectory(prefix=f"drivebench-seed-{seed}-") as temporary:
        folder = Path(temporary) / "run"
        command = [sys.executable, "-P", "-m", "orchestrator.cli", "train", *recipe, "--seed", str(seed)]
        with open(Path(temporary) / LOG_FILE, "wb") as out:
            code = subprocess.run(command + ["-o", str(folder)], stdout=out, stderr=subprocess.STDOUT).returncode
        files = {path.name: path.read_bytes() for path in sorted(folder.glob("*")) if path.is_file()}
        files[LOG_FILE] = (Path(temporary) / LOG_FILE).read_bytes()
        return {"code": code, "files": files, "node": socket.gethostname()}


def _outcome(ray, reference) -> dict[str, Any]:
    try:
        return ray.get(reference)
    except Exception as error:  # the task's node died past its retries, or Ray itself failed it
        text = str(error).strip().splitlines()
        return {"code": None, "files": {}, "node": "?", "error": f"{type(error).__name__}: {text[0] if text else ''}"}


def _land(seed: int, folder: Path, outcome: dict[str, Any], *, log) -> SeedRun:
    folder.mkdir(parents=True, exist_ok=True)
    for name, data in outcome["files"].items():
        (folder / Path(name).name).write_bytes(data)
    if outcome["code"] == 0 and finished(folder):
        run = done_run(seed, folder)
        log(f"seed {seed}: done on {outcome['node']}, best epoch {run.best_epoch}")
        return run
    reason = outcome.get("error") or f"exit {outcome['code']} on {outcome['node']}"
    log(f"seed {seed}: failed ({reason}); see {folder / LOG_FILE}")
    return SeedRun(seed=seed, folder=folder, status="failed", log=folder / LOG_FILE)
