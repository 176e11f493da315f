"""The plugin manager: built-in and third-party plugins are found through the entry-point
group ``fwk``; ``FWK_NO_ENTRYPOINTS=1`` turns autoloading off (tests, embedding), after which
plugins are registered by hand with ``pm.register(module)``.

A plugin that fails to import is recorded in ``pm.fwk_broken`` and reported by ``fwk list``;
the other plugins keep working.
"""
from __future__ import annotations

import os
from importlib.metadata import entry_points

import pluggy

from . import hookspecs
from .registry import BrokenPlugin, Registry, build_registry

ENTRYPOINT_GROUP = "fwk"


def autoload_disabled() -> bool:
    """Whether ``FWK_NO_ENTRYPOINTS`` turns entry-point loading off."""
    return os.environ.get("FWK_NO_ENTRYPOINTS", "").strip() not in ("", "0", "false", "no")


def make_plugin_manager(load_entrypoints: bool | None = None, plugins=()) -> pluggy.PluginManager:
    """A pluggy manager with fwk's hooks, the entry-point plugins (unless disabled) and ``plugins``;
    plugins that fail to load are recorded in ``fwk_broken``, versions in ``fwk_versions``."""
    pm = pluggy.PluginManager(hookspecs.PROJECT)
    pm.add_hookspecs(hookspecs)
    pm.fwk_broken = []
    pm.fwk_versions = {}
    if load_entrypoints is None:
        load_entrypoints = not autoload_disabled()
    if load_entrypoints:
        for ep in sorted(entry_points(group=ENTRYPOINT_GROUP), key=lambda e: e.name):
            if pm.has_plugin(ep.name):
                continue
            try:
                module = ep.load()
                pm.register(module, name=ep.name)
            except Exception as exc:
                pm.fwk_broken.append(BrokenPlugin(ep.name, f"{type(exc).__name__}: {exc}"))
                continue
            pm.fwk_versions[ep.name] = ep.dist.version if ep.dist else ""
    for plugin in plugins:
        name = getattr(plugin, "__name__", None)
        if not pm.is_registered(plugin):
            pm.register(plugin, name=name)
    return pm


_REGISTRY: Registry | None = None


def get_registry(refresh: bool = False) -> Registry:
    """The process-wide registry built from the entry points (cached)."""
    global _REGISTRY
    if _REGISTRY is None or refresh:
        pm = make_plugin_manager()
        reg = build_registry(pm)
        reg.broken[:0] = pm.fwk_broken
        _REGISTRY = reg
    return _REGISTRY


def registry_from(*plugins, load_entrypoints: bool = False) -> Registry:
    """A registry from explicit plugin modules (tests, embedding)."""
    pm = make_plugin_manager(load_entrypoints=load_entrypoints, plugins=plugins)
    reg = build_registry(pm)
    reg.broken[:0] = pm.fwk_broken
    return reg
