"""Brains by name, imported lazily so that torch loads only when a neural brain is asked for.

A brain is named in one of four ways, everywhere a brain is named (``--brain``, matrix files, compose's ``BRAIN``,
``drivebench brains check``):

* a built-in name (``explicit``, ``memdccp``, ...);
* a name an installed package declares in the ``drivebench.brains`` entry-point group, e.g. in its pyproject::

      [project.entry-points."drivebench.brains"]
      my_brain = "my_package.brain:MyBrain"

* a target ``package.module:Attribute`` (a Brain class or any callable that takes keyword options and returns a
  brain); like uvicorn, the current directory is importable, so ``my_brain:MyBrain`` finds ``./my_brain.py``;
* a Behavior Metrics brain file, ``path/to/brain.py``, run unchanged by ``brains.behavior_metrics``.
"""

from __future__ import annotations

import importlib
import inspect
import os
import sys
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Any

from brains.base import Brain
from brains.nets import MODELS
from protocol.suggest import did_you_mean

ENTRY_POINT_GROUP = "drivebench.brains"
SHIPPED_WEIGHTS = Path(__file__).resolve().parent / "weights"  # brains/weights/<network>.ckpt, in a wheel too
BEHAVIOR_METRICS = "behavior_metrics"

# name -> "module:factory". The factory takes keyword options and returns a Brain.
_REGISTRY: dict[str, str] = {
    "explicit": "brains.explicit.brain:ExplicitBrain",
    "constant": "brains.constant.brain:ConstantBrain",
    "noisy": "brains.noisy.brain:NoisyBrain",
    "expert": "brains.expert.brain:ExpertBrain",  # privileged: pure pursuit on the ground-truth pose
    "lane_policy": "brains.lane_policy.brain:LanePolicyBrain",  # an RL policy (examples/rl), from line features
    "ros2": "brains.ros2.brain:Ros2Brain",  # a ROS 2 node drives, through rmw_zenoh's keys (needs the host's bus)
    # Every network of brains.nets is a brain of its name, served from a checkpoint (``--weights CKPT``) that must
    # hold that network (brains.neural.brain makes the factory); "neural" serves whatever the checkpoint holds.
    **{name: f"brains.neural.brain:{name}" for name in MODELS},
    "neural": "brains.neural.brain:neural",
    # A Behavior Metrics brain file, run unchanged: --brain behavior_metrics --brain-option file=brain.py
    BEHAVIOR_METRICS: "brains.behavior_metrics.adapter:BehaviorMetricsBrain",
}


class UnknownBrainError(ValueError):
    pass


class BrainOptionsError(ValueError):
    """A brain's options are missing or unusable (no weights, a bad checkpoint): one line, no traceback."""


@dataclass(frozen=True)
class BrainSource:
    """Where a brain name leads: ``target`` ("module:attribute") and, for people, where it comes from."""

    name: str
    target: str
    origin: str  # "built-in", "entry point of <distribution> <version>", "module path", "Behavior Metrics file"
    options: tuple[tuple[str, Any], ...] = ()  # options the name itself implies (a BM file's path)


# What a built-in brain needs beyond the core install, by the module its target lives in: a network brain loads a
# checkpoint (torch) and serves it with onnxruntime (both the ``ml`` extra); a Behavior Metrics file's perturbations
# are albumentations' (the ``bm`` extra), and the file itself may import more (its own requirements).
_EXTRAS_OF_MODULE = {
    "brains.neural.brain": ("ml", "torch"),
    "brains.behavior_metrics.adapter": ("bm", "albumentations"),
}


def needs(source: BrainSource) -> tuple[str, str] | None:
    """(extra, module) a brain needs beyond the core install (``("ml", "torch")``), or None when it needs none or
    drivebench cannot tell (an installed package's or a module path's brain declares its own requirements)."""
    if source.origin not in ("built-in", "Behavior Metrics file"):
        return None
    return _EXTRAS_OF_MODULE.get(source.target.partition(":")[0])


def register(name: str, target: str) -> None:
    """Register a brain factory as ``"package.module:callable"`` (imported only when the brain is made)."""
    if ":" not in target:
        raise ValueError(f"brain target must look like 'module:callable', got {target!r}")
    _REGISTRY[name] = target


def entry_point_brains() -> dict[str, BrainSource]:
    """Brains that installed packages declare in the ``drivebench.brains`` entry-point group (built-ins win)."""
    found = {}
    for entry in metadata.entry_points(group=ENTRY_POINT_GROUP):
        if entry.name in _REGISTRY or entry.name in found:
            continue
        dist = getattr(entry, "dist", None)
        origin = f"entry point of {dist.name} {dist.version}" if dist is not None else "entry point"
        found[entry.name] = BrainSource(entry.name, entry.value, origin)
    return found


def brain_sources() -> list[BrainSource]:
    """Every brain known by name: the built-ins, then the installed packages' ones."""
    built_in = [BrainSource(name, target, "built-in") for name, target in sorted(_REGISTRY.items())]
    return built_in + sorted(entry_point_brains().values(), key=lambda source: source.name)


def brain_names() -> list[str]:
    return sorted(source.name for source in brain_sources())


def is_module_target(name: str) -> bool:
    module, sep, attribute = name.partition(":")
    parts = module.split(".") + attribute.split(".")
    return bool(sep and module and attribute) and all(part.isidentifier() for part in parts)


def shipped_weights(name: str) -> Path | None:
    """The checkpoint drivebench ships for the network brain ``name`` (``pilotnet``, ``memdccp``, ...), or None."""
    path = SHIPPED_WEIGHTS / f"{name}.ckpt"
    return path if name in MODELS and path.is_file() else None


def shipped_network(name: str) -> str | None:
    """The network a named network brain serves (``pilotnet`` -> ``pilotnet``), or None for other brains."""
    return name if name in MODELS else None


def is_brain_file(name: str) -> bool:
    return name.endswith(".py")


def is_behavior_metrics_brain(name: str | None) -> bool:
    """A Behavior Metrics brain file: its path, or ``behavior_metrics`` (with ``file=``). Its fixed crops are made
    for Behavior Metrics' 640x480 F1 camera."""
    return bool(name) and (is_brain_file(str(name)) or name == BEHAVIOR_METRICS)


def resolve(name: str) -> BrainSource:
    """Where brain ``name`` comes from; :class:`UnknownBrainError` (one line) when it leads nowhere."""
    if name in _REGISTRY:
        return BrainSource(name, _REGISTRY[name], "built-in")
    if is_brain_file(name):
        if not Path(name).is_file():
            raise UnknownBrainError(f"Behavior Metrics brain file {name!r} not found")
        return BrainSource(
            name, _REGISTRY[BEHAVIOR_METRICS], "Behavior Metrics file", options=(("file", str(Path(name).resolve())),)
        )
    if is_module_target(name):
        return BrainSource(name, name, "module path")
    installed = entry_point_brains()
    if name in installed:
        return installed[name]
    raise UnknownBrainError(
        f"unknown brain {name!r} (known: {', '.join(brain_names())}; or give "
        f"package.module:Class, or a Behavior Metrics brain file path/to/brain.py)" + did_you_mean(name, brain_names())
    )


def load_factory(source: BrainSource):
    """The callable behind ``source``, imported now; :class:`UnknownBrainError` naming what could not be imported."""
    module_name, _, attribute = source.target.partition(":")
    if os.getcwd() not in sys.path:
        sys.path.append(os.getcwd())  # my_brain:MyBrain finds ./my_brain.py, as `python -m brains` would
    try:
        factory: Any = importlib.import_module(module_name)
    except ImportError as error:
        raise UnknownBrainError(f"brain {source.name!r}: cannot import module {module_name!r} ({error})") from None
    for part in attribute.split("."):
        owner, factory = factory, getattr(factory, part, None)
        if factory is None:
            names = [name for name in dir(owner) if not name.startswith("_")]
            raise UnknownBrainError(
                f"brain {source.name!r}: module {module_name!r} has no {attribute!r}" + did_you_mean(part, names)
            )
    if not callable(factory):
        raise UnknownBrainError(f"brain {source.name!r}: {source.target} is not a class or a callable")
    return factory


def require_brain(name: str) -> BrainSource:
    """Resolve ``name`` and import what it leads to, so that a typo fails before any process starts."""
    source = resolve(name)
    load_factory(source)
    return source


def preflight(name: str, options: dict[str, Any]) -> None:
    """Everything about brain ``name`` with ``options`` that can be known before any process starts, so a mistake is
    one line at once instead of a brain host dying after the stack came up: the name resolves and imports, the
    factory takes these options (``--weights`` on a brain without weights is refused), and a factory's own
    ``preflight`` passes (neural brains: the checkpoint loads and holds the right network).
    Raises :class:`UnknownBrainError` or :class:`BrainOptionsError`."""
    source = resolve(name)
    factory = load_factory(source)
    options = {**dict(source.options), **options}
    try:
        signature = inspect.signature(factory)
    except (TypeError, ValueError):  # a builtin or C callable: nothing to check up front
        signature = None
    if signature is not None:
        try:
            signature.bind(**options)
        except TypeError as error:
            unknown = [key for key in options if key not in signature.parameters]
            if unknown == ["weights"]:
                raise BrainOptionsError(f"brain {name!r} takes no weights (--weights is for neural brains)") from None
            raise BrainOptionsError(f"bad options for brain {name!r}: {error}") from None
    check = getattr(factory, "preflight", None)
    if callable(check):
        check(**options)


def bus_name(brain: str) -> str:
    """The name a brain goes by on the bus when nobody chose one: key chunks take letters, digits, ``_ . -``.

    ``my_package.brain:MyBrain`` -> ``MyBrain``; ``path/to/brain_f1.py`` -> ``brain_f1``; other names as they are.
    """
    if is_brain_file(brain):
        return Path(brain).stem
    if is_module_target(brain):
        return brain.partition(":")[2].replace(".", "-")
    return brain


def make_brain(name: str, **options: Any) -> Brain:
    """A new instance of brain ``name`` built with ``options``."""
    source = resolve(name)
    factory = load_factory(source)
    return factory(**dict(source.options), **options)
