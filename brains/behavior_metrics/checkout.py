"""Importing a Behavior Metrics brain file, with the user's Behavior Metrics checkout for BM's own modules.

Neural BM brains import helpers from BM's package (``from brains.gazebo.f1.torch_utils.pilotnet import PilotNet``,
``from utils.constants import ROOT_PATH``). drivebench's own top-level package is also called ``brains``, so with
``bm_root`` (``--brain-option bm_root=PATH`` or ``$DRIVEBENCH_BM_ROOT``: a BehaviorMetrics checkout, or its
``behavior_metrics`` folder) the checkout's ``brains`` folder is appended to drivebench's ``brains`` package path:
``brains.gazebo...`` and ``brains.CARLA...`` then import from the checkout while drivebench's own modules
(``brains.base``, ``brains.registry``, ...) stay first and unchanged. The checkout's folder goes first on
``sys.path`` for BM's other top-level modules (``utils``, ``robot``); it holds none of drivebench's package names.

A BM file's own ``import albumentations`` gets the 1.x names BM's files import and 2.x removed
(``brains.behavior_metrics.albumentations_1``).

Without a checkout, a file that imports BM's modules fails at once with one line naming the import, its line and
the option.
"""

from __future__ import annotations

import importlib.util
import inspect
import linecache
import sys
from pathlib import Path
from types import ModuleType, TracebackType

from brains.behavior_metrics.albumentations_1 import bm_file_builtins
from brains.registry import BrainOptionsError
from protocol import environment

BM_PACKAGES = ("brains", "utils", "robot")  # BM's top-level packages a brain file imports from
_DRIVEBENCH_PACKAGES = ("protocol", "circuits", "services", "recorder", "orchestrator")
HOW_TO_GIVE = f"give --brain-option bm_root=PATH (your BehaviorMetrics checkout) or set {environment.BM_ROOT.name}"


def find_bm_root(bm_root: str | None) -> Path | None:
    """The folder holding BM's ``brains`` and ``utils`` (``bm_root`` or ``$DRIVEBENCH_BM_ROOT``; None if neither)."""
    given = bm_root or environment.BM_ROOT.value()
    if not given:
        return None
    where = "bm_root" if bm_root else environment.BM_ROOT.name
    root = Path(given).expanduser().resolve()
    for candidate in (root / "behavior_metrics", root):
        if (candidate / "brains").is_dir():
            break
    else:
        raise BrainOptionsError(
            f"{where} {given!r} is not a Behavior Metrics checkout (no brains/ folder in it or in its "
            "behavior_metrics/ folder)"
        )
    clash = [name for name in _DRIVEBENCH_PACKAGES if (candidate / name).exists()]
    if clash:
        raise BrainOptionsError(f"{where} {given!r} holds {', '.join(clash)}: drivebench's own package names")
    return candidate


def use_bm_root(root: Path) -> None:
    """Make BM's modules under ``root`` importable beside drivebench's (idempotent)."""
    import brains

    bm_brains = str(root / "brains")
    if bm_brains not in brains.__path__:
        brains.__path__.append(bm_brains)  # after drivebench's own folder: ours win for the names both have
    if str(root) not in sys.path:
        sys.path.insert(0, str(root))


def _line_in(path: Path, traceback: TracebackType | None) -> tuple[int, str]:
    """The last (line number, source line) of ``path`` in ``traceback``; (0, "") if it is not in it."""
    found = (0, "")
    while traceback is not None:
        if Path(traceback.tb_frame.f_code.co_filename).resolve() == path:
            number = traceback.tb_lineno
            found = (number, linecache.getline(str(path), number).strip())
        traceback = traceback.tb_next
    return found


def line_in(path: Path, error: BaseException) -> int:
    """The line of ``path`` where ``error`` last passed through it (0: it did not)."""
    return _line_in(path, error.__traceback__)[0]


def where_in(path: Path, error: BaseException) -> str:
    """`` (file.py:LINE)`` where ``error`` came out of ``path``, or "" if it did not pass through it."""
    number, _ = _line_in(path, error.__traceback__)
    return f" ({path.name}:{number})" if number else ""


def _import_error(path: Path, error: Exception, root: Path | None) -> BrainOptionsError:
    number, line = _line_in(path, error.__traceback__)
    missing = getattr(error, "name", None) or ""
    if isinstance(error, ModuleNotFoundError) and missing.split(".")[0] in BM_PACKAGES:
        at = f"line {number} `{line}`" if number else f"module {missing!r}"
        if root is None:
            return BrainOptionsError(
                f"Behavior Metrics brain file {str(path)!r}: {at} imports Behavior Metrics' own modules: {HOW_TO_GIVE}"
            )
        return BrainOptionsError(
            f"Behavior Metrics brain file {str(path)!r}: {at}: no module {missing!r} in the checkout {str(root)!r}"
        )
    at = f" at line {number}" if number else ""
    return BrainOptionsError(
        f"Behavior Metrics brain file {str(path)!r} failed to import{at}: {type(error).__name__}: {error}"
    )


def load_brain_file(path: str | Path, *, bm_root: str | None = None) -> ModuleType:
    """Import a Behavior Metrics brain file as a module of its own; one-line :class:`BrainOptionsError` if unusable."""
    path = Path(path).expanduser().resolve()
    if not path.is_file():
        raise BrainOptionsError(f"Behavior Metrics brain file {str(path)!r} not found")
    root = find_bm_root(bm_root)
    if root is not None:
        use_bm_root(root)
    name = f"behavior_metrics_brain_{abs(hash(str(path))):x}"
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None:
        raise BrainOptionsError(f"Behavior Metrics brain file {str(path)!r} is not a Python file")
    module = importlib.util.module_from_spec(spec)
    # BM's files import albumentations 1.x names (its default brain: RandomBrightness) that 2.x removed.
    module.__dict__["__builtins__"] = bm_file_builtins()
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
    except Exception as error:  # the user's file: whatever it raises, say where
        del sys.modules[name]
        raise _import_error(path, error, root) from None
    if not inspect.isclass(getattr(module, "Brain", None)):
        raise BrainOptionsError(f"Behavior Metrics brain file {str(path)!r} defines no class Brain")
    return module
