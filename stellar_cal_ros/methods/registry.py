"""The method registry: every estimation method is one file that declares one spec.

A method file defines, at module level, ``METHOD = MethodSpec(...)``: its name, whether it
is a streaming *filter* or a *batch* fit, its baseline effects, the stages it models, whether
it needs the site, and what runs it.  The registry collects them:

* the package's own: every module of ``stellar_cal_ros/methods/`` whose source has a line
  starting ``METHOD = MethodSpec(`` is imported on first use (only those: the others, and
  their imports, stay unloaded).  A look-up of one name (:func:`get`, :func:`find`, ``in``
  :class:`MethodNames`) imports only the file whose declaration names it
  (``METHOD = MethodSpec(name="psce", ...``): a ``psce`` replay does not import the ACF,
  bundle or swaying-base modules, nor read the installed entry points (a plugin cannot
  take a package method's name anyway: :func:`register` refuses it);
* installed ones: entry points in the group ``stellar_cal_ros.methods`` (each names a
  :class:`MethodSpec` or a module holding ``METHOD``);
* a user's file: :func:`load_method_module` (``stellar-cal ... --method-module FILE.py``).

Everything that dispatches on a method reads it here: the command line (``--method`` of
``replay``, ``batch``, ``diagnose`` and ``discover``), the streaming driver and the
``calibrator`` node (filter class and configuration), the model rule
(:mod:`~stellar_cal_ros.methods.models`), the diagnosis
(:func:`~stellar_cal_ros.diagnosis.discover.method_spec`), campaigns, checkpoints and the
result commands.  A new method is one file plus its tests.

Filter methods
    ``filter_cls`` is a :class:`~stellar_cal_ros.methods.kernel.StarFilter` subclass built as
    ``filter_cls(model, t0, [site,] config, nominal_dt=..., consider=...)`` (``site`` when
    ``needs_site``), ``config_cls`` its :class:`~stellar_cal_ros.methods.kernel.KernelConfig`
    subclass.  The replay, the node, the diagnosis and campaigns run it through the one
    streaming driver (:class:`~stellar_cal_ros.methods.driver.Calibrator`).
Batch methods
    ``batch(bag, prior, effects, options, progress)`` fits a whole bag and returns a
    :class:`BatchOutput` (what ``stellar-cal batch`` writes and prints); ``effects`` is the
    ``--effects`` list (ids added to the method's set, ``-id`` removes one), ``options`` holds
    the ``batch`` command's ``loss``, ``outlier_probability`` and ``on_error`` (the reader's
    ``raise``/``skip``: a method reading past damage records :meth:`~stellar_cal_ros.io.
    reader.BagReader.losses` in its result's ``data_quality``), and ``progress`` is called
    with the name of each of ``steps`` as it ends.  With a ``runner`` the method can also be
    diagnosed.
"""

from __future__ import annotations

import ast
import importlib
import importlib.util
import logging
import re
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from stellar_cal_ros.effects.base import Stage
from stellar_cal_ros.errors import ModelError

log = logging.getLogger(__name__)

KINDS = ("filter", "batch")
ENTRY_POINT_GROUP = "stellar_cal_ros.methods"
#: how a method file of the package declares its spec (the registry imports only these)
_DECLARATION = re.compile(r"^METHOD = MethodSpec\(", re.MULTILINE)

#: ``runner(data, prior, effects, keep_tables=False, eval_fraction=0.5, consider=None,
#: gyro_fault="raise") -> ReplayResult``: one run over a bag as the diagnosis sees it
Runner = Callable[..., Any]


@dataclass
class BatchOutput:
    """What a batch method's fit gives ``stellar-cal batch``."""

    calibration: Any  #: the result (:class:`~stellar_cal_ros.io.calibration.Calibration`)
    covariance: tuple[list[str], Any]  #: (names, matrix) of the estimated parameters
    residuals: dict[str, Any]  #: per-star residual table (columns), ``--residuals``
    lines: list[str]  #: the summary printed
    result: Any = None  #: the method's own result object


#: the stages of a method with no accelerometer model (PSCE, ACF): every stage but ACCEL
STAGES_WITHOUT_ACCEL = (Stage.GYRO, Stage.DIRECTION, Stage.TIME, Stage.TRACKER, Stage.CAMERA)


@dataclass(frozen=True)
class MethodSpec:
    """What one estimation method is and what runs it (see the module docstring)."""

    name: str  #: ``--method`` value and the result's ``method`` key
    kind: str  #: ``filter`` (streaming Kalman filter) or ``batch`` (a fit of the whole bag)
    summary: str  #: one line for ``--help``: the paper, and when to use it
    #: effects always estimated (``--effects`` adds to them; they cannot be removed)
    baseline: tuple[str, ...]
    stages: tuple[Stage, ...] = tuple(Stage)  #: stages it models (effects elsewhere: refused)
    needs_site: bool = False  #: needs ``/gnss/fix`` whatever the effects
    filter_cls: type | None = None  #: filter methods: the StarFilter subclass
    config_cls: type | None = None  #: its configuration dataclass (filters: KernelConfig)
    #: filter methods: data seconds of IMU a replay holds ahead of the frame being processed,
    #: from the configuration (a strapdown's reference window); None: the replay's default
    imu_lookahead: Callable[[Any], float] | None = None
    #: batch methods: the fit run by ``stellar-cal batch`` (module docstring)
    batch: Callable[..., Any] | None = None
    steps: tuple[str, ...] = ()  #: batch methods: named steps reported as progress
    #: one run as the diagnosis, ``report`` and campaigns see it (:data:`Runner`); None for a
    #: filter method: the streaming replay.  A batch method without one cannot be diagnosed.
    runner: Runner | None = None
    #: its runs can carry *consider* parameters (the kernel's sensitivity), which the
    #: diagnosis' one-pass screening needs; None: True for filter methods
    consider: bool | None = None
    source: str = field(default="", compare=False)  #: where it was declared (messages)

    def __post_init__(self) -> None:
        if not self.name or not re.fullmatch(r"[a-z][a-z0-9_]*", self.name):
            raise ModelError(f"method name {self.name!r}: lower-case letters, digits, _")
        if self.kind not in KINDS:
            raise ModelError(f"method {self.name}: kind {self.kind!r} is not one of {KINDS}")
        object.__setattr__(self, "baseline", tuple(self.baseline))
        object.__setattr__(self, "stages", tuple(Stage(s) for s in self.stages))
        if self.consider is None:
            object.__setattr__(self, "consider", self.kind == "filter")
        if self.kind == "filter" and (self.filter_cls is None or self.config_cls is None):
            raise ModelError(f"filter method {self.name} needs filter_cls and config_cls")
        if self.kind == "batch" and self.batch is None:
            raise ModelError(f"batch method {self.name} needs its batch function")

    @property
    def diagnosable(self) -> bool:
        """Whether ``diagnose``/``discover`` can run it (a filter, or a batch runner)."""
        return self.kind == "filter" or self.runner is not None


METHODS: dict[str, MethodSpec] = {}
_loaded = False
_plugins_loaded = False
#: package methods registered by a one-name look-up before the full load (:func:`_load`
#: registers them again in file order, so that :func:`names` keeps its order)
_early: set[str] = set()
_declarations: list[Declaration] | None = None


@dataclass(frozen=True)
class Declaration:
    """What a package file's ``METHOD = MethodSpec(...)`` says, read from its source.

    The command line's ``--method`` choices, ``--help`` and a bag's refusal read these
    (:func:`catalog`): no method module, nor numba or scipy, is imported for them.  A field
    the source does not give as a literal (a name the file defines or imports from the
    package is followed) is None; :func:`catalog` then imports the file, unless only a
    filter's ``stages`` are unknown (a filter reads the IMU whatever they are: what the
    stages are read for here).
    """

    module: str
    name: str | None
    kind: str | None
    summary: str | None
    stages: tuple[Stage, ...] | None
    diagnosable: bool | None

    @property
    def complete(self) -> bool:
        """Whether it says enough to list or judge the method without importing it."""
        return self.kind in KINDS and None not in (self.name, self.summary, self.diagnosable) \
            and (self.stages is not None or self.kind == "filter")


def _source_tree(module: str) -> ast.Module | None:
    """The parsed source of one of this package's modules (None when it has no file)."""
    path = Path(__file__).parents[1].joinpath(*module.split(".")[1:]).with_suffix(".py")
    try:
        return ast.parse(path.read_text(encoding="utf-8"))
    except (OSError, SyntaxError, ValueError):
        return None


def _stages(node: ast.expr, tree: ast.Module, depth: int = 0) -> tuple[Stage, ...] | None:
    """The stages an expression of a declaration names (None: not readable from source).

    A tuple of ``Stage.X``, or a name assigned one at module level in the file or in the
    package module the file imports it from.
    """
    if isinstance(node, (ast.Tuple, ast.List)):
        out = [Stage[e.attr] for e in node.elts if isinstance(e, ast.Attribute)
               and isinstance(e.value, ast.Name) and e.value.id == "Stage"
               and e.attr in Stage.__members__]
        return tuple(out) if len(out) == len(node.elts) else None
    if not isinstance(node, ast.Name) or depth > 2:
        return None
    for st in tree.body:
        targets = st.targets if isinstance(st, ast.Assign) else \
            [st.target] if isinstance(st, ast.AnnAssign) else []
        value = getattr(st, "value", None)
        if value is not None and any(isinstance(t, ast.Name) and t.id == node.id
                                     for t in targets):
            return _stages(value, tree, depth + 1)
        if isinstance(st, ast.ImportFrom) and (st.module or "").startswith(
                f"{__package__.split('.')[0]}.") and any(
                (a.asname or a.name) == node.id and a.name == node.id for a in st.names):
            other = _source_tree(st.module or "")
            return _stages(node, other, depth + 1) if other is not None else None
    return None


def _declaration(module: str, tree: ast.Module) -> Declaration:
    """The :class:`Declaration` of ``METHOD = MethodSpec(...)`` in a module's source."""
    call = next((st.value for st in tree.body if isinstance(st, ast.Assign)
                 and any(isinstance(t, ast.Name) and t.id == "METHOD" for t in st.targets)
                 and isinstance(st.value, ast.Call) and isinstance(st.value.func, ast.Name)
                 and st.value.func.id == "MethodSpec"), None)
    if call is None:
        return Declaration(module, None, None, None, None, None)
    given = {k.arg: k.value for k in call.keywords if k.arg is not None}
    hidden = any(k.arg is None for k in call.keywords)  # a ``**`` expansion: anything

    def text(key: str) -> str | None:
        node = given.get(key)
        return node.value if isinstance(node, ast.Constant) and \
            isinstance(node.value, str) else None

    kind = text("kind")
    stages = _stages(given["stages"], tree) if "stages" in given else \
        (None if hidden else tuple(Stage))
    runner = given.get("runner")
    if kind == "filter":
        diagnosable: bool | None = True
    elif runner is not None:
        diagnosable = not (isinstance(runner, ast.Constant) and runner.value is None)
    else:
        diagnosable = None if hidden else False
    return Declaration(module, text("name"), kind, text("summary"), stages, diagnosable)


def _package_declarations() -> list[Declaration]:
    """The :class:`Declaration` of each of this package's files that declares a method.

    Sorted by file name; a declaration whose name is not a literal ``name="..."`` has name
    None (such a file is imported by every one-name look-up).
    """
    global _declarations
    if _declarations is None:
        here = Path(__file__).parent
        out = []
        for path in sorted(here.glob("*.py")):
            if path.stem == "registry":
                continue
            text = path.read_text(encoding="utf-8")
            if _DECLARATION.search(text):
                module = f"{__package__}.{path.stem}"
                try:
                    out.append(_declaration(module, ast.parse(text)))
                except SyntaxError:  # imported, it says what is wrong
                    out.append(Declaration(module, None, None, None, None, None))
        _declarations = out
    return _declarations


def _package_files() -> Iterator[str]:
    """Module names of this package's files that declare a method (sorted by file name)."""
    for d in _package_declarations():
        yield d.module


def _load() -> None:
    """Collect the package's methods, then installed plugins (once)."""
    global _loaded
    if _loaded:
        return
    _loaded = True
    for name in _package_files():
        module = importlib.import_module(name)
        spec = getattr(module, "METHOD", None)
        if isinstance(spec, MethodSpec) and spec.name in _early \
                and METHODS.get(spec.name) is spec:
            del METHODS[spec.name]  # registered early by a look-up: again, in file order
        _register_module(module, name)
    _early.clear()
    _load_plugins()


def _load_plugins() -> None:
    """Register the installed plugins (once; a package method's name stays the package's)."""
    global _plugins_loaded
    if _plugins_loaded:
        return
    _plugins_loaded = True
    from importlib.metadata import entry_points  # (~0.05 s: only when all are listed)

    for ep in entry_points(group=ENTRY_POINT_GROUP):
        try:
            obj = ep.load()
        except Exception as exc:  # an installed plugin: say which, go on with the rest
            log.warning("method plugin %s failed to load: %s", ep.value, exc)
            continue
        spec = obj if isinstance(obj, MethodSpec) else getattr(obj, "METHOD", None)
        if isinstance(spec, MethodSpec) and any(d.name == spec.name
                                                for d in _package_declarations()):
            _lookup(spec.name)  # the package's first: :func:`register` refuses the plugin
        if isinstance(obj, MethodSpec):
            register(obj)
        else:
            _register_module(obj, ep.value)


def _lookup(name: str) -> MethodSpec | None:
    """The spec of ``name``, importing only the package file that declares it if it can.

    Before the full load, a name some package file declares is imported from that file
    alone; any other name is looked up among the plugins (the package's files declare
    theirs: none of them is imported for it).
    """
    spec = METHODS.get(name)
    if spec is not None or _loaded:
        return spec
    for d in _package_declarations():
        if d.name is None or d.name == name:
            spec = _register_module(importlib.import_module(d.module), d.module)
            if not _loaded:
                _early.add(spec.name)
    spec = METHODS.get(name)
    if spec is not None:
        return spec
    _load_plugins()
    return METHODS.get(name)


def _register_module(module: Any, where: str) -> MethodSpec:
    spec = getattr(module, "METHOD", None)
    if not isinstance(spec, MethodSpec):
        raise ModelError(f"{where} declares no METHOD = MethodSpec(...)")
    if not spec.source:
        object.__setattr__(spec, "source", where)
    return register(spec)


def register(spec: MethodSpec) -> MethodSpec:
    """Add a method; its name must be new (the same spec again is a no-op)."""
    if not isinstance(spec, MethodSpec):
        raise ModelError(f"{spec!r} is not a MethodSpec")
    old = METHODS.get(spec.name)
    if old is not None and old != spec:
        raise ModelError(f"method {spec.name!r} is already registered"
                         + (f" (by {old.source})" if old.source else ""))
    METHODS[spec.name] = spec
    return spec


def load_method_module(path: str | Path) -> str:
    """Import a user's Python file and register the ``METHOD`` it declares; its name."""
    path = Path(path)
    if not path.is_file():
        raise ModelError(f"method module {path} does not exist")
    _load()
    mod_spec = importlib.util.spec_from_file_location(
        f"stellar_cal_user_method_{path.stem}", path)
    if mod_spec is None or mod_spec.loader is None:
        raise ModelError(f"cannot import method module {path}")
    module = importlib.util.module_from_spec(mod_spec)
    try:
        mod_spec.loader.exec_module(module)
    except Exception as exc:  # a user's file: report any failure in one line
        raise ModelError(f"method module {path} failed to import: "
                         f"{type(exc).__name__}: {exc}") from exc
    spec = getattr(module, "METHOD", None)
    if isinstance(spec, MethodSpec) and spec.name in METHODS and \
            METHODS[spec.name].source == str(path.resolve()):
        METHODS[spec.name] = spec  # the same file loaded again
        object.__setattr__(spec, "source", str(path.resolve()))
        return spec.name
    if isinstance(spec, MethodSpec):
        object.__setattr__(spec, "source", str(path.resolve()))
    return _register_module(module, str(path)).name


def get(name: str) -> MethodSpec:
    """The spec of ``name``; :class:`ModelError` naming the known ones otherwise."""
    spec = _lookup(name)
    if spec is None:
        raise ModelError(f"unknown method {name!r} (one of {', '.join(names())})")
    return spec


def peek(name: str | None) -> MethodSpec | Declaration | None:
    """What :func:`find` gives, or the :class:`Declaration` of a package method not imported.

    The declaration when it is complete (its kind, stages, summary: no import).
    """
    name = name or ""
    spec = METHODS.get(name)
    if spec is not None:
        return spec
    d = next((d for d in _package_declarations() if d.name == name), None)
    return d if d is not None and d.complete else _lookup(name)


def find(name: str | None) -> MethodSpec | None:
    """The spec of ``name``, None when no method has that name (``prior``, ``truth`` ...)."""
    return _lookup(name or "")


def catalog(kind: str | None = None,
            diagnosable: bool = False) -> list[MethodSpec | Declaration]:
    """Every method, as :func:`names` lists them (a package one not imported: its declaration).

    A package method not imported yet is its :class:`Declaration` when the source says
    everything (else its file is imported).

    Both have ``name``, ``kind``, ``summary``, ``stages`` and ``diagnosable``: what
    ``--help``, the ``--method`` choices and a bag's refusal read (no method module, numba
    or scipy imported for them: a refused bag or ``--help`` costs < 1 CPU-s).
    """
    _load_plugins()
    package: list[MethodSpec | Declaration] = []
    for d in _package_declarations():
        spec = METHODS.get(d.name) if d.name is not None else None
        if spec is None and not d.complete:
            spec = _register_module(importlib.import_module(d.module), d.module)
            if not _loaded:
                _early.add(spec.name)
        package.append(spec if spec is not None else d)
    ours = {e.name for e in package}
    out = package + [s for s in METHODS.values() if s.name not in ours]
    out = [s for s in out if (kind is None or s.kind == kind)
           and (s.diagnosable or not diagnosable)]
    return sorted(out, key=lambda s: KINDS.index(s.kind))


def names(kind: str | None = None, diagnosable: bool = False) -> list[str]:
    """Registered method names (filters first, each kind in file order).

    Plugins and ``--method-module`` files after the package's.
    """
    return [s.name for s in catalog(kind, diagnosable) if s.name is not None]


class MethodNames:
    """Method names resolved when first read.

    As argparse ``choices`` they import no method until a command takes ``--method``
    (``stellar-cal -h`` and ``stellar-cal info`` stay fast).
    """

    def __init__(self, kind: str | None = None, diagnosable: bool = False) -> None:
        self.kind, self.diagnosable = kind, diagnosable

    def _names(self) -> list[str]:
        return names(self.kind, self.diagnosable)

    def __contains__(self, name: object) -> bool:
        spec = peek(name) if isinstance(name, str) else None  # (its declaration, or a file)
        return spec is not None and (self.kind is None or spec.kind == self.kind) and \
            bool(spec.diagnosable or not self.diagnosable)

    def __iter__(self) -> Iterator[str]:
        return iter(self._names())

    def __len__(self) -> int:
        return len(self._names())

    def describe(self) -> str:
        """``name: summary`` of each, ``;``-separated (``--help``)."""
        return "; ".join(f"{s.name}: {s.summary}"
                         for s in catalog(self.kind, self.diagnosable))
