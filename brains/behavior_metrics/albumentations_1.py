"""The albumentations that Behavior Metrics' brain files were written against, for their own imports only.

Behavior Metrics pins albumentations 1.0.3; drivebench's ``bm`` extra installs 2.x, which removed names BM's files
import: its default brain (``brain_f1_opencv.py``, the brain of BM's ``default.yml``) starts with
``from albumentations import (Compose, Normalize, RandomRain, RandomBrightness, ...)`` and would fail with an
ImportError before it drives. A BM brain file is executed with builtins whose ``__import__`` answers
``albumentations`` with :class:`Albumentations1`: the installed module plus the 1.x names 2.x removed, each built
from its 2.x equivalent with 1.0.3's parameters and defaults (1.0.3's documentation). Nothing else sees them: the
``albumentations`` module everyone else imports is not changed, and BM's other modules (imported from a checkout)
import it as they find it.

Transforms still in 2.x whose 1.0.3 parameters 2.x renamed (``RandomRain(slant_lower=...)``) are 2.x's: BM's brain
files import them, and perturb through ``handler.transform_image``, which drivebench implements itself.
"""

from __future__ import annotations

import builtins
from collections.abc import Callable, Mapping, Sequence
from types import ModuleType
from typing import Any


def _p(p: float, always_apply: bool) -> float:
    """1.x's ``always_apply=True`` applied a transform whatever ``p`` said; 2.x has only ``p``."""
    return 1.0 if always_apply else p


def RandomBrightness(limit: Any = 0.2, always_apply: bool = False, p: float = 0.5) -> Any:  # 1.x's name
    """1.0.3's RandomBrightness: RandomBrightnessContrast with the contrast left alone."""
    import albumentations

    return albumentations.RandomBrightnessContrast(
        brightness_limit=limit, contrast_limit=0, brightness_by_max=True, p=_p(p, always_apply)
    )


def RandomContrast(limit: Any = 0.2, always_apply: bool = False, p: float = 0.5) -> Any:
    """1.0.3's RandomContrast: RandomBrightnessContrast with the brightness left alone."""
    import albumentations

    return albumentations.RandomBrightnessContrast(brightness_limit=0, contrast_limit=limit, p=_p(p, always_apply))


def JpegCompression(
    quality_lower: int = 99, quality_upper: int = 100, always_apply: bool = False, p: float = 0.5
) -> Any:
    """1.0.3's JpegCompression: ImageCompression (JPEG) with its quality range."""
    import albumentations

    return albumentations.ImageCompression(
        compression_type="jpeg", quality_range=(quality_lower, quality_upper), p=_p(p, always_apply)
    )


def Cutout(
    num_holes: int = 8,
    max_h_size: int = 8,
    max_w_size: int = 8,
    fill_value: Any = 0,
    always_apply: bool = False,
    p: float = 0.5,
) -> Any:
    """1.0.3's Cutout: CoarseDropout with ``num_holes`` holes of exactly max_h_size x max_w_size pixels."""
    import albumentations

    return albumentations.CoarseDropout(
        num_holes_range=(num_holes, num_holes),
        hole_height_range=(max_h_size, max_h_size),
        hole_width_range=(max_w_size, max_w_size),
        fill=fill_value,
        p=_p(p, always_apply),
    )


REMOVED_IN_2: dict[str, Callable[..., Any]] = {
    "RandomBrightness": RandomBrightness,
    "RandomContrast": RandomContrast,
    "JpegCompression": JpegCompression,
    "Cutout": Cutout,
}


class Albumentations1(ModuleType):
    """The installed albumentations as a BM file sees it: every attribute of it, and the 1.x names 2.x removed."""

    def __init__(self, installed: ModuleType):
        super().__init__(installed.__name__, installed.__doc__)
        self._installed = installed

    def __getattr__(self, name: str) -> Any:
        if name in REMOVED_IN_2 and not hasattr(self._installed, name):
            return REMOVED_IN_2[name]
        return getattr(self._installed, name)

    def __dir__(self) -> list[str]:
        return sorted(set(dir(self._installed)) | set(REMOVED_IN_2))


def bm_file_builtins() -> dict[str, Any]:
    """Builtins for a BM brain file's namespace: ``import albumentations`` there gives :class:`Albumentations1`."""
    installed_import = builtins.__import__
    proxies: dict[int, Albumentations1] = {}

    def bm_import(
        name: str,
        globals: Mapping[str, Any] | None = None,  # __import__'s own parameter names
        locals: Mapping[str, Any] | None = None,
        fromlist: Sequence[str] | None = (),
        level: int = 0,
    ) -> Any:
        module = installed_import(name, globals, locals, fromlist, level)
        if level == 0 and isinstance(module, ModuleType) and module.__name__ == "albumentations":
            return proxies.setdefault(id(module), Albumentations1(module))
        return module

    namespace = dict(builtins.__dict__)
    namespace["__import__"] = bm_import
    return namespace
