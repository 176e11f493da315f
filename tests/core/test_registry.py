import types

import pytest

from fwk.errors import PluginError
from fwk.hookspecs import hookimpl
from fwk.plugins import registry_from

from . import fake_plugin


def _plugin(name, **hooks):
    m = types.ModuleType(name)
    for k, v in hooks.items():
        setattr(m, k, hookimpl(v))
    return m


def test_duplicate_names_name_both_plugins():
    class A:
        """a"""
        name = "dup"

    class B:
        """b"""
        name = "dup"

    p1 = _plugin("plug_one", fwk_register_metrics=lambda: [A])
    p2 = _plugin("plug_two", fwk_register_metrics=lambda: [B])
    with pytest.raises(PluginError, match=r"metric 'dup' is registered twice: by plugin plug_\w+ and by plugin plug_\w+"):
        registry_from(p1, p2)


def test_broken_plugin_reported_others_work():
    def boom():
        raise RuntimeError("kaputt")

    bad = _plugin("bad_plugin", fwk_register_models=boom)
    reg = registry_from(fake_plugin, bad)
    assert "modelish" in reg.names("model")
    assert any(b.plugin == "bad_plugin" and "kaputt" in b.error for b in reg.broken)


def test_entrypoint_autoload_switch(monkeypatch):
    from fwk.plugins import make_plugin_manager

    monkeypatch.setenv("FWK_NO_ENTRYPOINTS", "1")
    pm = make_plugin_manager()
    assert pm.get_plugins() == set()


def test_builtin_entrypoints_load_without_breakage():
    from fwk.plugins import get_registry

    reg = get_registry(refresh=True)
    assert not reg.broken, reg.broken
    for kind in ("dataset", "representation", "model", "metric", "task"):
        assert reg.names(kind), kind


def test_every_kind_registers_through_its_hook():
    from fwk.hookspecs import HOOKS, KINDS

    classes = {}
    hooks = {}
    for kind in KINDS:
        cls = type(f"C_{kind}", (), {"name": f"x-{kind}", "__doc__": f"A {kind}."})
        classes[kind] = cls
        hooks[HOOKS[kind]] = (lambda c: (lambda: [c]))(cls)
    # fwk_register_datasets fwk_register_representations fwk_register_samplers fwk_register_convs
    # fwk_register_models fwk_register_metrics fwk_register_assemblers fwk_register_tasks
    reg = registry_from(_plugin("all_kinds", **hooks))
    for kind in KINDS:
        assert reg.get(kind, f"x-{kind}") is classes[kind]
        assert reg.entry(kind, f"x-{kind}").summary == f"A {kind}."
