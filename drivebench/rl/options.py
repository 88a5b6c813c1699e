"""The environment's keyword arguments, checked before anything starts: each mistake is one ValueError that names
the argument and what is allowed (Gymnasium's convention: an exception, never a process exit)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import msgspec
import numpy as np

from circuits import Circuit, CircuitError, load_circuit
from protocol.episode_spec import CameraSpec, EpisodeSpec, NoiseStage
from protocol.variations import VariationError, apply_variation, noise_stage

OBSERVATIONS = ("image", "image+state", "features")
# Where each episode's car starts: "line", the spec's start_m (0, the start line, unless a variation sets it); or
# "random", anywhere along the circuit, drawn from reset's seed (random starts keep a policy from fitting the first
# corner).
STARTS = ("line", "random")


@dataclass(frozen=True)
class EnvOptions:
    """What the keyword arguments resolved to. ``specs``: one base episode spec per variation (circuit, seed and
    brain are filled in per episode); ``circuits``: the circuits an episode is drawn from."""

    circuits: tuple[str, ...]
    specs: tuple[EpisodeSpec, ...]
    observation: str
    speed_range_mps: tuple[float, float]
    yaw_rate_range_radps: tuple[float, float]
    start: str = "line"


def as_names(value: Any, *, what: str) -> tuple[str, ...]:
    """A name or a non-empty list of names."""
    names = (value,) if isinstance(value, str) else tuple(value) if isinstance(value, Sequence) else ()
    if not names or not all(isinstance(name, str) for name in names):
        raise ValueError(f"{what} must be a name or a non-empty list of names, got {value!r}")
    return names


def camera_spec(camera: Any) -> CameraSpec:
    """``(width_px, height_px)``, ``"WxH"`` or a CameraSpec."""
    if isinstance(camera, CameraSpec):
        return camera
    try:
        width, height = (int(v) for v in camera.lower().split("x")) if isinstance(camera, str) else camera
        return CameraSpec(width_px=int(width), height_px=int(height))
    except (TypeError, ValueError) as error:
        raise ValueError(f"camera must be (width_px, height_px) or 'WxH' within 8..4096, got {camera!r}: {error}")


def value_range(value: Any, *, what: str) -> tuple[float, float]:
    try:
        low, high = (float(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be (low, high), got {value!r}") from None
    if not (math.isfinite(low) and math.isfinite(high) and low < high):
        raise ValueError(f"{what} must be finite with low < high, got {value!r}")
    return low, high


GENERATED = (
    "random:*",
    "twisty:*",
    "grandprix:*",
)  # a fresh generated circuit per episode, its seed drawn from reset's seed


def start_m_option(value: Any, circuit: Circuit) -> float:
    """``reset(options={"start_m": ...})``: metres along ``circuit`` from its start line, in driving order."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"reset options: start_m must be a number of metres, got {value!r}")
    try:
        circuit.check_start_m(float(value))
    except CircuitError as error:
        raise ValueError(f"reset options: {error}") from None
    return float(value)


def check_circuits(names: tuple[str, ...]) -> None:
    for name in names:
        try:
            load_circuit(name.replace(":*", ":0") if name in GENERATED else name)
        except CircuitError as error:
            raise ValueError(f"circuit={name!r}: {error}") from None


def check_starts(circuits: tuple[str, ...], *, variations: tuple[str, ...], specs: tuple[EpisodeSpec, ...]) -> None:
    """A variation's start_m must lie on every named circuit (a generated one is checked when it is drawn)."""
    for text, spec in zip(variations, specs):
        for name in (name for name in circuits if spec.start_m and name not in GENERATED):
            try:
                load_circuit(name).check_start_m(spec.start_m)
            except CircuitError as error:
                raise ValueError(f"variation={text!r}: {error}") from None


def check_one_start(start: str, *, variations: tuple[str, ...], specs: tuple[EpisodeSpec, ...]) -> None:
    """``start="random"`` and a variation's ``start_m`` are two answers to where the car starts (the random draw
    used to win without a word): ValueError naming both."""
    if start != "random":
        return
    for text, spec in zip(variations, specs):
        if spec.start_m:
            raise ValueError(
                f"start='random' draws each episode's start, and variation={text!r} sets one: give one of them"
            )


def base_specs(*, variations: tuple[str, ...], camera: Any, renderer: str, noise: Any, **spec_fields) -> tuple:
    """One base spec per variation; ValueError naming the argument on any bad value."""
    try:
        stages: list[NoiseStage] = [noise_stage(item) for item in ([noise] if isinstance(noise, str) else noise)]
    except (VariationError, TypeError) as error:
        raise ValueError(f"noise={noise!r}: {error}") from None
    try:
        base = EpisodeSpec(camera=camera_spec(camera), renderer=renderer, noise=stages, **spec_fields)
    except (ValueError, msgspec.ValidationError) as error:
        raise ValueError(f"bad episode settings: {error}") from None
    specs = []
    for text in variations:
        try:
            specs.append(apply_variation(base, text))
        except VariationError as error:
            raise ValueError(f"variation={text!r}: {error}") from None
    return tuple(specs)


def env_options(
    *,
    circuit: Any,
    variation: Any,
    noise: Any,
    camera: Any,
    renderer: str,
    observation: str,
    speed_range_mps: Any,
    yaw_rate_range_radps: Any,
    start: str = "line",
    **spec_fields,
) -> EnvOptions:
    """Check every keyword argument of the environment; ValueError (one line, naming it) on the first bad one."""
    circuits = as_names(circuit, what="circuit")
    check_circuits(circuits)
    if observation not in OBSERVATIONS:
        raise ValueError(f"observation must be one of {', '.join(OBSERVATIONS)}, got {observation!r}")
    if start not in STARTS:
        raise ValueError(f"start must be one of {', '.join(STARTS)}, got {start!r}")
    variations = as_names(variation, what="variation")
    specs = base_specs(variations=variations, camera=camera, renderer=renderer, noise=noise, **spec_fields)
    check_starts(circuits, variations=variations, specs=specs)
    check_one_start(start, variations=variations, specs=specs)
    return EnvOptions(
        circuits=circuits,
        specs=specs,
        observation=observation,
        speed_range_mps=value_range(speed_range_mps, what="speed_range_mps"),
        yaw_rate_range_radps=value_range(yaw_rate_range_radps, what="yaw_rate_range_radps"),
        start=start,
    )


def check_render_threads(render_threads: Any, *, router: str | None) -> None:
    """ValueError (one line) unless ``render_threads`` is an integer >= 1 that this environment can apply: only to a
    stack of its own (with ``router`` the running stack's simulator renders as it was started)."""
    if isinstance(render_threads, bool) or not isinstance(render_threads, int) or render_threads < 1:
        raise ValueError(f"render_threads must be an integer >= 1, got {render_threads!r}")
    if router is not None and render_threads != 1:
        raise ValueError(
            f"render_threads={render_threads} needs the environment's own stack: with router= the running stack's "
            "simulator renders as it was started"
        )
