"""The plugin manager: built-in and third-party plugins are found through the entry-point
group ``fwk``; ``FWK_NO_ENTRYPOINTS=1`` turns autoloading off (tests, embedding), after which
plugins are registered by hand with ``pm.register(module)``.

A plugin that fails to import, with any exception (``SystemExit`` and ``KeyboardInterrupt``
raised by the plugin included; a Ctrl-C the user presses still interrupts), is recorded in
``pm.fwk_broken`` and reported by ``fwk list``; the other plugins keep working.

A third-party entry point may not take the name of one of fwk's built-in plugins (the entry
points of the distribution ``fwk``), and two distributions may not declare the same entry-point
name: every command refuses to start, in one line naming both distributions. A name listed in
``FWK_PLUGIN_OVERRIDES`` (comma-separated) may be taken: the third-party plugin replaces the
built-in of that name (an entry point, or a component of the same kind, ``fwk.registry``).
"""
from __future__ import annotations

import contextlib
import os
import signal
import threading
from importlib.metadata import entry_points

import pluggy

from . import hookspecs
from .errors import PluginError
from .registry import BUILTIN_DISTRIBUTION, BrokenPlugin, Registry, build_registry, describe_failure

ENTRYPOINT_GROUP = "fwk"
#: names (comma-separated) a third-party plugin may take from a built-in one
ENV_OVERRIDES = "FWK_PLUGIN_OVERRIDES"


def autoload_disabled() -> bool:
    """Whether ``FWK_NO_ENTRYPOINTS`` turns entry-point loading off."""
    return os.environ.get("FWK_NO_ENTRYPOINTS", "").strip() not in ("", "0", "false", "no")


def allowed_overrides() -> frozenset[str]:
    """The names ``FWK_PLUGIN_OVERRIDES`` lets a third-party plugin take from a built-in."""
    return frozenset(n.strip() for n in os.environ.get(ENV_OVERRIDES, "").split(",") if n.strip())


def _dist(ep) -> tuple[str, str]:
    """(distribution name, version) of an entry point ('' when unknown)."""
    d = getattr(ep, "dist", None)
    if d is None:
        return "", ""
    try:
        return str(d.name or ""), str(d.version or "")
    except Exception:  # a distribution with broken metadata
        return "", ""


def _label(ep) -> str:
    name, version = _dist(ep)
    return f"{name} {version}".strip() or "an unknown distribution"


def choose_entry_points(eps) -> list:
    """One entry point per name, sorted by name: a name that several distributions declare is
    refused with a PluginError naming them, unless the clash is a third-party plugin taking a
    built-in's name listed in ``FWK_PLUGIN_OVERRIDES`` (then the third-party one is chosen)."""
    by_name: dict[str, list] = {}
    for ep in eps:
        if not any(ep.value == e.value and _dist(ep) == _dist(e) for e in by_name.get(ep.name, [])):
            by_name.setdefault(ep.name, []).append(ep)
    chosen = []
    for name in sorted(by_name):
        cands = by_name[name]
        if len(cands) == 1:
            chosen.append(cands[0])
            continue
        builtin = [e for e in cands if _dist(e)[0] == BUILTIN_DISTRIBUTION]
        others = [e for e in cands if _dist(e)[0] != BUILTIN_DISTRIBUTION]
        if builtin and len(others) == 1:
            if name in allowed_overrides():
                chosen.append(others[0])
                continue
            raise PluginError(
                f"plugin {name!r} of distribution {_label(others[0])} takes the name of fwk's built-in plugin "
                f"{name!r} (distribution {_label(builtin[0])}): uninstall or rename it, or let it replace the "
                f"built-in with {ENV_OVERRIDES}={name}")
        raise PluginError(f"plugin {name!r} is declared by several distributions ("
                          f"{', '.join(_label(e) for e in cands)}): uninstall all but one")
    return chosen


@contextlib.contextmanager
def _signals_noted():
    """While plugins import: a list that records SIGINT and SIGTERM as they arrive (the
    handlers in place still run), so that a KeyboardInterrupt a plugin raises marks it broken
    while one from the user's Ctrl-C still stops fwk."""
    seen: list[int] = []
    old = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            prev = signal.getsignal(sig)
            if callable(prev):  # a Python handler (default_int_handler, fwk's SIGTERM handler)
                def note(signum, frame, prev=prev):
                    seen.append(signum)
                    prev(signum, frame)

                old[sig] = prev
                signal.signal(sig, note)
    try:
        yield seen
    finally:
        for sig, prev in old.items():
            signal.signal(sig, prev)


def make_plugin_manager(load_entrypoints: bool | None = None, plugins=()) -> pluggy.PluginManager:
    """A pluggy manager with fwk's hooks, the entry-point plugins (unless disabled) and ``plugins``;
    plugins that fail to load are recorded in ``fwk_broken``, versions in ``fwk_versions``,
    distributions in ``fwk_dists``."""
    pm = pluggy.PluginManager(hookspecs.PROJECT)
    pm.add_hookspecs(hookspecs)
    pm.fwk_broken = []
    pm.fwk_versions = {}
    pm.fwk_dists = {}
    if load_entrypoints is None:
        load_entrypoints = not autoload_disabled()
    if load_entrypoints:
        with _signals_noted() as seen:
            for ep in choose_entry_points(entry_points(group=ENTRYPOINT_GROUP)):
                if pm.has_plugin(ep.name):
                    continue
                try:
                    module = ep.load()
                    pm.register(module, name=ep.name)
                except BaseException as exc:  # noqa: B036 - SystemExit, KeyboardInterrupt of a plugin included
                    if seen:  # the user pressed Ctrl-C, or fwk was told to stop: not the plugin's fault
                        raise
                    pm.fwk_broken.append(BrokenPlugin(ep.name, describe_failure(exc)))
                    continue
                pm.fwk_dists[ep.name], pm.fwk_versions[ep.name] = _dist(ep)
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
        reg = build_registry(pm, overrides=allowed_overrides())
        reg.broken[:0] = pm.fwk_broken
        _REGISTRY = reg
    return _REGISTRY


def registry_from(*plugins, load_entrypoints: bool = False) -> Registry:
    """A registry from explicit plugin modules (tests, embedding)."""
    pm = make_plugin_manager(load_entrypoints=load_entrypoints, plugins=plugins)
    reg = build_registry(pm, overrides=allowed_overrides())
    reg.broken[:0] = pm.fwk_broken
    return reg
