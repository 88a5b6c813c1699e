"""Short forms of world variations, camera presets and noise stages, for command lines and matrix files.

    apply_variation(spec, "line=white,road=white,walls=off,camera=left,lighting=no_sun,direction=reverse")
    apply_variation(spec, "start_m=120")  ->  the car starts 120 m along the circuit (checked against its length
        where the circuit is loaded: ``Circuit.check_start_m``)
    apply_variation(spec, "look=gazebo")  ->  then check_look(spec) once the renderer is known
    noise_stage("salt_pepper=0.2")  ->  SaltPepper(probability=0.2)
    noise_stage("rain")  ->  Rain()   (Behavior Metrics' perturbations take no parameters)
    noise_stage({"occlusion": {"patches": 2, "size_fraction": 0.3}})

Every mistake raises :class:`VariationError` naming the key or model and what is allowed.
"""

from __future__ import annotations

import math
from typing import Any

import msgspec
import yaml

from protocol.episode_spec import (
    DIRECTIONS,
    LOOK_RENDERERS,
    LOOKS,
    NOISE_MODELS,
    EpisodeSpec,
    NoiseStage,
    WorldVariation,
)
from protocol.suggest import did_you_mean


class VariationError(ValueError):
    pass


# Behavior Metrics' camera-offset worlds (simple circuit), relative to the default mount. As in BM, the rotated
# cameras are also shifted 0.20 m right (a copy-paste quirk of those worlds, kept so results compare).
CAMERA_PRESETS: dict[str, dict[str, float]] = {
    "default": {},
    "left": {"lateral_offset_m": 0.20},
    "right": {"lateral_offset_m": -0.20},
    "rotate_down": {"lateral_offset_m": -0.20, "pitch_down_rad": 0.2},
    "rotate_up": {"lateral_offset_m": -0.20, "pitch_down_rad": -0.2},
}

# variation key -> CameraSpec field, for explicit camera values
_CAMERA_KEYS = {
    "camera_offset_m": "lateral_offset_m",
    "camera_height_m": "height_m",
    "camera_pitch_rad": "pitch_down_rad",
    "camera_yaw_rad": "yaw_rad",
    "camera_hfov_rad": "hfov_rad",
}
_WORLD_KEYS = ("line", "road", "walls", "lighting", "look")
WORLD_KEYS: tuple[str, ...] = _WORLD_KEYS  # variation keys that change the world
CAMERA_KEYS: tuple[str, ...] = ("camera", *_CAMERA_KEYS)  # variation keys that move the camera
# Variation keys that change the route driven, not the pictures: which way round, and where along it the car starts.
ROUTE_KEYS: tuple[str, ...] = ("direction", "start_m")
_BOOLEAN = {"on": True, "off": False, "true": True, "false": False, "yes": True, "no": False}

# The parameter a bare ``model=value`` sets.
_PRIMARY = {
    "salt_pepper": "probability",
    "gaussian": "sigma",
    "blur": "kernel_px",
    "brightness": "brightness",
    "occlusion": "patches",
    "jpeg": "quality",
    "delay": "frames",
    "drop": "probability",
}
_MODELS: dict[str, Any] = {str(model.__struct_config__.tag): model for model in NOISE_MODELS}
_VARIATION_NAMES = (*_WORLD_KEYS, "camera", *_CAMERA_KEYS, *ROUTE_KEYS)


def parse_pairs(text: str) -> list[tuple[str, str]]:
    """``"a=1,b=2"`` -> [("a", "1"), ("b", "2")]."""
    pairs = []
    for item in (part.strip() for part in text.split(",")):
        if not item:
            continue
        key, sep, value = item.partition("=")
        if not sep or not key.strip() or not value.strip():
            raise VariationError(f"{item!r} must look like key=value")
        pairs.append((key.strip(), value.strip()))
    return pairs


def apply_variation(spec: EpisodeSpec, text: str | dict[str, Any]) -> EpisodeSpec:
    """The spec with world and camera variations applied (``"line=white,walls=off,camera=left"`` or a mapping)."""
    pairs = parse_pairs(text) if isinstance(text, str) else [(str(k), v) for k, v in text.items()]
    world = msgspec.structs.asdict(spec.world)
    camera = msgspec.structs.asdict(spec.camera)
    direction, start_m = spec.direction, spec.start_m
    for key, value in pairs:
        if key == "direction":
            if value not in DIRECTIONS:
                raise VariationError(
                    f"direction must be one of {', '.join(DIRECTIONS)}, got {value!r}" + did_you_mean(value, DIRECTIONS)
                )
            direction = value
        elif key == "start_m":
            start_m = _start_m(value)
        elif key == "walls":
            walls = _BOOLEAN.get(str(value).lower()) if not isinstance(value, bool) else value
            if walls is None:
                raise VariationError(f"walls must be on or off, got {value!r}")
            world["walls"] = walls
        elif key == "look" and value not in LOOKS:
            raise VariationError(f"unknown look {value!r} (looks: {', '.join(LOOKS)})" + did_you_mean(value, LOOKS))
        elif key in _WORLD_KEYS:
            world[key] = str(value)
        elif key == "camera":
            if value not in CAMERA_PRESETS:
                raise VariationError(
                    f"unknown camera preset {value!r} (known: {', '.join(CAMERA_PRESETS)})"
                    + did_you_mean(value, CAMERA_PRESETS)
                )
            camera.update({field: camera[field] + delta for field, delta in CAMERA_PRESETS[value].items()})
        elif key in _CAMERA_KEYS:
            camera[_CAMERA_KEYS[key]] = _number(key, value)
        else:
            raise VariationError(
                f"unknown variation {key!r} (known: {', '.join(_VARIATION_NAMES)})"
                + did_you_mean(key, _VARIATION_NAMES)
            )
    try:
        return msgspec.structs.replace(
            spec,
            direction=direction,
            start_m=start_m,
            world=msgspec.convert(world, WorldVariation),
            camera=msgspec.convert(camera, type(spec.camera)),
        )
    except msgspec.ValidationError as error:
        raise VariationError(str(error)) from None


def check_look(spec: EpisodeSpec) -> None:
    """VariationError (one line naming the choices) when ``spec.renderer`` cannot draw ``spec.world.look``."""
    look, renderer = spec.world.look, spec.renderer
    if renderer not in LOOK_RENDERERS[look]:
        raise VariationError(
            f"look={look} needs renderer {' or '.join(LOOK_RENDERERS[look])}, got renderer {renderer} "
            f"(looks: {', '.join(LOOKS)}; renderer {renderer} draws look="
            f"{', '.join(name for name, renderers in LOOK_RENDERERS.items() if renderer in renderers)})"
        )


def noise_stage(item: str | dict[str, Any]) -> NoiseStage:
    """One noise stage from ``"model"``, ``"model=value"``, ``"model:key=value,key=value"``, ``{model: value}`` or
    ``{model: {key: value}}``; the bare value sets the model's main parameter (see ``_PRIMARY``)."""
    if isinstance(item, str):
        model, sep, rest = item.partition(":")
        if sep:
            params: Any = {key: yaml.safe_load(value) for key, value in parse_pairs(rest)}
        else:
            model, sep, value = item.partition("=")
            params = yaml.safe_load(value) if sep else {}
        item = {model.strip(): params}
    if not isinstance(item, dict) or len(item) != 1:
        raise VariationError(f"a noise stage is one model with its parameters, got {item!r}")
    ((model, params),) = item.items()
    if model not in _MODELS:
        raise VariationError(
            f"unknown noise model {model!r} (known: {', '.join(_MODELS)})" + did_you_mean(model, _MODELS)
        )
    if params is None:
        params = {}
    if not isinstance(params, dict):
        if model not in _PRIMARY:  # Behavior Metrics' perturbations: BM's fixed parameters, no value to give
            raise VariationError(f"noise model {model} takes no value (write it alone: {model!r}), got {params!r}")
        params = {_PRIMARY[model]: params}
    try:
        return msgspec.convert(params, _MODELS[model])
    except msgspec.ValidationError as error:
        raise VariationError(f"noise model {model}: {error}") from None


def _start_m(value: Any) -> float:
    """A start along the circuit, metres: a number >= 0 (its upper bound, the circuit's length, is checked where the
    circuit is known)."""
    start_m = _number("start_m", value) if not isinstance(value, bool) else math.nan  # YAML's yes/no is no distance
    if not start_m >= 0:  # also refuses NaN
        raise VariationError(f"start_m must be a number of metres >= 0, got {value!r}")
    return start_m


def _number(key: str, value: Any) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        raise VariationError(f"{key} must be a number, got {value!r}") from None
