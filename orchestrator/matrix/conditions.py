"""The conditions of a matrix file: variations (a product of world and camera settings) or worlds (listed one by
one), and perturbations (camera moves and noise models), each read from the typed values of the file (with the
line of each in errors) and given the label that results and reports use."""

from __future__ import annotations

import itertools
import math
import re
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import yaml

from orchestrator.matrix.plan import DEFAULT_VARIATION, NO_PERTURBATION
from orchestrator.matrix.schema import items
from protocol.deploy.typed_yaml import Document
from protocol.deploy.typed_yaml import Path as At
from protocol.episode_spec import NOISE_MODELS, EpisodeSpec, NoiseStage
from protocol.suggest import did_you_mean

# The protocol's own lists of world and camera variation keys (it has no public name for them).
from protocol.variations import (
    CAMERA_KEYS,
    ROUTE_KEYS,
    WORLD_KEYS,
    VariationError,
    apply_variation,
    noise_stage,
    parse_pairs,
)

VARIATION_KEYS = (*WORLD_KEYS, *CAMERA_KEYS, *ROUTE_KEYS)
CAMERA_PERTURBATION_KEYS = CAMERA_KEYS
NOISE_MODEL_NAMES = tuple(str(model.__struct_config__.tag) for model in NOISE_MODELS)  # every model has a str tag
# An item of a perturbation string: "model", "model=value", "model:key=value,..." or "camera_key=value".
_STRING_ITEM = re.compile(r"\s*([A-Za-z_][A-Za-z0-9_]*)\s*(?:([=:])(.*))?", re.S)
# "+" joins items; one followed by a digit or sign belongs to a number ("1e+5", "brightness=+0.2").
_ITEM_JOIN = re.compile(r"\+(?=\s*[A-Za-z_])")


def label_text(value: Any) -> str:
    """A value as it appears in labels: booleans as on/off, floats in their shortest exact form."""
    if isinstance(value, bool):
        return "on" if value else "off"
    if isinstance(value, float):
        return repr(value)
    if value is None:
        return "none"
    return str(value)


# -- variations ----------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Axis:
    """One variation key and its values: (label text, value as apply_variation takes it, line)."""

    key: str
    values: tuple[tuple[str, Any, int], ...]


@dataclass(frozen=True)
class World:
    """One world variation: its label, the items to apply, and the label text of each key (for exclude)."""

    label: str
    items: tuple[tuple[str, Any], ...] = ()

    @property
    def texts(self) -> dict[str, str]:
        return {key: label_text(value) for key, value in self.items}


def read_variation_value(document: Document, value: Any, path: At, *, key: str) -> Any:
    if isinstance(value, (dict, list)):
        raise document.error(path, f"a value of {key} must be a single value, got {value!r}")
    _check_finite(document, path, key, value)
    try:
        apply_variation(EpisodeSpec(), {key: value})
    except VariationError as error:
        raise document.error(path, f"bad {key} value {value!r}: {error}") from None
    return value


def _is_variation_key(document: Document, path: At, key: str) -> bool:
    """Whether ``key`` is a variation key; the mistake is noted when it is not."""
    if key not in VARIATION_KEYS:
        hint = did_you_mean(key, VARIATION_KEYS)
        document.note(
            document.error(
                path, f"unknown variation key {key!r} (allowed: {', '.join(VARIATION_KEYS)}){hint}", at_key=True
            )
        )
        return False
    return True


def read_axes(document: Document, variations: dict[str, Any] | None, path: At) -> list[Axis]:
    """The axes of ``variations``, each value checked; a key or a value with a mistake is noted and left out."""
    axes = []
    for key, written in (variations or {}).items():
        if not _is_variation_key(document, (*path, key), key):
            continue  # its values cannot be checked against an unknown key
        values: dict[str, tuple[str, Any, int]] = {}
        for item, item_path in items(written, (*path, key)):
            value = document.attempt(read_variation_value, document, item, item_path, key=key)
            if value is None:  # noted (the schema lets no null through here)
                continue
            text = label_text(value)
            if text in values:
                document.note(
                    document.error(item_path, f"{key} value {text!r} is listed twice (also on line {values[text][2]})")
                )
                continue
            values[text] = (text, value, document.line(item_path))
        axes.append(Axis(key=key, values=tuple(values.values())))
    return axes


def read_worlds(axes: list[Axis]) -> list[World]:
    if not axes:
        return [World(label=DEFAULT_VARIATION)]
    return [
        read_world([(axis.key, value) for axis, (_, value, _) in zip(axes, combination)])
        for combination in itertools.product(*(axis.values for axis in axes))
    ]


def read_listed_worlds(document: Document, worlds_value: Any, path: At) -> tuple[list[World], list[Axis]]:
    """``worlds:``, a list of variation mappings: the worlds in written order, and per key the values they use
    (the axes exclude entries may name). A world with a mistake in a key or a value is noted and left out."""
    worlds: dict[str, tuple[World, int]] = {}
    values: dict[str, dict[str, tuple[str, Any, int]]] = {}
    for item, item_path in items(worlds_value, path):
        pairs = _world_pairs(document, item, item_path)
        if pairs is None:
            continue  # without its faulty value it could look like another world: no "listed twice" from that
        for key, value in pairs:
            line = document.line((*item_path, key))
            values.setdefault(key, {}).setdefault(label_text(value), (label_text(value), value, line))
        world = read_world(pairs)
        if world.label in worlds:
            first = worlds[world.label][1]
            document.note(document.error(item_path, f"world {world.label!r} is listed twice (also on line {first})"))
            continue
        worlds[world.label] = (world, document.line(item_path))
    axes = [Axis(key=key, values=tuple(texts.values())) for key, texts in values.items()]
    return [world for world, _ in worlds.values()], axes


def _world_pairs(document: Document, item: dict[str, Any], path: At) -> list[tuple[str, Any]] | None:
    """(key, value) of one listed world, or None once the mistake of each key or value that has one is noted."""
    before = document.noted
    pairs = []
    for key, value in item.items():
        if _is_variation_key(document, (*path, key), key):
            pairs.append((key, document.attempt(read_variation_value, document, value, (*path, key), key=key)))
    return pairs if document.noted == before else None


def read_world(items: list[tuple[str, Any]]) -> World:
    if not items:
        return World(label=DEFAULT_VARIATION)
    return World(label=",".join(f"{key}={label_text(value)}" for key, value in items), items=tuple(items))


# -- perturbations -------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Perturbation:
    """Noise stages (in written order) and camera variation items of one perturbation, with its label and line."""

    label: str
    line: int
    noise: tuple[NoiseStage, ...] = ()
    camera: tuple[tuple[str, Any], ...] = ()


def read_perturbation(document: Document, value: Any, path: At) -> Perturbation:
    noise, camera, labels = [], [], []
    for key, params, item_path, at_key in _perturbation_items(document, value, path):
        if key in NOISE_MODEL_NAMES:
            noise.append(_noise(document, item_path, key, params))
        elif key in CAMERA_PERTURBATION_KEYS:
            _camera_item(document, item_path, key, params)
            camera.append((key, params))
        else:
            raise document.error(
                item_path,
                f"unknown perturbation {key!r} (noise models: {', '.join(NOISE_MODEL_NAMES)}"
                f"; camera keys: {', '.join(CAMERA_PERTURBATION_KEYS)}; or none)",
                at_key=at_key,
            )
        labels.append(_item_label(key, params))
    return Perturbation(
        label="+".join(labels) or NO_PERTURBATION, line=document.line(path), noise=tuple(noise), camera=tuple(camera)
    )


def _perturbation_items(document: Document, value: Any, path: At) -> Iterator[tuple[str, Any, At, bool]]:
    """(key, parameters, path, whether the key is the place to point at) of each item: noise model or camera
    key; nothing for ``none``."""
    if isinstance(value, dict):
        if not value:
            raise document.error(path, "an empty perturbation (write none for no perturbation)")
        for key, params in value.items():
            if isinstance(params, list):
                raise document.error((*path, key), f"perturbation {key!r} takes a value or a mapping, not a list")
            yield key, params, (*path, key), True
        return
    if value is None or (isinstance(value, str) and value.strip().lower() == NO_PERTURBATION):
        return
    if not isinstance(value, str):
        raise document.error(
            path, f'a perturbation is none, "model=value", "camera=left" or a mapping of them, got {value!r}'
        )
    for part in _ITEM_JOIN.split(value):
        yield (*_string_item(document, path, part), path, False)


def _string_item(document: Document, path: At, text: str) -> tuple[str, Any]:
    match = _STRING_ITEM.fullmatch(text)
    if not match:
        raise document.error(
            path,
            f"bad perturbation item {text.strip()!r} (want model, model=value, model:key=value,... or camera=PRESET)",
        )
    key, separator, rest = match[1], match[2], match[3]
    if separator is None:
        return key, {}
    if separator == "=":
        return key, _yaml_value(document, path, rest)
    try:
        pairs = parse_pairs(rest)
    except VariationError as error:
        raise document.error(path, f"bad perturbation item {text.strip()!r}: {error}") from None
    return key, {name: _yaml_value(document, path, value) for name, value in pairs}


def _yaml_value(document: Document, path: At, text: str) -> Any:
    """A value written inside a string (``"gaussian=10"``), read as YAML like the command line does."""
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError:
        raise document.error(path, f"cannot read the value {text.strip()!r}") from None


def _noise(document: Document, path: At, model: str, params: Any) -> NoiseStage:
    try:
        return noise_stage({model: params})
    except VariationError as error:
        raise document.error(path, f"bad {model} parameters {params!r}: {error}") from None


def _camera_item(document: Document, path: At, key: str, value: Any) -> None:
    if isinstance(value, (dict, list)):
        raise document.error(path, f"perturbation {key!r} takes a single value, got {value!r}")
    _check_finite(document, path, key, value)
    try:
        apply_variation(EpisodeSpec(), {key: value})
    except VariationError as error:
        raise document.error(path, f"bad {key} value {value!r}: {error}") from None


def _check_finite(document: Document, path: At, key: str, value: Any) -> None:
    if isinstance(value, float) and not math.isfinite(value):
        raise document.error(path, f"{key} must be a finite number, got {value!r}")


def _item_label(key: str, params: Any) -> str:
    if isinstance(params, dict):
        if not params:
            return key
        return f"{key}:" + ",".join(f"{name}={label_text(value)}" for name, value in params.items())
    return f"{key}={label_text(params)}"


def read_perturbations(document: Document, value: Any, path: At) -> list[Perturbation]:
    """The perturbations written at ``path`` (``[none]`` when ``value`` is None: not written); one with a mistake
    is noted and left out."""
    if value is None:
        return [Perturbation(label=NO_PERTURBATION, line=1)]
    perturbations: dict[str, Perturbation] = {}
    for item, item_path in items(value, path):
        perturbation = document.attempt(read_perturbation, document, item, item_path)
        if perturbation is None:  # noted
            continue
        if perturbation.label in perturbations:
            first = perturbations[perturbation.label].line
            document.note(
                document.error(item_path, f"perturbation {perturbation.label!r} is listed twice (also on line {first})")
            )
            continue
        perturbations[perturbation.label] = perturbation
    return list(perturbations.values())
