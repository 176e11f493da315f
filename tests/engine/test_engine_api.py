"""fwk.engine's names: named classes, importable from the package; the import costs stay where
they belong (TrainConfig without torch, `fwk list` without Lightning)."""
import dataclasses
import subprocess
import sys

import lightning.pytorch as pl
import pytest
import torch

import fwk.engine
from fwk.engine import (AutoencoderModule, EpochSampler, LossModule, ManualSchedulers, RNGState, TrainConfig,
                        autoencoder_module, fit, kl_divergence, loss_module)


def test_every_exported_name_resolves():
    for name in fwk.engine.__all__:
        assert getattr(fwk.engine, name) is not None
    assert set(fwk.engine.__all__) <= set(dir(fwk.engine))
    with pytest.raises(AttributeError):
        fwk.engine.no_such_name  # noqa: B018


def test_named_classes():
    assert dataclasses.is_dataclass(TrainConfig)
    assert issubclass(LossModule, pl.LightningModule) and issubclass(AutoencoderModule, LossModule)
    assert issubclass(RNGState, pl.Callback) and issubclass(ManualSchedulers, pl.Callback)
    assert issubclass(EpochSampler, torch.utils.data.Sampler)
    for obj in (TrainConfig, LossModule, AutoencoderModule, RNGState, ManualSchedulers, fit, kl_divergence):
        assert "<locals>" not in obj.__qualname__ and obj.__doc__


def test_call_forms_build_the_named_modules():
    net = torch.nn.Module()
    net.enc, net.dec = torch.nn.Linear(4, 2), torch.nn.Linear(2, 4)
    m = loss_module({"net": net}, lambda module, batch, stage: 0.0)
    assert type(m) is LossModule and list(m.state_dict()) == [f"net.{k}" for k in net.state_dict()]
    a = autoencoder_module(net, lambda F: F, 0.0)
    assert type(a) is AutoencoderModule and list(a.state_dict()) == list(m.state_dict())


def _imports(code: str) -> set:
    r = subprocess.run([sys.executable, "-c", code + "\nimport sys; print(' '.join(sys.modules))"],
                       capture_output=True, text=True, check=True)
    return set(r.stdout.split())


def test_recipes_and_runs_import_neither_torch_nor_lightning():
    # torch costs ~1 s of import time and Lightning ~2.2 s more: `fwk --help` must not pay them
    loaded = _imports("import fwk.engine.config, fwk.recipes, fwk.runs, fwk.cli")
    assert "torch" not in loaded and "lightning" not in loaded


def test_fwk_list_does_not_import_lightning():
    # plugins import fwk.engine names (fit, loss_module, ...) at their top; Lightning loads on training
    loaded = _imports("from fwk.cli import main; main(['list'])")
    assert "lightning" not in loaded
