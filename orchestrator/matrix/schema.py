"""The shape of a matrix file as msgspec types: which keys exist, their types and their bounds. Converting the
file's data to :class:`MatrixFile` (``protocol.deploy.typed_yaml.convert``) checks all of that, each mistake at its
line;
what depends on the values together (brain names, circuits, variation values, labels, exclude and include) is
read from the typed values in ``orchestrator.matrix.load`` and its helpers.

Wherever a list is expected, a single item stands for a one-item list (:func:`items`).
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

import msgspec
from msgspec import UNSET, Meta, UnsetType

from protocol.deploy.typed_yaml import Document, Path, convert, display
from protocol.episode_spec import CAMERA_BOUNDS, RENDERERS, SPEC_BOUNDS, CameraSpec

Text = Annotated[str, Meta(min_length=1)]
Scalar = str | int | float | bool
Count = Annotated[int, Meta(ge=1)]
Seed = Annotated[int, Meta(ge=0)]
Renderer = Literal[RENDERERS]  # type: ignore[valid-type]  # the protocol's tuple: pybullet, gl, auto
Mapping = dict[str, Any]


def _one_or_more(item: Any, *, single: Any = None) -> Any:
    """A non-empty list of ``item``, or one ``single`` (default: ``item``) standing for a one-item list."""
    return Annotated[list[item], Meta(min_length=1)] | (item if single is None else single)


class BrainFields(msgspec.Struct, forbid_unknown_fields=True, kw_only=True):
    """A brains or shadows entry written as a mapping (a bare name is ``{name: NAME}``)."""

    name: Text
    weights: Text | UnsetType = UNSET
    label: Text | UnsetType = UNSET
    options: Mapping = {}


Brains = _one_or_more(str | BrainFields)
Perturbations = _one_or_more(str | Mapping | None, single=str | Mapping)  # none, "model=value" or a mapping


class Limits(msgspec.Struct, forbid_unknown_fields=True, kw_only=True):
    """The episode limits a matrix sets (``EpisodeSpec``'s own defaults for the rest; its bounds, SPEC_BOUNDS)."""

    laps: Annotated[int, SPEC_BOUNDS["laps"]] | UnsetType = UNSET
    max_sim_seconds: Annotated[float, SPEC_BOUNDS["max_sim_seconds"]] | UnsetType = UNSET
    brain_timeout_s: Annotated[float, SPEC_BOUNDS["brain_timeout_s"]] | UnsetType = UNSET
    step_s: Annotated[float, SPEC_BOUNDS["step_s"]] | UnsetType = UNSET


def _partial(base: type[msgspec.Struct], *, name: str, bounds: dict[str, Meta]) -> Any:
    """A struct with ``base``'s fields, each UNSET unless written, unknown keys refused, ``bounds`` on some."""
    fields = [
        (
            field.name,
            (Annotated[field.type, bounds[field.name]] if field.name in bounds else field.type) | UnsetType,
            UNSET,
        )
        for field in msgspec.structs.fields(base)
    ]
    return msgspec.defstruct(name, fields, forbid_unknown_fields=True, kw_only=True)


# CameraSpec's own fields (a new one is a new key here) and bounds (CAMERA_BOUNDS), each failing at its own line.
CameraFields = _partial(CameraSpec, name="CameraFields", bounds=CAMERA_BOUNDS)


MAX_DRAWN = 1000


class Draw(msgspec.Struct, forbid_unknown_fields=True, kw_only=True):
    """A part's ``draw``: held-out conditions drawn from a seed (``orchestrator.matrix.draw``)."""

    count: Annotated[int, Meta(ge=1, le=MAX_DRAWN)]
    circuits: _one_or_more(Text)  # type: ignore[valid-type]  # names, or the families random, twisty and grandprix
    seed: Seed = 0
    variations: dict[str, _one_or_more(Scalar)] = {}  # type: ignore[valid-type]


class Part(msgspec.Struct, forbid_unknown_fields=True, kw_only=True):
    """What a part may set for itself; what it leaves UNSET comes from the top level."""

    circuits: _one_or_more(Text) | UnsetType = UNSET  # type: ignore[valid-type]
    variations: dict[str, _one_or_more(Scalar)] | UnsetType = UNSET  # type: ignore[valid-type]
    worlds: _one_or_more(dict[str, Scalar]) | UnsetType = UNSET  # type: ignore[valid-type]
    perturbations: Perturbations | UnsetType = UNSET  # type: ignore[valid-type]
    repetitions: Count | UnsetType = UNSET
    limits: Limits | UnsetType = UNSET
    exclude: _one_or_more(Mapping) | UnsetType = UNSET  # type: ignore[valid-type]
    include: _one_or_more(Mapping) | UnsetType = UNSET  # type: ignore[valid-type]
    draw: Draw | UnsetType = UNSET  # instead of circuits and worlds: conditions drawn from a seed


class MatrixFile(Part, forbid_unknown_fields=True, kw_only=True):
    """A whole matrix file: a part's keys, and what only the top level sets."""

    name: Text | UnsetType = UNSET
    brains: Brains  # type: ignore[valid-type]
    shadows: Brains | UnsetType = UNSET  # type: ignore[valid-type]
    camera: str | CameraFields | UnsetType = UNSET  # type: ignore[valid-type]  # "320x240" or fields
    seed: Seed | UnsetType = UNSET
    realtime: bool | UnsetType = UNSET
    renderer: Renderer | UnsetType = UNSET
    parts: Annotated[dict[str, Part], Meta(min_length=1)] | UnsetType = UNSET


def read_matrix_file(document: Document) -> MatrixFile:
    """The file's data as a :class:`MatrixFile`; raises ``document.error_type`` at the line of the first mistake."""
    return convert(document.data, MatrixFile, document=document, what="the matrix")


def written(struct: msgspec.Struct) -> dict[str, Any]:
    """The fields of ``struct`` the file wrote (not UNSET), in declaration order."""
    return {key: value for key, value in msgspec.structs.asdict(struct).items() if value is not UNSET}


def items(value: Any, path: Path) -> list[tuple[Any, Path]]:
    """(item, its path) of a list, or of one value standing for a one-item list."""
    if isinstance(value, list):
        return [(item, (*path, index)) for index, item in enumerate(value)]
    return [(value, path)]


def text_at(document: Document, value: Any, path: Path) -> str:
    """``value`` as non-blank text (stripped), or an error at its line."""
    text = convert(value, Text, document=document, path=path).strip()
    if not text:
        raise document.error(path, f"{display(path) or 'a value'} must not be blank")
    return text
