"""The registry: kind -> name -> component class, filled from the plugin manager's hooks.

Duplicate names within a kind raise a PluginError naming both plugins and their distributions
(a third-party component may replace a built-in one of the same kind and name only when
``FWK_PLUGIN_OVERRIDES`` lists the name, ``fwk.plugins``); an unknown name raises an
UnknownComponentError that lists the registered choices (and the closest one).

What a plugin author gets wrong silently otherwise is reported as a broken plugin (``fwk list``
prints it on stderr; a recipe naming a component of it says to look there), the other plugins
working on: a hook function fwk does not define (``fwk_register_dataset``) or a
``fwk_register_*`` function not marked ``@hookimpl``; a plugin that registers no component; a
component whose constructor has a parameter without an annotation (the constructor is the
recipe schema: the component is refused, its plugin's others registered).
"""
from __future__ import annotations

import dataclasses
import difflib
import inspect
from dataclasses import dataclass, field

from .errors import PluginError, UnknownComponentError, quote
from .hookspecs import HOOKS, KINDS

#: the distribution whose entry points are fwk's built-in plugins
BUILTIN_DISTRIBUTION = "fwk"


def describe_failure(exc: BaseException) -> str:
    """``Type: message`` of a plugin's failure, in one line of at most ~200 characters."""
    try:
        text = str(exc)
    except Exception:
        text = ""
    text = " ".join(text.split())
    if len(text) > 200:
        text = text[:200] + "..."
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


@dataclass(frozen=True)
class Entry:
    """One registered component: its kind, name, class, and the plugin (and version) that registers
    it."""

    kind: str
    name: str
    component: type
    plugin: str
    version: str
    distribution: str = ""  # the installed distribution that declares the plugin ('' registered by hand)

    @property
    def builtin(self) -> bool:
        """Whether fwk itself registers the component (one of its built-in plugins)."""
        return self.distribution == BUILTIN_DISTRIBUTION

    @property
    def origin(self) -> str:
        """``plugin P`` with its distribution and version where known (for error messages)."""
        dist = f"{self.distribution} {self.version}".strip()
        return f"plugin {self.plugin}" + (f" (distribution {dist})" if self.distribution else "")

    @property
    def summary(self) -> str:
        """The first line of the component's docstring."""
        doc = inspect.getdoc(self.component) or ""
        return doc.strip().splitlines()[0] if doc.strip() else ""


@dataclass
class BrokenPlugin:
    """A plugin that failed to load or register, and why."""

    plugin: str
    error: str


def did_you_mean(word: str, choices) -> str:
    """``'; did you mean X?'`` for the closest of ``choices``, or an empty string."""
    close = difflib.get_close_matches(str(word)[:200], [str(c) for c in choices], n=1, cutoff=0.6)
    return f"; did you mean {close[0]}?" if close else ""


@dataclass
class Registry:
    """kind -> name -> Entry, and the plugins that failed to load."""

    entries: dict[str, dict[str, Entry]] = field(default_factory=lambda: {k: {} for k in KINDS})
    broken: list[BrokenPlugin] = field(default_factory=list)

    def add(self, kind: str, component: type, plugin: str, version: str = "", distribution: str = "",
            overrides=frozenset()) -> None:
        """Register ``component`` under its ``name``: a PluginError if another class has the name,
        unless one is built-in, the other third-party, and ``overrides`` lists the name (then the
        third-party one wins, whichever comes first)."""
        if kind not in self.entries:
            raise PluginError(f"plugin {plugin} registers unknown kind {quote(kind)}")
        name = getattr(component, "name", None)
        if not isinstance(name, str) or not name:
            raise PluginError(f"plugin {plugin}: {kind} class {getattr(component, '__qualname__', quote(component))} "
                              f"has no `name`")
        new = Entry(kind, name, component, plugin, version, distribution)
        old = self.entries[kind].get(name)
        if old is not None and old.component is not component:
            if old.builtin != new.builtin:
                if name in overrides:
                    if old.builtin:
                        self.entries[kind][name] = new
                    return
                third, builtin = (new, old) if old.builtin else (old, new)
                raise PluginError(
                    f"{kind} {quote(name)} of {third.origin} takes the name of fwk's built-in {kind} of "
                    f"{builtin.origin}: uninstall or rename it, or let it replace the built-in with "
                    f"FWK_PLUGIN_OVERRIDES={name}")
            raise PluginError(f"{kind} {quote(name)} is registered twice: by {old.origin} and by {new.origin}")
        self.entries[kind][name] = new

    def get(self, kind: str, name: str, key_path: str | None = None) -> type:
        """The class registered as ``name`` of ``kind`` (an UnknownComponentError listing the
        choices if none)."""
        return self.entry(kind, name, key_path).component

    def entry(self, kind: str, name: str, key_path: str | None = None) -> Entry:
        """The Entry registered as ``name`` of ``kind`` (an UnknownComponentError listing the
        choices if none)."""
        if kind not in self.entries:
            raise UnknownComponentError(f"unknown kind {kind!r}; choices: {', '.join(KINDS)}")
        try:
            return self.entries[kind][name]
        except (KeyError, TypeError):
            choices = sorted(self.entries[kind])
            where = f"{key_path}: " if key_path else ""
            broken = ""
            if self.broken:  # the component may be one of theirs
                names = [b.plugin for b in self.broken]
                broken = (f"; plugins that failed to load (fwk list): {', '.join(names[:3])}"
                          f"{f' and {len(names) - 3} more' if len(names) > 3 else ''}")
            raise UnknownComponentError(
                f"{where}unknown {kind} {quote(name)}{did_you_mean(name, choices)} "
                f"(registered: {', '.join(choices) or 'none'}){broken}"
            ) from None

    def names(self, kind: str) -> list[str]:
        """The registered names of ``kind``, sorted."""
        return sorted(self.entries[kind])

    def __iter__(self):
        for kind in KINDS:
            for name in sorted(self.entries[kind]):
                yield self.entries[kind][name]


def build_registry(pm, overrides=frozenset()) -> Registry:
    """Collect the registrations of every plugin in ``pm`` (a ``fwk.plugins.make_plugin_manager``
    manager, with the plugins' versions and distributions). A plugin whose hook raises (any
    exception, SystemExit included) is reported, not fatal; ``overrides``: the names a
    third-party component may take from a built-in one (``Registry.add``)."""
    reg = Registry()
    dists = getattr(pm, "fwk_dists", {})
    versions = getattr(pm, "fwk_versions", {})
    returned: dict[str, int] = {}  # plugin -> components its hooks returned
    for kind in KINDS:
        hook = getattr(pm.hook, HOOKS[kind])
        for impl in hook.get_hookimpls():
            plugin_name = pm.get_name(impl.plugin) or repr(impl.plugin)
            try:
                comps = list(impl.function() or [])
            except (Exception, SystemExit, KeyboardInterrupt) as exc:  # a broken plugin must not take the others down
                reg.broken.append(BrokenPlugin(plugin_name, describe_failure(exc)))
                continue
            version = versions.get(plugin_name, "")
            returned[plugin_name] = returned.get(plugin_name, 0) + len(comps)
            for comp in comps:
                missing = unannotated_parameters(comp)
                if missing:
                    reg.broken.append(BrokenPlugin(plugin_name, (
                        f"{kind} {quote(getattr(comp, 'name', None) or getattr(comp, '__qualname__', comp))} "
                        f"not registered: constructor parameter{'s' if len(missing) > 1 else ''} "
                        f"{', '.join(missing)} {'have' if len(missing) > 1 else 'has'} no annotation (the constructor "
                        "is the recipe schema: annotate every parameter, docs/writing-a-plugin.md)")))
                    continue
                reg.add(kind, comp, plugin_name, version, dists.get(plugin_name, ""), overrides)
    broken = {b.plugin for b in reg.broken}
    for plugin_name, plugin in pm.list_name_plugin():
        if plugin is None:  # blocked
            continue
        for problem in hook_problems(pm, plugin):
            reg.broken.append(BrokenPlugin(plugin_name, problem))
            broken.add(plugin_name)
        if not returned.get(plugin_name) and plugin_name not in broken:
            dist = f"{dists.get(plugin_name, '')} {versions.get(plugin_name, '')}".strip()
            reg.broken.append(BrokenPlugin(plugin_name, (
                f"registers no component{f' (distribution {dist})' if dist else ''}: none of its hooks "
                f"({', '.join(HOOKS.values())}) returned a class")))
    return reg


def unannotated_parameters(cls) -> list[str]:
    """The constructor parameters of a component class that have no annotation (those the
    framework supplies, ``build_args``, and ``*args`` / ``**kwargs`` aside)."""
    init = cls if dataclasses.is_dataclass(cls) else getattr(cls, "__init__", None)
    if init is None or init is object.__init__:
        return []
    try:
        sig = inspect.signature(init)  # justified: the constructor is the recipe schema (fwk.hookspecs)
    except (TypeError, ValueError):  # justified: a builtin's __init__ has no signature to read
        return []
    supplied = set(getattr(cls, "build_args", ()) or ())
    return [n for n, p in sig.parameters.items()
            if n != "self" and n not in supplied and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)
            and p.annotation is inspect.Parameter.empty]


def hook_problems(pm, plugin) -> list[str]:
    """What a plugin's hooks get wrong silently: a function marked ``@hookimpl`` under a name fwk
    defines no hook for (pluggy accepts it and never calls it), and a ``fwk_register_*``
    function not marked ``@hookimpl`` (pluggy ignores it)."""
    out = []
    known = set(HOOKS.values())
    for attr in sorted(dir(plugin)):
        try:
            obj = getattr(plugin, attr)
        except Exception:  # a plugin attribute that fails to read is not a hook
            continue
        if not callable(obj):
            continue
        marked = pm.parse_hookimpl_opts(plugin, attr) is not None
        if marked and attr not in known:
            out.append(f"hook {attr} is not one of fwk's hooks{did_you_mean(attr, sorted(known))} "
                       f"(fwk never calls it; the hooks: {', '.join(HOOKS.values())})")
        elif not marked and attr in known:
            out.append(f"{attr} is not marked @hookimpl (from fwk.hookspecs import hookimpl): fwk never calls it")
    return out
