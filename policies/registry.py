"""Where policy names come from: the project's rules, installed plug-ins and the user's own.

A :class:`PolicyRegistry` resolves a policy *spec* to a policy object. A spec is

* a name of the project's policies (``fixed-10s``, ``learned``, ...: :mod:`policies`);
* a name registered on the registry at run time with :meth:`PolicyRegistry.register`;
* a name an installed distribution declares in the entry-point group ``slam_gym.policies``
  (read lazily, on the first lookup, with :func:`importlib.metadata.entry_points`), e.g. in the
  plug-in's ``pyproject.toml``::

      [project.entry-points."slam_gym.policies"]
      my-rule = "my_package.rules:MyRule"

* a reference ``package.module:attribute`` to a policy class, a factory returning a policy, or a
  policy object, for a policy in a module that is importable but not installed as a plug-in
  (the same syntax as an entry point's value).

A factory is anything callable with keyword options that returns a policy (``act(obs, info)``
and ``reset()``, :class:`policies.base.Policy`); a policy class is one. A reference to a policy
*object* gives a deep copy of it, so runs never share the state of one object.

The project's names take precedence: a plug-in's entry point with the same name is ignored with
a warning naming its distribution. :meth:`~PolicyRegistry.register` is idempotent for the same
factory and raises ``ValueError`` for a name already taken by another one.

Worker processes (the benchmark's process pool, Ray) import this module afresh: names registered
at run time exist only in the process that registered them, so the benchmark hands their
factories to its workers itself (:func:`slam_gym.evaluation.benchmark`); entry points and
references resolve in any process that can import them.
"""

from __future__ import annotations

import copy
import functools
import hashlib
import importlib
import inspect
import logging
import pickle
import re
from collections.abc import Callable, Mapping
from importlib.metadata import EntryPoint, entry_points
from typing import Any

from filters.validation import require

logger = logging.getLogger(__name__)

ENTRY_POINT_GROUP = "slam_gym.policies"
"""The entry-point group installed distributions declare their policies in."""

Factory = Callable[..., Any]

PARAMETERISED = re.compile(r"(?P<base>[A-Za-z0-9_.-]+)\[(?P<inner>.*)\]", re.S)
"""A name with its parameters: ``BASE[...]`` (``threshold-optimise[global_position_std_m>=2]``),
where the factory of ``BASE`` reads the bracket with its ``parse_parameters(text) -> options``
(:meth:`policies.heuristics.ThresholdOptimise.parse_parameters`): the form tables print a rule
of a family in, so every name they print can be typed back."""


def _parameter_parser(target: Any) -> Callable[[str], dict] | None:
    fn = target.func if isinstance(target, functools.partial) else target
    return getattr(fn, "parse_parameters", None)


def is_reference(spec: Any) -> bool:
    """Whether ``spec`` is a ``package.module:attribute`` reference (not a policy name)."""
    return isinstance(spec, str) and ":" in spec


def is_policy(obj: Any) -> bool:
    """Whether ``obj`` is a policy object: callable ``act`` and ``reset`` (not a class)."""
    return (not isinstance(obj, type) and callable(getattr(obj, "act", None))
            and callable(getattr(obj, "reset", None)))


def load_reference(reference: str) -> Any:
    """Import ``package.module:attribute`` (dotted attributes allowed) and return the attribute.

    ``ValueError`` naming the reference when the module cannot be imported or lacks the
    attribute."""
    module_name, _, attribute = reference.partition(":")
    require(bool(module_name) and bool(attribute) and ":" not in attribute, "policy reference",
            reference, "'package.module:attribute'")
    try:
        target: Any = importlib.import_module(module_name)
    except Exception as exc:  # ImportError, a SyntaxError in the module, its own exceptions
        raise ValueError(f"policy reference={reference!r} is invalid: cannot import module "
                         f"{module_name!r} ({type(exc).__name__}: {exc})") from exc
    for part in attribute.split("."):
        if not hasattr(target, part):
            raise ValueError(f"policy reference={reference!r} is invalid: {module_name!r} has "
                             f"no attribute {attribute!r}")
        target = getattr(target, part)
    return target


def build(target: Any, spec: str, options: Mapping[str, Any]) -> Any:
    """A policy from what a name or reference resolved to: call a factory with ``options``, or
    copy a policy object (which takes no options). ``ValueError`` naming ``spec`` when the result
    is not a policy."""
    if is_policy(target):
        require(not options, f"options of policy {spec!r}", dict(options),
                "empty (it names a policy object, not a factory)")
        return copy.deepcopy(target)
    require(callable(target), "policy", spec,
            "a policy class, a factory returning a policy, or a policy object")
    try:
        params = inspect.signature(target).parameters.values()
    except (TypeError, ValueError):  # builtins without a signature: let the call decide
        params = ()
    accepts_any = any(p.kind is p.VAR_KEYWORD for p in params)
    allowed = [p.name for p in params
               if p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD) and p.name != "self"]
    unknown = sorted(set(options) - set(allowed))
    if unknown and not accepts_any and params:
        raise ValueError(f"option(s) {', '.join(unknown)} invalid for policy {spec!r}: must be "
                         f"among {', '.join(allowed) if allowed else '(no options)'}")
    try:
        policy = target(**options)
    except Exception as exc:
        raise ValueError(f"policy {spec!r} is invalid: calling it to build a policy failed "
                         f"({type(exc).__name__}: {exc}); it must name a policy class, a "
                         "factory returning a policy, or a policy object") from exc
    require(is_policy(policy), f"policy {spec!r}", policy,
            "an object with act(obs, info) and reset() (what its factory returned)")
    return policy


def _defining_modules(target: Any) -> list[Any]:
    """The modules whose code a policy runs: the module defining ``target`` (a class, a function,
    a ``functools.partial``'s function, or an object's class) and those of its base classes,
    builtins left out."""
    while isinstance(target, functools.partial):
        target = target.func
    cls = target if isinstance(target, type) else None
    if cls is None and not inspect.isroutine(target):
        cls = type(target)
    found = [inspect.getmodule(target if cls is None else cls)]
    if cls is not None:
        found += [inspect.getmodule(base) for base in cls.__mro__]
    modules = {}
    for module in found:
        if module is not None and module.__name__ != "builtins":
            modules.setdefault(module.__name__, module)
    return [modules[name] for name in sorted(modules)]


def _source_bytes(module: Any, target: Any) -> bytes:
    """A module's file content; where there is no file (a class typed at a prompt), the
    target's source, else its qualified name."""
    path = getattr(module, "__file__", None)
    if path:
        try:
            with open(path, "rb") as f:
                return f.read()
        except OSError:
            pass
    try:
        return inspect.getsource(target if isinstance(target, type) else type(target)).encode()
    except (OSError, TypeError):
        return repr(getattr(target, "__qualname__", type(target).__qualname__)).encode()


def _value_bytes(value: Any) -> bytes:
    """A value pickled (the same bytes for the same values), else its ``repr`` without memory
    addresses (an object that does not pickle counts by its type and printable content)."""
    try:
        return pickle.dumps(value, protocol=4)
    except Exception:
        return re.sub(r" at 0x[0-9a-fA-F]+", "", repr(value)).encode()


def _state_bytes(target: Any) -> bytes:
    """What a policy object or a ``functools.partial`` carries: its options (attributes)."""
    if isinstance(target, functools.partial):
        return b"\0".join([_value_bytes(target.args), _value_bytes(sorted(target.keywords)),
                           *(_value_bytes(target.keywords[k]) for k in sorted(target.keywords)),
                           _state_bytes(target.func)])
    if isinstance(target, type) or inspect.isroutine(target):
        return b""
    state = getattr(target, "__dict__", None)
    if not isinstance(state, dict):
        return _value_bytes(target)
    return b"\0".join(k.encode() + b"=" + _value_bytes(state[k]) for k in sorted(state))


def policy_digest(target: Any) -> str:
    """The digest (16 hex characters of a SHA-256) of what a user's policy runs: the content of
    the source files of the modules that define it (the module of its class or factory and of
    the base classes) and, for a policy object or a ``functools.partial``, its options (its
    attributes). Editing the module, or changing the object's options, changes the digest; the
    benchmark keys a user policy's runs with it (``policy_sha256``), so a rerun never reuses the
    rows of other code (:func:`slam_gym.evaluation.run_jobs`)."""
    h = hashlib.sha256()
    for module in _defining_modules(target):
        h.update(module.__name__.encode() + b"\0")
        h.update(hashlib.sha256(_source_bytes(module, target)).digest())
    h.update(_state_bytes(target))
    return h.hexdigest()[:16]


def policy_label(policy: Any) -> str:
    """The name results use for a policy object: its ``name`` attribute when the object (or its
    class) sets one other than the base class's placeholder ``"policy"``, else its class name."""
    name = getattr(policy, "name", None)
    if isinstance(name, str) and name and name != "policy":
        return name
    return type(policy).__name__


class PolicyRegistry:
    """Policy names -> factories: built-in ones, run-time registrations and entry points.

    ``builtin`` maps the project's names to factories (a name -> ``make(**options)``);
    ``group`` is the entry-point group read (None: no entry points, e.g. for a private
    registry in a test). The registry is an explicit object: :mod:`policies` holds the default
    one, and a user may build their own.
    """

    def __init__(self, builtin: Mapping[str, Factory] | None = None, *,
                 group: str | None = ENTRY_POINT_GROUP) -> None:
        self._builtin: dict[str, Factory] = dict(builtin or {})
        self._registered: dict[str, Factory] = {}
        self._group = group
        self._entry_points: dict[str, EntryPoint] | None = None  # read on first use

    # -- registration ---------------------------------------------------------------------
    def register(self, name: str, factory: Factory) -> None:
        """Make ``name`` build policies with ``factory(**options)`` (or copy a policy object).

        Registering the same factory under the same name again does nothing; another factory
        under a name already taken (built-in, plug-in or registered) raises ``ValueError``.
        Names may not contain ``,`` (the command line's list separator) or ``:`` (references).
        """
        require(isinstance(name, str) and name.strip() == name and bool(name)
                and not any(c in name for c in ",: "), "name", name,
                "a non-empty str without spaces, ',' or ':'")
        require(callable(factory) or is_policy(factory), "factory", factory,
                "a policy class, a factory returning a policy, or a policy object")
        if self._registered.get(name) is factory:
            return
        taken = self.source(name)
        require(taken is None, "name", name,
                f"a name not taken already (it is {taken}); unregister it first to replace it")
        self._registered[name] = factory

    def unregister(self, name: str) -> None:
        """Forget a name registered with :meth:`register` (built-ins and plug-ins stay)."""
        require(name in self._registered, "name", name,
                f"a registered name (registered: {sorted(self._registered) or 'none'})")
        del self._registered[name]

    # -- lookup ---------------------------------------------------------------------------
    def _plugins(self) -> dict[str, EntryPoint]:
        if self._entry_points is None:
            found: dict[str, EntryPoint] = {}
            if self._group is not None:
                for ep in entry_points(group=self._group):
                    dist = getattr(ep.dist, "name", "?")
                    if ep.name in self._builtin:
                        logger.warning("entry point %r of %s in group %s is ignored: the "
                                       "project's policy of that name takes precedence",
                                       ep.name, dist, self._group)
                    elif ep.name in found and found[ep.name].value != ep.value:
                        logger.warning("entry point %r of %s in group %s is ignored: another "
                                       "distribution declares it (%s)", ep.name, dist,
                                       self._group, found[ep.name].value)
                    else:
                        found.setdefault(ep.name, ep)
            self._entry_points = found
        return self._entry_points

    def source(self, name: str) -> str | None:
        """Where ``name`` comes from (``"built-in"``, ``"registered"``, ``"plug-in <value>"``)
        or None when unknown."""
        if name in self._builtin:
            return "built-in"
        if name in self._registered:
            return "registered"
        ep = self._plugins().get(name)
        return None if ep is None else f"plug-in {ep.value}"

    def available(self) -> list[str]:
        """Every name :meth:`make` accepts (besides references), sorted."""
        return sorted({*self._builtin, *self._registered, *self._plugins()})

    def factory(self, spec: str) -> Any:
        """What ``spec`` (a name or a ``module:attribute`` reference) resolves to: a factory or
        a policy object. ``ValueError`` for an unknown name, listing :meth:`available`."""
        if not isinstance(spec, str) or not spec:
            raise self._unknown(spec)
        if spec in self._builtin:
            return self._builtin[spec]
        parameterised = self._builtin_parameterised(spec)
        if parameterised is not None:
            return parameterised
        if spec in self._registered:
            return self._registered[spec]
        if is_reference(spec):
            return load_reference(spec)
        ep = self._plugins().get(spec)
        if ep is None:
            raise self._unknown(spec)
        try:
            return ep.load()
        except Exception as exc:
            raise ValueError(f"policy name={spec!r} is invalid: its entry point {ep.value!r} "
                             f"failed to load ({type(exc).__name__}: {exc})") from exc

    def _builtin_parameterised(self, spec: str) -> Any:
        """The factory of a project name with parameters (:data:`PARAMETERISED`), its options
        bound; None when ``spec`` is not of that form with a project name."""
        match = PARAMETERISED.fullmatch(spec)
        if match is None or match["base"] not in self._builtin:
            return None
        target = self._builtin[match["base"]]
        parse = _parameter_parser(target)
        require(parse is not None, "policy name", spec,
                f"{match['base']!r} without brackets ({match['base']} takes no parameters in "
                "its name)")
        return functools.partial(target, **parse(match["inner"]))

    def _unknown(self, spec: Any) -> ValueError:
        return ValueError(f"policy name={spec!r} is invalid: must be one of "
                          f"{', '.join(self.available())} or a 'package.module:attribute' "
                          "reference")

    def make(self, spec: str, **options: Any) -> Any:
        """Build the policy ``spec`` names with keyword ``options``."""
        target = self.factory(spec)
        if spec in self._builtin or self._builtin_parameterised(spec) is not None:
            return target(**options)
        return build(target, spec, options)

    def digest(self, spec: str) -> str | None:
        """:func:`policy_digest` of what ``spec`` resolves to, or None for the project's own
        names (whose code is the project's)."""
        if spec in self._builtin or self._builtin_parameterised(spec) is not None:
            return None
        return policy_digest(self.factory(spec))

    def needs_shipping(self, spec: str) -> bool:
        """Whether a worker process cannot resolve ``spec`` by itself (a name registered at run
        time: its factory has to travel with the job)."""
        return spec in self._registered and spec not in self._builtin
