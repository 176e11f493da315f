"""The registry: kind -> name -> component class, filled from the plugin manager's hooks.

Duplicate names within a kind raise a PluginError naming both plugins; an unknown name raises
an UnknownComponentError that lists the registered choices (and the closest one).
"""
from __future__ import annotations

import difflib
import inspect
from dataclasses import dataclass, field

from .errors import PluginError, UnknownComponentError
from .hookspecs import HOOKS, KINDS


@dataclass(frozen=True)
class Entry:
    """One registered component: its kind, name, class, and the plugin (and version) that registers
    it."""

    kind: str
    name: str
    component: type
    plugin: str
    version: str

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
    close = difflib.get_close_matches(str(word), [str(c) for c in choices], n=1, cutoff=0.6)
    return f"; did you mean {close[0]}?" if close else ""


@dataclass
class Registry:
    """kind -> name -> Entry, and the plugins that failed to load."""

    entries: dict[str, dict[str, Entry]] = field(default_factory=lambda: {k: {} for k in KINDS})
    broken: list[BrokenPlugin] = field(default_factory=list)

    def add(self, kind: str, component: type, plugin: str, version: str = "") -> None:
        """Register ``component`` under its ``name`` (a PluginError if another class has the name)."""
        if kind not in self.entries:
            raise PluginError(f"plugin {plugin} registers unknown kind {kind!r}")
        name = getattr(component, "name", None)
        if not isinstance(name, str) or not name:
            raise PluginError(f"plugin {plugin}: {kind} class {component.__qualname__} has no `name`")
        old = self.entries[kind].get(name)
        if old is not None and old.component is not component:
            raise PluginError(
                f"{kind} {name!r} is registered twice: by plugin {old.plugin} and by plugin {plugin}"
            )
        self.entries[kind][name] = Entry(kind, name, component, plugin, version)

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
            raise UnknownComponentError(
                f"{where}unknown {kind} {name!r}{did_you_mean(name, choices)} "
                f"(registered: {', '.join(choices) or 'none'})"
            ) from None

    def names(self, kind: str) -> list[str]:
        """The registered names of ``kind``, sorted."""
        return sorted(self.entries[kind])

    def __iter__(self):
        for kind in KINDS:
            for name in sorted(self.entries[kind]):
                yield self.entries[kind][name]


def build_registry(pm) -> Registry:
    """Collect the registrations of every plugin in ``pm`` (a ``fwk.plugins.make_plugin_manager``
    manager, with the plugins' versions). A plugin whose hook raises is reported, not fatal."""
    reg = Registry()
    for kind in KINDS:
        hook = getattr(pm.hook, HOOKS[kind])
        for impl in hook.get_hookimpls():
            plugin_name = pm.get_name(impl.plugin) or repr(impl.plugin)
            try:
                comps = impl.function() or []
            except Exception as exc:  # a broken plugin must not take the others down
                reg.broken.append(BrokenPlugin(plugin_name, f"{type(exc).__name__}: {exc}"))
                continue
            version = pm.fwk_versions.get(plugin_name, "")
            for comp in comps:
                reg.add(kind, comp, plugin_name, version)
    return reg
