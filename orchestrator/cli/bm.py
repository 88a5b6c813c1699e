"""``drivebench bm import CONFIG.yml -o matrix.yaml``: a Behavior Metrics experiment config as a drivebench matrix.

    drivebench bm import configs/gazebo/torch-multiple.yml -o bm.yaml --bm-root ~/BehaviorMetrics
    drivebench matrix bm.yaml

Brains x worlds x repetitions, BM's timeouts, ``ImageTranform`` as the perturbation, every BM F1 world launch name
as a circuit and a world variation (``orchestrator.matrix.bm_config``). The keys drivebench cannot honour are
printed once each (and kept as comments in the matrix). Exit 2 with one line for a config it cannot convert.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import yaml

from orchestrator.cli.errors import EXIT_OK, UsageError


def add(commands: argparse._SubParsersAction) -> None:
    bm = commands.add_parser("bm", help="Behavior Metrics compatibility: convert its experiment configs")
    actions = bm.add_subparsers(dest="bm_command", required=True)
    convert = actions.add_parser(
        "import",
        help="turn a Behavior Metrics experiment config (YAML) into a drivebench matrix file",
        description="Write a drivebench matrix from a Behavior Metrics config: its BrainPath brains x its worlds x "
        "its repetitions, with its timeouts, Parameters (each brain's config) and ImageTranform (the perturbation).",
    )
    convert.add_argument("config", type=Path, help="Behavior Metrics config (configs/gazebo/*.yml)")
    convert.add_argument("-o", "--out", type=Path, required=True, help="matrix file to write (YAML)")
    convert.add_argument(
        "--bm-root",
        type=Path,
        metavar="PATH",
        help="your BehaviorMetrics checkout: relative BrainPaths start at its behavior_metrics folder, and the "
        "brains get it as bm_root (for their imports of brains.gazebo... and utils...)",
    )
    convert.add_argument("--overwrite", action="store_true", help="replace the matrix file if it exists")
    convert.set_defaults(func=command_import)


def command_import(args: argparse.Namespace) -> int:
    from brains.behavior_metrics.checkout import find_bm_root
    from brains.registry import BrainOptionsError
    from orchestrator.matrix.bm_config import BMConfigError, convert_bm_config

    if args.out.exists() and not args.overwrite:
        raise UsageError(f"{args.out} exists (give --overwrite to replace it)")
    try:
        data = yaml.safe_load(args.config.read_text())
    except OSError as error:
        raise UsageError(f"{args.config}: {error.strerror or error}") from None
    except yaml.YAMLError as error:
        raise UsageError(f"{args.config} is not YAML: {str(error).splitlines()[0]}") from None
    try:
        root = find_bm_root(str(args.bm_root)) if args.bm_root is not None else None
        conversion = convert_bm_config(
            data,
            config_path=args.config.resolve(),
            out_path=args.out.resolve(),
            bm_root=root,
            bm_root_option=str(args.bm_root.resolve()) if args.bm_root is not None else None,
        )
    except (BMConfigError, BrainOptionsError) as error:
        raise UsageError(f"{args.config}: {error}") from None
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(conversion.text(source=str(args.config)))
    for line in conversion.dropped:
        print(f"drivebench bm import: not converted: {line}", file=sys.stderr)
    for line in conversion.notes:
        print(f"drivebench bm import: note: {line}", file=sys.stderr)
    matrix = conversion.matrix
    episodes = len(matrix["brains"]) * len(matrix["parts"]) * matrix["repetitions"]
    print(
        f"wrote {args.out}: {len(matrix['brains'])} brain(s) x {len(matrix['parts'])} world(s) x "
        f"{matrix['repetitions']} repetition(s) = {episodes} episode(s); run it with: drivebench matrix {args.out}",
        file=sys.stderr,
    )
    return EXIT_OK
