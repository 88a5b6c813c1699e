"""The conditions of a matrix file: variations (a product of world and camera settings) or worlds (listed one by
one), and perturbations (camera moves and noise models), each read from YAML nodes with its line in errors and
given the label that results and reports use."""

from __future__ import annotations

import itertools
import math
import re
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import yaml

from orchestrator.matrix_plan import (
    DEFAULT_VARIATION,
    NO_PERTURBATION,
)
from orchestrator.yaml_nodes import NodeReader, label_text, line_of
from protocol.messages import NOISE_MODELS, EpisodeSpec, NoiseStage

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
NOISE_MODEL_NAMES = tuple(model.__struct_config__.tag for model in NOISE_MODELS)
# An item of a perturbation string: "model", "model=value", "model:key=value,..." or "camera_key=value".
_STRING_ITEM = re.compile(r"\s*([A-Za-z_][A-Za-z0-9_]*)\s*(?:([=:])(.*))?", re.S)
# "+" joins items; one followed by a digit or sign belongs to a number ("1e+5", "brightness=+0.2").
_ITEM_JOIN = re.compile(r"\+(?=\s*[A-Za-z_])")


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


def read_variation_value(reader: NodeReader, node: yaml.Node, *, key: str) -> Any:
    value = reader.scalar(node, what=f"a value of {key}")
    _check_finite(reader, node, key, value)
    try:
        apply_variation(EpisodeSpec(), {key: value})
    except VariationError as error:
        raise reader.error(node, f"bad {key} value {value!r}: {error}") from None
    return value


def _check_variation_key(reader: NodeReader, node: yaml.Node, key: str) -> None:
    if key not in VARIATION_KEYS:
        raise reader.error(node, f"unknown variation key {key!r} (allowed: {', '.join(VARIATION_KEYS)})")


def read_axes(reader: NodeReader, node: yaml.Node | None) -> list[Axis]:
    if node is None:
        return []
    axes = []
    for key, (key_node, values_node) in reader.mapping(node, what="variations").items():
        _check_variation_key(reader, key_node, key)
        values: dict[str, tuple[str, Any, int]] = {}
        for item in reader.items(values_node, what=f"variations.{key}"):
            value = read_variation_value(reader, item, key=key)
            text = label_text(value)
            if text in values:
                raise reader.error(item, f"{key} value {text!r} is listed twice (also on line {values[text][2]})")
            values[text] = (text, value, line_of(item))
        axes.append(Axis(key=key, values=tuple(values.values())))
    return axes


def read_worlds(axes: list[Axis]) -> list[World]:
    if not axes:
        return [World(label=DEFAULT_VARIATION)]
    return [
        read_world([(axis.key, value) for axis, (_, value, _) in zip(axes, combination)])
        for combination in itertools.product(*(axis.values for axis in axes))
    ]


def read_listed_worlds(reader: NodeReader, node: yaml.Node) -> tuple[list[World], list[Axis]]:
    """``worlds:``, a list of variation mappings: the worlds in written order, and per key the values they use
    (the axes exclude entries may name)."""
    worlds: dict[str, tuple[World, int]] = {}
    values: dict[str, dict[str, tuple[str, Any, int]]] = {}
    for item in reader.items(node, what="worlds"):
        items = []
        for key, (key_node, value_node) in reader.mapping(item, what="a world").items():
            _check_variation_key(reader, key_node, key)
            value = read_variation_value(reader, value_node, key=key)
            items.append((key, value))
            values.setdefault(key, {}).setdefault(label_text(value), (label_text(value), value, line_of(value_node)))
        world = read_world(items)
        if world.label in worlds:
            raise reader.error(item, f"world {world.label!r} is listed twice (also on line {worlds[world.label][1]})")
        worlds[world.label] = (world, line_of(item))
    axes = [Axis(key=key, values=tuple(texts.values())) for key, texts in values.items()]
    return [world for world, _ in worlds.values()], axes


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


def read_perturbation(reader: NodeReader, node: yaml.Node) -> Perturbation:
    noise, camera, labels = [], [], []
    for key, params, item_node in _perturbation_items(reader, node):
        if key in NOISE_MODEL_NAMES:
            noise.append(_noise(reader, item_node, key, params))
        elif key in CAMERA_PERTURBATION_KEYS:
            _camera_item(reader, item_node, key, params)
            camera.append((key, params))
        else:
            raise reader.error(
                item_node,
                f"unknown perturbation {key!r} (noise models: {', '.join(NOISE_MODEL_NAMES)}"
                f"; camera keys: {', '.join(CAMERA_PERTURBATION_KEYS)}; or none)",
            )
        labels.append(_item_label(key, params))
    return Perturbation(
        label="+".join(labels) or NO_PERTURBATION, line=line_of(node), noise=tuple(noise), camera=tuple(camera)
    )


def _perturbation_items(reader: NodeReader, node: yaml.Node) -> Iterator[tuple[str, Any, yaml.Node]]:
    """(key, parameters, node) of each item: noise model or camera key; nothing for ``none``."""
    if isinstance(node, yaml.MappingNode):
        entries = reader.mapping(node, what="a perturbation")
        if not entries:
            raise reader.error(node, "an empty perturbation (write none for no perturbation)")
        for key, (key_node, value_node) in entries.items():
            if isinstance(value_node, yaml.SequenceNode):
                raise reader.error(value_node, f"perturbation {key!r} takes a value or a mapping, not a list")
            yield key, reader.value(value_node), key_node
        return
    value = reader.scalar(node, what="a perturbation")
    if value is None or (isinstance(value, str) and value.strip().lower() == NO_PERTURBATION):
        return
    if not isinstance(value, str):
        raise reader.error(
            node, f'a perturbation is none, "model=value", "camera=left" or a mapping of them, got {value!r}'
        )
    for part in _ITEM_JOIN.split(value):
        yield (*_string_item(reader, node, part), node)


def _string_item(reader: NodeReader, node: yaml.Node, text: str) -> tuple[str, Any]:
    match = _STRING_ITEM.fullmatch(text)
    if not match:
        raise reader.error(
            node,
            f"bad perturbation item {text.strip()!r} (want model, model=value, model:key=value,... or camera=PRESET)",
        )
    key, separator, rest = match[1], match[2], match[3]
    if separator is None:
        return key, {}
    if separator == "=":
        return key, reader.yaml_text(node, rest)
    try:
        pairs = parse_pairs(rest)
    except VariationError as error:
        raise reader.error(node, f"bad perturbation item {text.strip()!r}: {error}") from None
    return key, {name: reader.yaml_text(node, value) for name, value in pairs}


def _noise(reader: NodeReader, node: yaml.Node, model: str, params: Any) -> NoiseStage:
    try:
        return noise_stage({model: params})
    except VariationError as error:
        raise reader.error(node, f"bad {model} parameters {params!r}: {error}") from None


def _camera_item(reader: NodeReader, node: yaml.Node, key: str, value: Any) -> None:
    if isinstance(value, (dict, list)):
        raise reader.error(node, f"perturbation {key!r} takes a single value, got {value!r}")
    _check_finite(reader, node, key, value)
    try:
        apply_variation(EpisodeSpec(), {key: value})
    except VariationError as error:
        raise reader.error(node, f"bad {key} value {value!r}: {error}") from None


def _check_finite(reader: NodeReader, node: yaml.Node, key: str, value: Any) -> None:
    if isinstance(value, float) and not math.isfinite(value):
        raise reader.error(node, f"{key} must be a finite number, got {value!r}")


def _item_label(key: str, params: Any) -> str:
    if isinstance(params, dict):
        if not params:
            return key
        return f"{key}:" + ",".join(f"{name}={label_text(value)}" for name, value in params.items())
    return f"{key}={label_text(params)}"


def read_perturbations(reader: NodeReader, node: yaml.Node | None) -> list[Perturbation]:
    if node is None:
        return [Perturbation(label=NO_PERTURBATION, line=1)]
    perturbations: dict[str, Perturbation] = {}
    for item in reader.items(node, what="perturbations"):
        perturbation = read_perturbation(reader, item)
        if perturbation.label in perturbations:
            first = perturbations[perturbation.label].line
            raise reader.error(item, f"perturbation {perturbation.label!r} is listed twice (also on line {first})")
        perturbations[perturbation.label] = perturbation
    return list(perturbations.values())
