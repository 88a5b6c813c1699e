"""ONNX export of a checkpoint (``drivebench export CKPT -o model.onnx``) and its parity check against PyTorch;
``drivebench pack CKPT -o model.ckpt`` writes the git-friendly packed form (float16 shards of at most 9 MiB,
:func:`brains.neural.checkpoint.pack_checkpoint`) and checks it against the original the same way.

The file has one input ``frames`` (float32 (B, 3, H, W), or (B, T, 3, H, W) oldest first; B is dynamic) and one
output ``command`` ((B, 2) normalised (v_n, w_n)). Its ``metadata_props`` carry the checkpoint's model, hyper,
input and normalisation as JSON (:func:`brains.neural.checkpoint.to_metadata`) and the checkpoint's sha256, so the
file serves on its own: ``python -m brains --brain memdccp --weights model.onnx`` needs onnxruntime, not torch.

Legacy TorchScript-based exporter (``dynamo=False``): all four networks export with it, and their outputs match
eager PyTorch within a few 1e-6.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import sys
import warnings
from pathlib import Path

import numpy as np

from brains.neural.checkpoint import (
    Checkpoint,
    CheckpointError,
    build_model,
    input_shape,
    load_checkpoint,
    pack_checkpoint,
    to_metadata,
)
from brains.neural.runners import OrtRunner

INPUT_NAME, OUTPUT_NAME = "frames", "command"
SOURCE_SHA256_KEY = "drivebench.source_sha256"


def file_sha256(path: str | Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as file:
        for block in iter(lambda: file.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def export_onnx(ckpt_path: str | Path, out_path: str | Path, *, opset: int = 17,
                ckpt: Checkpoint | None = None) -> Path:
    """Export checkpoint ``ckpt_path`` to ONNX at ``out_path`` (folders created); returns ``out_path``.

    ``ckpt``: the already loaded checkpoint of ``ckpt_path`` (saves loading it twice). The file is written under a
    temporary name and renamed, so a reader never sees half a file.
    """
    import onnx
    import torch

    ckpt = ckpt or load_checkpoint(ckpt_path)
    model = build_model(ckpt)
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    partial = out_path.with_name(f".{out_path.name}.{os.getpid()}.partial")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the legacy exporter's deprecation notices, once per export
            torch.onnx.export(model, (torch.zeros(input_shape(ckpt, batch=1)),), str(partial), dynamo=False,
                              opset_version=opset, input_names=[INPUT_NAME], output_names=[OUTPUT_NAME],
                              dynamic_axes={INPUT_NAME: {0: "batch"}, OUTPUT_NAME: {0: "batch"}},
                              do_constant_folding=True)
        proto = onnx.load(str(partial))
        meta = {**to_metadata(ckpt), SOURCE_SHA256_KEY: file_sha256(ckpt.path)}
        onnx.helper.set_model_props(proto, meta)
        onnx.save(proto, str(partial))
        partial.replace(out_path)
    finally:
        partial.unlink(missing_ok=True)
    return out_path


def check_parity(ckpt_path: str | Path, onnx_path: str | Path, *, batch: int = 4, seed: int = 0) -> float:
    """Max |torch eager - onnxruntime| over the (batch, 2) normalised outputs for seeded N(0, 1) inputs (which is
    what ImageNet-normalised pixels look like)."""
    import torch

    ckpt = load_checkpoint(ckpt_path)
    model = build_model(ckpt)
    x = np.random.default_rng(seed).standard_normal(input_shape(ckpt, batch=batch)).astype(np.float32)
    with torch.inference_mode():
        expected = model(torch.from_numpy(x)).numpy()
    got = OrtRunner(onnx_path, threads=1)(x)
    return float(np.max(np.abs(expected - got)))


def pack_difference(original: str | Path, packed: str | Path, *, batch: int = 4, seed: int = 0) -> float:
    """Max |original - packed| over the (batch, 2) normalised outputs for seeded N(0, 1) inputs."""
    import torch

    ckpt_a, ckpt_b = load_checkpoint(original), load_checkpoint(packed)
    x = torch.from_numpy(np.random.default_rng(seed).standard_normal(input_shape(ckpt_a, batch=batch))
                         .astype(np.float32))
    with torch.inference_mode():
        return float((build_model(ckpt_a)(x) - build_model(ckpt_b)(x)).abs().max())


# -- command line ----------------------------------------------------------------------------------------------------


def add_export_command(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add ``export CKPT -o model.onnx [--opset 17] [--parity-batch 4]``; dispatch it to :func:`run_export`."""
    export = subparsers.add_parser("export", help="export a trained checkpoint to ONNX and check it against PyTorch")
    export.add_argument("checkpoint", type=Path, help="drivebench.checkpoint.v1 file")
    export.add_argument("-o", "--output", type=Path, required=True, help="ONNX file to write")
    export.add_argument("--opset", type=int, default=17, help="ONNX opset (default 17)")
    export.add_argument("--parity-batch", type=int, default=4, help="batch of random inputs for the parity check")
    return export


def run_export(args: argparse.Namespace) -> int:
    """Export, then print the measured parity. 0 on success, 2 (one line on stderr) for a bad checkpoint."""
    return _reporting_errors("export needs torch, onnx and onnxruntime", args.output, lambda: _export(args))


def _export(args: argparse.Namespace) -> int:
    out = export_onnx(args.checkpoint, args.output, opset=args.opset)
    parity = check_parity(args.checkpoint, out, batch=args.parity_batch)
    size_mb = out.stat().st_size / 1e6
    print(f"wrote {out} ({size_mb:.1f} MB, opset {args.opset}); "
          f"max |onnxruntime - torch| = {parity:.2e} over {args.parity_batch} random inputs")
    return 0


def _reporting_errors(needs: str, output: Path, action) -> int:
    """``action()``, with a missing library, a bad checkpoint or an unwritable output as one line and exit code 2."""
    try:
        return action()
    except ImportError as error:
        message = f"{needs} ({error})"
    except CheckpointError as error:
        message = str(error)
    except OSError as error:
        message = f"cannot write {output}: {error.strerror or error}"
    print(f"drivebench: error: {message}", file=sys.stderr)
    return 2


def add_pack_command(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add ``pack CKPT -o OUT.ckpt [--float32] [--shard-mb 9] [--parity-batch 4]``; dispatch it to
    :func:`run_pack`."""
    pack = subparsers.add_parser("pack", help="write a checkpoint in the packed, git-friendly form (float16 shards)")
    pack.add_argument("checkpoint", type=Path, help="drivebench.checkpoint.v1 file (packed or not)")
    pack.add_argument("-o", "--output", type=Path, required=True,
                      help="packed checkpoint to write (its shards OUT.shard0, OUT.shard1, ... go beside it)")
    pack.add_argument("--float32", action="store_true", help="keep float32 weights (default: float16, half the size)")
    pack.add_argument("--shard-mb", type=float, default=9.0, metavar="MIB",
                      help="most MiB per shard file (default 9: every file stays under 10 MB)")
    pack.add_argument("--parity-batch", type=int, default=4, help="batch of random inputs for the output check")
    return pack


def run_pack(args: argparse.Namespace) -> int:
    """Pack, then print the files, their sizes and the measured output difference. 0 on success, 2 (one line on
    stderr) for a bad checkpoint or option."""
    shard_bytes = int(args.shard_mb * 2**20)
    if shard_bytes < 1:
        print(f"drivebench: error: --shard-mb must be > 0, got {args.shard_mb}", file=sys.stderr)
        return 2
    if args.output.resolve() == args.checkpoint.resolve():
        print(f"drivebench: error: {args.output}: write the packed form to another file than the original",
              file=sys.stderr)
        return 2
    return _reporting_errors("pack needs torch", args.output, lambda: _pack(args, shard_bytes))


def _pack(args: argparse.Namespace, shard_bytes: int) -> int:
    written = pack_checkpoint(args.checkpoint, args.output, half=not args.float32, shard_bytes=shard_bytes)
    difference = pack_difference(args.checkpoint, args.output, batch=args.parity_batch)
    for path in written:
        size = path.stat().st_size
        print(f"wrote {path} ({size / 1e6:.2f} MB)" if size >= 10_000 else f"wrote {path} ({size} bytes)")
    total = sum(path.stat().st_size for path in written)
    print(f"{len(written)} files, {total / 1e6:.1f} MB in all (original {args.checkpoint.stat().st_size / 1e6:.1f} MB, "
          f"{'float32' if args.float32 else 'float16'}); max |packed - original| = {difference:.2e} over "
          f"{args.parity_batch} random inputs")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m brains.neural.export", description=__doc__.split("\n\n")[0])
    add_export_command(parser.add_subparsers(dest="command", required=True))
    return run_export(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
