"""``drivebench export`` (a checkpoint to ONNX, checked against PyTorch) and ``drivebench pack`` (a checkpoint in
its packed, git-friendly form). Torch and onnx are imported only when one runs."""

from __future__ import annotations

import argparse
from pathlib import Path

from orchestrator.cli.errors import EXIT_OK, UsageError


def add(subparsers: argparse._SubParsersAction) -> None:
    """``export CKPT -o model.onnx [--opset 17] [--parity-batch 4]`` and ``pack CKPT -o OUT.ckpt [--float32]
    [--shard-mb 9] [--parity-batch 4]``."""
    export = subparsers.add_parser("export", help="export a trained checkpoint to ONNX and check it against PyTorch")
    export.add_argument("checkpoint", type=Path, help="drivebench.checkpoint.v1 file")
    export.add_argument("-o", "--output", type=Path, required=True, help="ONNX file to write")
    export.add_argument("--opset", type=int, default=17, help="ONNX opset (default 17)")
    export.add_argument("--parity-batch", type=int, default=4, help="batch of random inputs for the parity check")
    export.set_defaults(func=run_export)
    pack = subparsers.add_parser("pack", help="write a checkpoint in the packed, git-friendly form (float16 shards)")
    pack.add_argument("checkpoint", type=Path, help="drivebench.checkpoint.v1 file (packed or not)")
    pack.add_argument(
        "-o",
        "--output",
        type=Path,
        required=True,
        help="packed checkpoint to write (its shards OUT.shard0, OUT.shard1, ... go beside it)",
    )
    pack.add_argument("--float32", action="store_true", help="keep float32 weights (default: float16, half the size)")
    pack.add_argument(
        "--shard-mb",
        type=float,
        default=9.0,
        metavar="MIB",
        help="most MiB per shard file (default 9: every file stays under 10 MB)",
    )
    pack.add_argument("--parity-batch", type=int, default=4, help="batch of random inputs for the output check")
    pack.set_defaults(func=run_pack)


def run_export(args: argparse.Namespace) -> int:
    """Export, then print the measured parity. 0 on success, 2 (one line on stderr) for a bad checkpoint."""
    _check_parity_batch(args)  # before the file is written: a bad value must not leave an unchecked export behind
    return _reporting_errors("export needs torch, onnx and onnxruntime", args.output, lambda: _export(args))


def _check_parity_batch(args: argparse.Namespace) -> None:
    if args.parity_batch < 1:
        raise UsageError(f"--parity-batch must be >= 1, got {args.parity_batch}")


def _export(args: argparse.Namespace) -> int:
    from brains.neural.export import check_parity, export_onnx

    out = export_onnx(args.checkpoint, args.output, opset=args.opset)
    parity = check_parity(args.checkpoint, out, batch=args.parity_batch)
    size_mb = out.stat().st_size / 1e6
    print(
        f"wrote {out} ({size_mb:.1f} MB, opset {args.opset}); "
        f"max |onnxruntime - torch| = {parity:.2e} over {args.parity_batch} random inputs"
    )
    return EXIT_OK


def _reporting_errors(needs: str, output: Path, action) -> int:
    """``action()``, with a missing library, a bad checkpoint or an unwritable output as one line and exit code 2."""
    from brains.neural.checkpoint import CheckpointError

    try:
        return action()
    except ImportError as error:
        message = f"{needs} ({error})"
    except CheckpointError as error:
        message = str(error)
    except OSError as error:
        message = f"cannot write {output}: {error.strerror or error}"
    raise UsageError(message)


def run_pack(args: argparse.Namespace) -> int:
    """Pack, then print the files, their sizes and the measured output difference. 0 on success, 2 (one line on
    stderr) for a bad checkpoint or option."""
    shard_bytes = int(args.shard_mb * 2**20)
    if shard_bytes < 1:
        raise UsageError(f"--shard-mb must be > 0, got {args.shard_mb}")
    _check_parity_batch(args)
    if args.output.resolve() == args.checkpoint.resolve():
        raise UsageError(f"{args.output}: write the packed form to another file than the original")
    return _reporting_errors("pack needs torch", args.output, lambda: _pack(args, shard_bytes))


def _pack(args: argparse.Namespace, shard_bytes: int) -> int:
    from brains.neural.checkpoint import pack_checkpoint
    from brains.neural.export import pack_difference

    written = pack_checkpoint(args.checkpoint, args.output, half=not args.float32, shard_bytes=shard_bytes)
    difference = pack_difference(args.checkpoint, args.output, batch=args.parity_batch)
    for path in written:
        size = path.stat().st_size
        print(f"wrote {path} ({size / 1e6:.2f} MB)" if size >= 10_000 else f"wrote {path} ({size} bytes)")
    total = sum(path.stat().st_size for path in written)
    print(
        f"{len(written)} files, {total / 1e6:.1f} MB in all (original {args.checkpoint.stat().st_size / 1e6:.1f} MB, "
        f"{'float32' if args.float32 else 'float16'}); max |packed - original| = {difference:.2e} over "
        f"{args.parity_batch} random inputs"
    )
    return EXIT_OK
