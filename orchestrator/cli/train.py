"""``drivebench train``: fit one of the paper's networks to a dataset folder (argument parsing only; the work is in
:mod:`brains.training.trainer`, imported, with torch, only when the command runs).

    drivebench train --model deepest_lstm_tiny_pilotnet --data DATASET -o RUN_DIR [--epochs 50] [--batch-size 64]
        [--lr 1e-3] [--device auto|cpu|cuda] [--seed 0] [--patience 10] [--labels zscore|paper]
        [--hyper KEY=VALUE ...] [--threads N] [--max-samples-per-epoch N] [--limit-train-samples N]
        [--no-augment] [--no-balance] [--any-crop] [--resume | --overwrite]
        [--seeds 0-4 [--workers N | --ray ADDRESS [--ray-resource GPU=1]]]

Exit codes: 0 trained; 2 a request that cannot run (one line on stderr, ``drivebench: error: ...``); 130 after
Ctrl-C, with last.ckpt saved and a line saying how to resume.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from brains.nets import MODELS
from orchestrator.cli.errors import EXIT_INTERRUPTED, EXIT_OK, UsageError
from orchestrator.cli.ray import parse_ray_resources


class HyperError(ValueError):
    """A malformed --hyper item."""


def add(subparsers: argparse._SubParsersAction) -> None:
    """Add ``train`` to the ``drivebench`` sub-commands."""
    parser = subparsers.add_parser(
        "train",
        help="train a network on a dataset folder (needs torch)",
        description="Train one of the paper's networks on a dataset built with 'drivebench dataset build|collect'.",
    )
    parser.add_argument("--model", required=True, metavar="NAME", help=f"network: {', '.join(MODELS)}")
    parser.add_argument("--data", required=True, type=Path, metavar="DIR", help="dataset folder")
    parser.add_argument(
        "-o",
        "--output",
        required=True,
        type=Path,
        metavar="RUN_DIR",
        help="run folder: model.ckpt (best), last.ckpt, metrics.json, curve.png",
    )
    _add_optimiser_options(parser)
    _add_sampling_options(parser)
    restart = parser.add_mutually_exclusive_group()
    restart.add_argument("--resume", action="store_true", help="continue the run in RUN_DIR from its last.ckpt")
    restart.add_argument("--overwrite", action="store_true", help="replace a run already in RUN_DIR")
    add_seed_options(parser)
    parser.set_defaults(func=run_train)


def _add_optimiser_options(parser: argparse.ArgumentParser) -> None:
    """How the network is optimised: epochs, batches, learning rate, device, seed, early stop, labels, hyper."""
    parser.add_argument("--epochs", type=int, default=50, help="maximum epochs (default 50)")
    parser.add_argument("--batch-size", type=int, default=64, help="samples per batch (default 64)")
    parser.add_argument("--lr", type=float, default=1e-3, help="Adam learning rate (default 1e-3)")
    parser.add_argument(
        "--device",
        choices=("auto", "cpu", "cuda"),
        default="auto",
        help="auto = cuda if available, else cpu (default auto)",
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of weights, sampling and augmentation (default 0)")
    parser.add_argument(
        "--patience",
        type=int,
        default=10,
        help="stop after this many epochs without a lower validation loss (default 10)",
    )
    parser.add_argument(
        "--labels",
        choices=("zscore", "paper"),
        default="zscore",
        help="label normalisation: zscore with the train split's mean/std (default) or the paper's fixed ranges",
    )
    parser.add_argument(
        "--hyper",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="model constructor option, e.g. --hyper clean=true, --hyper lstm_units=16 (repeatable)",
    )


def _add_sampling_options(parser: argparse.ArgumentParser) -> None:
    """What each epoch sees: threads, epoch length, subset, augmentation, balance, crop check."""
    parser.add_argument("--threads", type=int, help="torch CPU threads (default: torch's)")
    parser.add_argument(
        "--max-samples-per-epoch",
        type=int,
        metavar="N",
        help="shorter epochs: N weighted draws instead of the train split's size",
    )
    parser.add_argument(
        "--limit-train-samples",
        type=int,
        metavar="N",
        help="train on a fixed random subset of N training samples only (overfitting sanity check)",
    )
    parser.add_argument(
        "--no-augment",
        dest="augment",
        action="store_false",
        help="no mirror / colour jitter / blur on training batches",
    )
    parser.add_argument(
        "--augment-noise",
        type=float,
        default=0.0,
        metavar="DENSITY",
        help="also salt and pepper noise of density up to DENSITY on half the training samples (default 0: off)",
    )
    parser.add_argument(
        "--no-balance",
        dest="balance",
        action="store_false",
        help="uniform sampling instead of 1/frequency of the |yaw rate| bin",
    )
    parser.add_argument(
        "--any-crop",
        action="store_true",
        help="train on a dataset whose crop is not the network's (the checkpoint records it; serving applies it)",
    )


def add_seed_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--seeds",
        metavar="LIST",
        help="train once per seed (0-4, or 0,2,7) into RUN_DIR/seed-N with RUN_DIR/training.json; run again to "
        "keep finished seeds and resume interrupted ones (a matrix names them all: weights: RUN_DIR/seed-*/model.ckpt)",
    )
    parser.add_argument(
        "--workers", type=int, default=1, metavar="N", help="with --seeds: train N seeds at once (default 1)"
    )
    parser.add_argument(
        "--ray",
        metavar="ADDRESS",
        help="with --seeds: one Ray task per seed on the cluster at ADDRESS (auto, HOST:PORT, ray://HOST:10001); "
        "nodes need drivebench and the dataset at the same path",
    )
    parser.add_argument(
        "--ray-resource",
        action="append",
        default=[],
        metavar="NAME=AMOUNT",
        help="with --ray: what one seed's task asks for besides one CPU, e.g. GPU=1 (repeatable)",
    )


def recipe_options(args: argparse.Namespace) -> list[str]:
    """The command's options that make the recipe: every option but the seed, the output and restarts."""
    recipe = ["--model", args.model, "--data", str(args.data), "--epochs", str(args.epochs)]
    recipe += ["--batch-size", str(args.batch_size), "--lr", repr(args.lr), "--device", args.device]
    recipe += ["--patience", str(args.patience), "--labels", args.labels]
    recipe += [f"--hyper={item}" for item in args.hyper]
    for flag, value in (
        ("--threads", args.threads),
        ("--max-samples-per-epoch", args.max_samples_per_epoch),
        ("--limit-train-samples", args.limit_train_samples),
    ):
        if value is not None:
            recipe += [flag, str(value)]
    recipe += ["--augment-noise", repr(args.augment_noise)]
    recipe += [flag for flag, on in (("--no-augment", not args.augment), ("--no-balance", not args.balance)) if on]
    return recipe + (["--any-crop"] if args.any_crop else [])


def run_seeds(args: argparse.Namespace) -> int:
    """``train --seeds``: one run per seed (orchestrator.seeds), each its own ``drivebench train`` process."""
    from orchestrator.seeds import (
        RecipeChangedError,
        SeedsError,
        check_recipe,
        manifest_base,
        parse_seeds,
        train_seeds,
    )

    try:
        seeds = parse_seeds(args.seeds)
    except SeedsError as error:
        raise UsageError(str(error)) from None
    if args.seed != 0 or args.resume or args.overwrite:
        raise UsageError("--seeds trains every seed it names and resumes by itself: drop --seed, --resume, --overwrite")
    if args.workers < 1:
        raise UsageError(f"--workers must be >= 1, got {args.workers}")
    if not args.data.is_dir():
        raise UsageError(f"--data {args.data}: no such dataset folder")
    resources = _ray_resources(args)
    if args.ray is not None:
        args.data = args.data.resolve()  # the nodes read it at the same path, whatever their working folder
    recipe = recipe_options(args)
    try:
        check_recipe(args.output, recipe=recipe, data=args.data)
    except RecipeChangedError as error:
        raise UsageError(str(error)) from None
    if args.ray is None:
        runs = train_seeds(
            seeds=seeds, output=args.output, recipe=recipe, data=args.data, workers=args.workers, log=_log
        )
    else:
        from orchestrator.seeds_ray import train_seeds_on_ray

        args.output.mkdir(parents=True, exist_ok=True)
        runs = train_seeds_on_ray(
            seeds=seeds,
            output=args.output,
            recipe=recipe,
            base=manifest_base(seeds=seeds, recipe=recipe, data=args.data),
            address=args.ray,
            resources=resources,
            log=_log,
        )
    failed = [run for run in runs if run.status != "done"]
    print(f"{args.output / 'training.json'}: {len(runs) - len(failed)} of {len(runs)} seeds trained")
    for run in failed:
        print(f"seed {run.seed}: {run.status}; see {run.log}", file=sys.stderr)
    return EXIT_INTERRUPTED if any(run.status == "interrupted" for run in failed) else (1 if failed else EXIT_OK)


def _ray_resources(args: argparse.Namespace) -> dict[str, float]:
    """``--ray-resource NAME=AMOUNT`` items as a mapping; UsageError (one line) for a mistake."""
    if args.ray is None:
        if args.ray_resource:
            raise UsageError("--ray-resource goes with --ray ADDRESS")
        return {}
    if not args.ray.strip():
        raise UsageError("--ray needs an address: auto, HOST:PORT or ray://HOST:10001")
    if args.workers != 1:
        raise UsageError("--workers is for a local run: on Ray, the nodes' CPUs set how many seeds train at once")
    try:
        return parse_ray_resources(args.ray_resource, example="GPU=1")
    except ValueError as error:
        raise UsageError(str(error)) from None


def parse_hyper(items: list[str]) -> dict[str, Any]:
    """["clean=true", "lstm_units=16"] -> {"clean": True, "lstm_units": 16}; HyperError for a malformed item."""
    hyper: dict[str, Any] = {}
    for item in items:
        key, sep, text = item.partition("=")
        if not sep or not key.strip().isidentifier():
            raise HyperError(f"--hyper must look like KEY=VALUE, got {item!r}")
        hyper[key.strip()] = _value(text.strip())
    return hyper


def _value(text: str) -> bool | int | float | str:
    if text.lower() in ("true", "false"):
        return text.lower() == "true"
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def run_train(args: argparse.Namespace) -> int:
    """Run ``drivebench train``; errors are one line on stderr, never a traceback."""
    if args.seeds is not None:
        return run_seeds(args)
    if args.workers != 1 or args.ray is not None:
        raise UsageError("--workers and --ray go with --seeds (one training run uses --threads)")
    try:
        from brains.training import trainer as training
    except ImportError as error:
        raise UsageError(f"training needs torch ({error}); install the 'ml' extra") from None
    try:
        options = training.TrainOptions(
            model=args.model,
            data=args.data,
            output=args.output,
            epochs=args.epochs,
            batch_size=args.batch_size,
            lr=args.lr,
            device=args.device,
            seed=args.seed,
            patience=args.patience,
            labels=args.labels,
            hyper=parse_hyper(args.hyper),
            threads=args.threads,
            max_samples_per_epoch=args.max_samples_per_epoch,
            limit_train_samples=args.limit_train_samples,
            augment=args.augment,
            augment_noise=args.augment_noise,
            balance=args.balance,
            resume=args.resume,
            overwrite=args.overwrite,
            any_crop=args.any_crop,
        )
        result = training.train(options, progress=sys.stderr.isatty(), log=_log)
    except training.TrainInterrupted as stop:
        print(
            f"drivebench: interrupted in epoch {stop.epoch} after batch {stop.batch}; saved {stop.last_checkpoint}; "
            f"run the same command with --resume to continue",
            file=sys.stderr,
        )
        return EXIT_INTERRUPTED
    except KeyboardInterrupt:  # while loading, or a second Ctrl-C: nothing saved beyond the last epoch
        print(
            f"drivebench: interrupted; {args.output / 'last.ckpt'} (if any) holds the last completed epoch",
            file=sys.stderr,
        )
        return EXIT_INTERRUPTED
    except (training.TrainError, HyperError) as error:
        raise UsageError(str(error)) from None
    print(_summary(result))
    return EXIT_OK


def _log(line: str) -> None:
    from tqdm import tqdm

    tqdm.write(line, file=sys.stderr)  # does not break a progress bar that is on screen


def _summary(result) -> str:
    metrics = result.metrics
    scores = metrics["val"] or metrics["train"]
    where = "val" if metrics["val"] else "train (no val split)"
    return (
        f"{result.checkpoint}: best epoch {result.best_epoch} of {result.epochs_run}; {where} MAE "
        f"v {scores['mae_speed_mps']:.3f} m/s, w {scores['mae_yaw_rate_radps']:.3f} rad/s, "
        f"MSE {scores['mse_normalised']:.4f} (normalised); {result.samples_per_s:.0f} training samples/s"
    )


__all__ = ["HyperError", "add", "parse_hyper", "run_train"]
