"""``drivebench dataset collect``: the paper's data generation in one step.

Drive a brain (the explicit one by default) round each circuit on a local stack with a recorder, one recording per
circuit, then build a dataset from the recordings. With ``--recovery-noise`` a noisy copy of the brain drives and the
brain itself only labels (it answers the same frames as a second brain host), so the dataset shows how to come back
to the line.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import uuid
from pathlib import Path

import msgspec
import numpy as np

from circuits import CircuitError, load_circuit
from orchestrator.stack.launcher import BrainLaunch, LocalStack, render_threads_for
from orchestrator.stack.progress import EpisodeProgress
from protocol import environment
from protocol.episode_spec import CameraSpec, EpisodeSpec
from protocol.variations import apply_variation, check_look, noise_stage
from services.simulator.renderers import choose_renderer

DRIVER = "driver"  # bus name of the noisy driver when collecting recovery data
# Without --renderer or $DRIVEBENCH_RENDERER: auto, gl where EGL works (parity: docs/guides/renderers.md).
COLLECT_RENDERER = environment.RENDERER_BY_COMMAND["dataset collect"]


def collection_brains(args: argparse.Namespace) -> list[BrainLaunch]:
    brains = [BrainLaunch(args.brain)]
    if args.recovery_noise > 0:
        brains.append(
            BrainLaunch(
                "noisy",
                name=DRIVER,
                options=(f"base={json.dumps(args.brain)}", f"steering_noise_radps={args.recovery_noise}"),
            )
        )
    return brains


class CollectError(ValueError):
    """A bad collect request (unknown circuit, bad variation): one line."""


def collection_specs(args: argparse.Namespace) -> list[EpisodeSpec]:
    circuits = [name.strip() for name in args.circuits.split(",") if name.strip()]
    if not circuits:
        raise CollectError("--circuits needs at least one circuit name")
    directions = ("forward", "reverse") if args.direction == "both" else (args.direction,)
    if getattr(args, "looks", None) and not getattr(args, "randomise", False):
        raise CollectError("--looks needs --randomise (without it, pin one look with --variation look=gazebo)")
    try:
        renderer = choose_renderer(getattr(args, "renderer", None), fallback=COLLECT_RENDERER)
    except ValueError as error:
        raise CollectError(str(error)) from None
    width, height = args.camera
    try:
        camera = CameraSpec(width_px=width, height_px=height)
    except ValueError as error:
        raise CollectError(f"--camera {width}x{height}: {error}") from None
    for circuit in circuits:
        try:
            load_circuit(circuit)
        except CircuitError as error:
            raise CollectError(f"--circuits {args.circuits}: {error}") from None
    specs = []
    for index, circuit in enumerate(circuits):
        for direction in directions:
            try:
                # seed = circuit index (reverse: + the circuit count) keeps forward-only collections as they were
                seed = index + (len(circuits) if direction == "reverse" else 0)
                spec = EpisodeSpec(
                    circuit=circuit,
                    laps=args.laps,
                    max_sim_seconds=args.max_sim_seconds,
                    seed=seed,
                    camera=camera,
                    active_brain=DRIVER if args.recovery_noise > 0 else args.brain,
                    direction=direction,
                    renderer=renderer,
                )
                if getattr(args, "randomise", False):
                    spec = randomised(spec, looks=tuple(getattr(args, "looks", None) or ("flat",)))
                for variation in args.variation:  # after the draw: what is pinned stays pinned
                    spec = apply_variation(spec, variation)
                check_look(spec)
                load_circuit(circuit).check_start_m(spec.start_m)  # --variation start_m=...: on this circuit
            except (CircuitError, ValueError) as error:
                raise CollectError(str(error)) from None
            specs.append(spec)
    return specs


def randomised(spec: EpisodeSpec, *, looks: tuple[str, ...] = ("flat",)) -> EpisodeSpec:
    """The spec in a world, camera mount and camera noise drawn from its seed: domain randomisation.

    Every world variation is equally likely (line red / white / none, road grey / white, walls on / off, lighting sun
    / no sun); the camera mount jitters up to 0.08 m sideways and pitches -0.03..0.22 rad down (the paper's rotated
    camera is 0.2 rad); 5 episodes in 11 see a clean camera, the others one of salt and pepper (two draws in six up
    to 0.7), Gaussian noise, blur, brightness or occlusion. The direction stays what the caller chose. The look is
    drawn from ``looks`` (equally likely) by a generator of its own, so that adding looks leaves every other draw of
    a seed as it was.

    The sideways jitter stays small on purpose: an expert labels from the car's true offset, and a camera moved
    sideways looks exactly like the car moved sideways, so a large random mount turns recovery labels into noise
    (measured: with up to 0.3 m, networks learned nothing from these data).
    """
    rng = np.random.default_rng([spec.seed, 0x5EED])
    world = {
        "line": str(rng.choice(["red", "white", "none"])),
        "road": str(rng.choice(["grey", "white"])),
        "walls": bool(rng.integers(2)),
        "lighting": str(rng.choice(["sun", "no_sun"])),
        "camera_offset_m": round(float(rng.uniform(-0.08, 0.08)), 3),
        "camera_pitch_rad": round(float(rng.uniform(-0.03, 0.22)), 3),
    }
    noises = [
        None,
        None,
        None,
        None,
        None,
        f"salt_pepper={rng.uniform(0.05, 0.7):.2f}",
        f"salt_pepper={rng.uniform(0.3, 0.7):.2f}",
        f"gaussian={rng.uniform(5, 30):.0f}",
        f"blur={int(rng.choice([3, 5, 7]))}",
        f"brightness={rng.uniform(-0.4, 0.4):.2f}",
        "occlusion:patches=2,size_fraction=0.25",
    ]
    noise = noises[int(rng.integers(len(noises)))]
    if len(looks) > 1:
        world["look"] = str(np.random.default_rng([spec.seed, 0x100C]).choice(list(looks)))
    elif looks != ("flat",):
        world["look"] = looks[0]
    spec = apply_variation(spec, world)
    return msgspec.structs.replace(spec, noise=[noise_stage(noise)] if noise else [])


def _episode_name(spec: EpisodeSpec) -> str:
    """File-name part of a collected episode: the circuit, and ``-reverse`` when driven the other way round."""
    name = spec.circuit.replace(":", "-")
    return f"{name}-reverse" if spec.direction == "reverse" else name


def collect(args: argparse.Namespace, options) -> int:
    specs = collection_specs(args)
    if args.recovery_noise > 0 and options.brain is None:
        options = dataclasses.replace(options, brain=args.brain)  # the undisturbed brain's commands are the labels
    output: Path = args.output.resolve()  # "-o ." has no name until resolved: its recordings go beside it, not in it
    if output.exists() and not output.is_dir():
        raise CollectError(f"output {args.output} exists and is not a folder")
    if output.is_dir() and any(output.iterdir()) and not args.overwrite:
        raise CollectError(
            f"output folder {args.output} is not empty (--overwrite replaces the dataset files in it and keeps the "
            f"others)"
        )
    work = output.parent / f"{output.name}.recordings"
    recordings = []
    for spec in specs:
        run_id = f"collect-{_episode_name(spec)}-{uuid.uuid4().hex[:6]}"
        recording = work / f"{_episode_name(spec)}.mcap"
        recording.unlink(missing_ok=True)
        print(
            f"collect: {spec.active_brain} on {spec.circuit} ({spec.direction}), {spec.laps} lap(s) -> {recording}",
            file=sys.stderr,
        )
        progress = EpisodeProgress(spec.laps, enabled=sys.stderr.isatty())
        try:
            with LocalStack(
                run_id=run_id,
                run_dir=work / "runs" / run_id,
                brains=collection_brains(args),
                record=recording,
                render_threads=render_threads_for(stacks=1),
            ) as stack:
                score = stack.run_episode(spec, on_live=progress.update)
        finally:
            progress.close()
        if stack.recording_failure is not None:  # a dataset must not be built on a recording short of frames
            raise CollectError(f"the recording {recording} is incomplete: {stack.recording_failure}")
        print(
            f"collect: {spec.circuit}: {score.reason}, {score.metrics.progress_laps:.2f} laps in "
            f"{score.metrics.sim_time_s:.1f} s",
            file=sys.stderr,
        )
        recordings.append(recording)
    return build_from_recordings(recordings, output=args.output, options=options, overwrite=args.overwrite)


def build_from_recordings(recordings: list[Path], *, output: Path, options, overwrite: bool) -> int:
    """A dataset in ``output`` from MCAP recordings (``drivebench dataset build``), with a summary line on stderr."""
    from recorder.dataset.build import DatasetError, build_dataset
    from recorder.reading import read_messages, recording_info

    for path in recordings:
        if output.resolve() in path.resolve().parents:
            raise DatasetError(f"output folder {output} holds the input {path}: write the dataset to another folder")
        recording_info(path)  # a missing or broken file fails before any work
    sources = [(str(path), lambda path=path: read_messages(path)) for path in recordings]
    manifest = build_dataset(
        sources, out_dir=output, options=options, progress=sys.stderr.isatty(), overwrite=overwrite
    )
    split = manifest.split
    print(
        f"dataset {output}: {manifest.totals.samples} samples from {len(recordings)} recording(s), "
        f"{manifest.totals.episodes} episode(s); train {split.train_samples} samples, val {split.val_samples} "
        f"({split.rule})",
        file=sys.stderr,
    )
    return 0
