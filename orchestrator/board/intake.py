"""What an upload is, decided before it is queued: anything else is refused at once, with the reason.

* a Python file holding one drivebench brain class (``reset(*, seed)`` and ``act(observation)``), run as the
  target ``submission:ClassName`` (``--brain module:Class``);
* a Behavior Metrics brain file (a class ``Brain`` with ``execute``), run unchanged (``--brain path/to/brain.py``);
* a wheel declaring exactly one brain in the ``drivebench.brains`` entry-point group, run as its target;
* an exported ONNX network, served by the ``neural`` brain (``--brain neural --weights net.onnx``).

The file is only read here (``ast`` for Python, the zip's listing for a wheel, the header for ONNX): nothing of it
runs in the server's process. Each submission gets ``DIR/submissions/<id>/``: the file as uploaded, and ``code/``,
the folder its evaluation runs in (its brain module is importable from there, as from ``drivebench run``'s folder).
``code/`` is all of the data folder the sandbox lets a brain read, so everything the brain loads is written there:
a Behavior Metrics brain file and an ONNX network too.
"""

from __future__ import annotations

import ast
import configparser
import zipfile
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path, PurePosixPath
from typing import Any

MAX_UPLOAD_BYTES = 50 * 2**20  # a small network's ONNX export is a few MB; more is not a brain for this challenge
MAX_UNPACKED_BYTES = 200 * 2**20  # a wheel's contents, unpacked: a guard against zip bombs
_ONNX_HEAD = b"\x08"  # an ONNX ModelProto starts with field 1 (ir_version, a varint): tag byte 0x08


class Kind(StrEnum):
    PYTHON = "python"
    BEHAVIOR_METRICS = "behavior_metrics"
    WHEEL = "wheel"
    ONNX = "onnx"


class Refused(ValueError):
    """The upload is not something the server evaluates: one line saying why."""


@dataclass(frozen=True)
class Brain:
    """How an evaluation names the submitted brain: ``entry`` is a matrix ``brains`` entry (name, weights), and
    ``code_dir`` the folder its processes run in."""

    kind: Kind
    entry: dict[str, Any]
    code_dir: Path


def classify(*, filename: str, content: bytes) -> Kind:
    """The kind of an upload, or :class:`Refused`."""
    if len(content) > MAX_UPLOAD_BYTES:
        raise Refused(f"{filename}: {len(content)} bytes, over the limit of {MAX_UPLOAD_BYTES} bytes")
    suffix = PurePosixPath(filename).suffix.lower()
    if suffix == ".py":
        return _python_kind(filename, content)
    if suffix == ".whl":
        _wheel_target(filename, content)
        return Kind.WHEEL
    if suffix == ".onnx":
        if not content.startswith(_ONNX_HEAD):
            raise Refused(f"{filename}: not an ONNX model (export one with drivebench export)")
        return Kind.ONNX
    raise Refused(
        f"{filename}: not a brain this server takes (a .py brain file, a .whl with a drivebench.brains entry point, "
        "an exported .onnx network, or a Behavior Metrics .py brain file)"
    )


def unpack(*, folder: Path, filename: str, content: bytes) -> Brain:
    """Write the upload into ``folder`` and say how its evaluation names it (``classify`` passed)."""
    kind = classify(filename=filename, content=content)
    code = folder / "code"
    code.mkdir(parents=True, exist_ok=True)
    if kind is Kind.PYTHON:
        (code / "submission.py").write_bytes(content)
        return Brain(kind, {"name": f"submission:{_python_classes(filename, content)[0]}"}, code)
    # Every file the brain reads lies in code/: the sandbox hides the rest of the submission's folder.
    if kind is Kind.BEHAVIOR_METRICS:
        path = code / "bm_brain.py"
        path.write_bytes(content)
        return Brain(kind, {"name": str(path.resolve())}, code)
    if kind is Kind.WHEEL:
        target = _wheel_target(filename, content)
        (folder / "upload.whl").write_bytes(content)
        with zipfile.ZipFile(folder / "upload.whl") as wheel:
            wheel.extractall(code)  # zipfile drops absolute paths and ".." parts of member names
        return Brain(kind, {"name": target}, code)
    path = code / "network.onnx"
    path.write_bytes(content)
    return Brain(kind, {"name": "neural", "weights": str(path.resolve())}, code)


def _python_kind(filename: str, content: bytes) -> Kind:
    tree = _parse(filename, content)
    if _python_classes(filename, content, tree=tree, refuse=False):
        return Kind.PYTHON
    if any(
        isinstance(node, ast.ClassDef) and node.name == "Brain" and "execute" in _methods(node) for node in tree.body
    ):
        return Kind.BEHAVIOR_METRICS
    raise Refused(
        f"{filename}: no brain class (a class with reset(*, seed) and act(observation)) and no Behavior Metrics "
        "Brain class (with execute)"
    )


def _parse(filename: str, content: bytes) -> ast.Module:
    try:
        return ast.parse(content.decode("utf-8"), filename=filename)
    except (UnicodeDecodeError, SyntaxError, ValueError) as error:
        raise Refused(f"{filename}: not a Python file this server can read ({type(error).__name__}: {error})") from None


def _methods(node: ast.ClassDef) -> set[str]:
    return {item.name for item in node.body if isinstance(item, (ast.FunctionDef, ast.AsyncFunctionDef))}


def _python_classes(filename: str, content: bytes, *, tree: ast.Module | None = None, refuse: bool = True) -> list[str]:
    """The top-level classes with ``reset`` and ``act``; :class:`Refused` (``refuse``) unless there is one."""
    tree = tree or _parse(filename, content)
    found = [
        node.name
        for node in tree.body
        if isinstance(node, ast.ClassDef) and {"reset", "act"} <= _methods(node) and not node.name.startswith("_")
    ]
    if refuse and len(found) != 1:
        raise Refused(f"{filename}: holds {len(found)} brain classes ({', '.join(found) or 'none'}); submit one")
    if len(found) > 1:
        raise Refused(f"{filename}: holds {len(found)} brain classes ({', '.join(found)}); submit one")
    return found


def _wheel_target(filename: str, content: bytes) -> str:
    """The one ``drivebench.brains`` entry point a wheel declares, or :class:`Refused`."""
    import io

    try:
        wheel = zipfile.ZipFile(io.BytesIO(content))
    except zipfile.BadZipFile:
        raise Refused(f"{filename}: not a wheel (not a zip file)") from None
    with wheel:
        if sum(info.file_size for info in wheel.infolist()) > MAX_UNPACKED_BYTES:
            raise Refused(f"{filename}: unpacks to more than {MAX_UNPACKED_BYTES} bytes")
        names = [name for name in wheel.namelist() if name.endswith(".dist-info/entry_points.txt")]
        entries = _brain_entries(wheel.read(names[0]).decode("utf-8", "replace")) if len(names) == 1 else {}
    if len(entries) != 1:
        raise Refused(f"{filename}: declares {len(entries)} drivebench.brains entry points; a submission has one")
    return next(iter(entries.values()))


def _brain_entries(text: str) -> dict[str, str]:
    parser = configparser.ConfigParser(delimiters=("=",), interpolation=None)
    parser.optionxform = str  # type: ignore[assignment, method-assign]  # entry point names keep their case
    try:
        parser.read_string(text)
    except configparser.Error:
        return {}
    return dict(parser["drivebench.brains"]) if parser.has_section("drivebench.brains") else {}
