"""Registry of effects: contract ids → classes, plus user plugins.

Built-in effects are listed here; a user adds one by

- passing ``--effect-module my_effect.py`` (a file defining :class:`Effect` subclasses), or
- installing a package with an entry point in group ``stellar_cal_ros.effects``.

:func:`create` returns a fresh instance (effects keep per-run state such as the prior's
nominal installation).  Within one stage, effects are applied in registry order, which is
the physical order (e.g. focal length before pixel aspect before thermal scaling).
"""

from __future__ import annotations

import importlib.util
import inspect
from importlib.metadata import entry_points
from pathlib import Path

from stellar_cal_ros.effects.astrometric import Aberration, ProperMotion, Refraction
from stellar_cal_ros.effects.base import Effect
from stellar_cal_ros.effects.camera_effects import (
    FocalLength,
    ImagePlaneTilt,
    PixelAspect,
    PrincipalPoint,
    RadialK1K2,
    RadialK3,
    Tangential,
    ThermalFocalLength,
)
from stellar_cal_ros.effects.installation import Installation
from stellar_cal_ros.effects.sensor_effects import (
    AccelBias,
    AccelScaleFactor,
    GyroBias,
    GyroMisalignment,
    GyroScaleFactor,
)
from stellar_cal_ros.effects.time_offset import TimeOffset
from stellar_cal_ros.errors import ModelError

_BUILTIN: list[type[Effect]] = [
    Installation,
    FocalLength,
    PixelAspect,
    PrincipalPoint,
    RadialK1K2,
    RadialK3,
    Tangential,
    ImagePlaneTilt,
    ThermalFocalLength,
    GyroBias,
    GyroScaleFactor,
    GyroMisalignment,
    AccelBias,
    AccelScaleFactor,
    TimeOffset,
    ProperMotion,
    Aberration,
    Refraction,
]

EFFECTS: dict[str, type[Effect]] = {cls.id: cls for cls in _BUILTIN}
ENTRY_POINT_GROUP = "stellar_cal_ros.effects"
_plugins_loaded = False


def _load_entry_points() -> None:
    global _plugins_loaded
    if _plugins_loaded:
        return
    _plugins_loaded = True
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        register(ep.load())


def register(cls: type[Effect]) -> type[Effect]:
    """Register an effect class (usable as a decorator); its ``id`` must be new."""
    if not (inspect.isclass(cls) and issubclass(cls, Effect)) or not cls.id:
        raise ModelError(f"{cls!r} is not an Effect subclass with an id")
    old = EFFECTS.get(cls.id)
    if old is not None and old is not cls and not _same_source(old, cls):
        raise ModelError(f"effect id {cls.id!r} is already registered (by {old.__module__})")
    EFFECTS[cls.id] = cls
    return cls


def _same_source(a: type, b: type) -> bool:
    """The same class loaded again from the same file (a reloaded effect module)."""
    src = getattr(a, "_effect_source", None)
    return a.__qualname__ == b.__qualname__ and src is not None and \
        src == getattr(b, "_effect_source", None)


def load_effect_module(path: str | Path) -> list[str]:
    """Import a Python file and register every :class:`Effect` subclass it defines."""
    path = Path(path)
    if not path.is_file():
        raise ModelError(f"effect module {path} does not exist")
    spec = importlib.util.spec_from_file_location(f"stellar_cal_user_effect_{path.stem}", path)
    if spec is None or spec.loader is None:
        raise ModelError(f"cannot import effect module {path}")
    module = importlib.util.module_from_spec(spec)
    try:
        spec.loader.exec_module(module)
    except Exception as exc:  # a user's file: report any failure clearly
        raise ModelError(f"effect module {path} failed to import: {exc}") from exc
    ids = []
    for obj in vars(module).values():
        if inspect.isclass(obj) and issubclass(obj, Effect) and obj.id and \
                obj.__module__ == module.__name__:
            obj._effect_source = str(path.resolve())
            register(obj)
            ids.append(obj.id)
    if not ids:
        raise ModelError(f"effect module {path} defines no Effect subclass with an id")
    return ids


def available() -> list[str]:
    """Ids of every registered effect, in application order."""
    _load_entry_points()
    return list(EFFECTS)


def create(effect_id: str) -> Effect:
    """Return a new instance of the effect ``effect_id``."""
    _load_entry_points()
    try:
        return EFFECTS[effect_id]()
    except KeyError:
        raise ModelError(
            f"unknown effect {effect_id!r}; available: {', '.join(EFFECTS)}"
        ) from None


def create_many(ids: list[str]) -> list[Effect]:
    """Instances for ``ids`` (duplicates removed), sorted in application order."""
    _load_entry_points()
    unique = list(dict.fromkeys(i for i in ids if i))
    effects = [create(i) for i in unique]
    order = {k: n for n, k in enumerate(EFFECTS)}
    return sorted(effects, key=lambda e: order[e.id])
