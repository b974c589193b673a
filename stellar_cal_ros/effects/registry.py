"""Registry of effects: contract ids → classes, found where they are written.

A library effect is one module of this package (``effects/<id>.py``); the registry imports
every module here whose name does not start with ``_`` (those hold shared helpers) and
registers each :class:`~stellar_cal_ros.effects.base.Effect` subclass with an ``id`` that
the module defines.  A user adds one by

- dropping such a file into this package,
- passing ``--effect-module my_effect.py`` (a file defining :class:`Effect` subclasses), or
- installing a package with an entry point in group ``stellar_cal_ros.effects``.

Nothing lists the effects: the package's files and the entry points are read on the first
look-up (:data:`EFFECTS`, :func:`available`, :func:`create`), so an entry-point effect is
known wherever an id is resolved.  The application order comes from the classes too: by
stage (:data:`~stellar_cal_ros.effects.base.STAGE_ORDER`), then by each class's ``order``
(e.g. focal length before pixel aspect before thermal scaling), then by id.

:func:`create` returns a fresh instance (effects keep per-run state such as the prior's
nominal installation).
"""

from __future__ import annotations

import importlib
import importlib.util
import inspect
import logging
import pkgutil
from collections.abc import Iterator, MutableMapping
from importlib.metadata import entry_points
from pathlib import Path

from stellar_cal_ros.effects.base import STAGE_ORDER, Effect
from stellar_cal_ros.errors import ModelError

log = logging.getLogger(__name__)

ENTRY_POINT_GROUP = "stellar_cal_ros.effects"
_PACKAGE = __name__.rpartition(".")[0]
#: the package's own folder: what a fresh process (a Dask worker) discovers too
_HOME = Path(__file__).resolve().parent


def order_key(cls: type[Effect]) -> tuple[int, int, str]:
    """Application (and state-layout) order of an effect class: stage, ``order``, id."""
    stage = STAGE_ORDER.index(cls.stage) if cls.stage in STAGE_ORDER else len(STAGE_ORDER)
    return stage, int(cls.order), cls.id


class _Registry(MutableMapping):
    """id → effect class; loads the package's effect files and entry points on first use.

    Iterates in application order (:func:`order_key`).
    """

    def __init__(self) -> None:
        self._classes: dict[str, type[Effect]] = {}
        self._sorted: list[str] | None = None
        self._loaded = False
        self._loading = False
        #: modules and entry points that failed to load: name → reason (reported on look-up)
        self.failed: dict[str, str] = {}

    def _ensure(self) -> None:
        if self._loaded or self._loading:
            return
        self._loading = True
        try:
            _discover(self)
            _load_entry_points(self)
        finally:
            self._loading = False
        self._loaded = True

    def reload(self) -> None:
        """Look again at the package's files (after a new one was added to its path)."""
        self._loaded = False
        self._ensure()

    def __getitem__(self, key: str) -> type[Effect]:
        self._ensure()
        return self._classes[key]

    def __setitem__(self, key: str, cls: type[Effect]) -> None:
        self._classes[key] = cls
        self._sorted = None

    def __delitem__(self, key: str) -> None:
        del self._classes[key]
        self._sorted = None

    def __contains__(self, key: object) -> bool:
        self._ensure()
        return key in self._classes

    def __iter__(self) -> Iterator[str]:
        self._ensure()
        if self._sorted is None:
            self._sorted = sorted(self._classes, key=lambda k: order_key(self._classes[k]))
        return iter(list(self._sorted))

    def __len__(self) -> int:
        self._ensure()
        return len(self._classes)


EFFECTS: _Registry = _Registry()


def _effect_classes(module) -> list[type[Effect]]:
    return [obj for obj in vars(module).values()
            if inspect.isclass(obj) and issubclass(obj, Effect) and obj.id
            and obj.__module__ == module.__name__]


def _discover(registry: _Registry) -> None:
    """Import every effect module of the package (its ``__path__``) and register its classes."""
    package = importlib.import_module(_PACKAGE)
    for info in pkgutil.iter_modules(package.__path__):
        name = info.name
        if name.startswith("_") or name in ("base", "registry") or info.ispkg:
            continue
        try:
            module = importlib.import_module(f"{_PACKAGE}.{name}")
        except Exception as exc:  # a broken file must not take the library down with it
            registry.failed[name] = f"{type(exc).__name__}: {exc}"
            log.warning("effect module %s failed to import: %s", name, exc)
            continue
        for cls in _effect_classes(module):
            register(cls)


def _load_entry_points(registry: _Registry) -> None:
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        try:
            register(ep.load())
        except Exception as exc:  # a broken plugin: reported, the others still load
            registry.failed[f"entry point {ep.name}"] = f"{type(exc).__name__}: {exc}"
            log.warning("effect entry point %s (%s) failed to load: %s", ep.name, ep.value, exc)


def register(cls: type[Effect]) -> type[Effect]:
    """Register an effect class (usable as a decorator); its ``id`` must be new."""
    if not (inspect.isclass(cls) and issubclass(cls, Effect)) or not cls.id:
        raise ModelError(f"{cls!r} is not an Effect subclass with an id")
    old = EFFECTS._classes.get(cls.id)
    if old is not None and old is not cls and not _same_source(old, cls):
        raise ModelError(f"effect id {cls.id!r} is already registered (by {old.__module__})")
    EFFECTS[cls.id] = cls
    return cls


def _same_source(a: type, b: type) -> bool:
    """The same class loaded again from the same file (a reloaded effect module)."""
    src = getattr(a, "_effect_source", None)
    return a.__qualname__ == b.__qualname__ and src is not None and \
        src == getattr(b, "_effect_source", None)


def is_library(cls: type[Effect]) -> bool:
    """The class comes from a file in the package's own folder (a fresh process finds it)."""
    module = inspect.getmodule(cls)
    path = getattr(module, "__file__", None)
    return (cls.__module__.startswith(_PACKAGE + ".") and path is not None
            and Path(path).resolve().parent == _HOME)


def load_effect_module(path: str | Path) -> list[str]:
    """Import a Python file and register every :class:`Effect` subclass it defines."""
    EFFECTS._ensure()
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
    for obj in _effect_classes(module):
        if is_private(obj.id):  # it would be fitted, never listed nor printed: silent
            raise ModelError(f"effect module {path}: id {obj.id!r} starts with '_', which "
                             "is reserved for the diagnosis's own nuisances: rename it")
        obj._effect_source = str(path.resolve())
        register(obj)
        ids.append(obj.id)
    if not ids:
        raise ModelError(f"effect module {path} defines no Effect subclass with an id")
    return ids


def is_private(name: str) -> bool:
    """A private effect's id, or one of its quantities (``_id.param``): a leading ``_``.

    A nuisance a diagnosis fits beside its candidates
    (:class:`~stellar_cal_ros.diagnosis.installation_step.StepNuisance`) is never listed,
    offered or printed.
    """
    return name.startswith("_")


def available() -> list[str]:
    """Ids of every registered effect, in application order.

    Not the private ones (an id with a leading ``_``: a nuisance a diagnosis fits beside
    its candidates, :class:`~stellar_cal_ros.diagnosis.installation_step.StepNuisance`),
    nor offered as candidates (:func:`candidates`, :func:`offered_on`).
    """
    return [i for i in EFFECTS if not is_private(i)]


def candidates() -> list[str]:
    """Ids of the effects offered as candidates in every round, in application order.

    Those whose ``offered_on`` names a test are offered only where it asks
    (:attr:`~stellar_cal_ros.effects.base.Effect.offered_on`).
    """
    return [i for i, cls in EFFECTS.items() if not cls.offered_on and not is_private(i)]


def offered_on(test: str) -> list[str]:
    """Ids of the effects offered as candidates where ``test`` asks for them."""
    return [i for i, cls in EFFECTS.items() if cls.offered_on == test and not is_private(i)]


def effect_class(effect_id: str) -> type[Effect]:
    """The class of ``effect_id`` (a one-line error naming the known ids if unknown).

    The known ids are :func:`available`'s (a private one is known, not offered); an effect
    module that failed to load is named with its error.
    """
    try:
        return EFFECTS[effect_id]
    except KeyError:
        failed = "".join(f"; {k} failed to load ({v})" for k, v in EFFECTS.failed.items())
        raise ModelError(
            f"unknown effect {effect_id!r}; known: {', '.join(available())}{failed}"
        ) from None


def create(effect_id: str) -> Effect:
    """Return a new instance of the effect ``effect_id``."""
    return effect_class(effect_id)()


def create_many(ids: list[str]) -> list[Effect]:
    """Instances for ``ids`` (duplicates removed), sorted in application order."""
    unique = list(dict.fromkeys(i for i in ids if i))
    effects = [create(i) for i in unique]
    return sorted(effects, key=lambda e: order_key(type(e)))
