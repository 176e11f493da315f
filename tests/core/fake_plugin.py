"""A small plugin used by the core tests (components of several kinds)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

from fwk.hookspecs import hookimpl
from fwk.recipes import Kind, Spec


class Spiralish:
    """A conv-like component with a length parameter (the conv role's members as stubs: recipe
    validation checks the role)."""

    name = "spiralish"
    build_args = ("in_channels", "out_channels", "hierarchy", "level")
    strided = False

    def __init__(self, in_channels: int = 3, out_channels: int = 3, hierarchy=None, level: int = 0,
                 length: int = 9, dilation: list[int] | None = None, bias: bool = True):
        self.length = length

    def forward(self, x):
        return x

    def reset_parameters(self) -> None:
        pass


class Modelish:
    """A model-like component with a nested conv (the model role's members as stubs)."""

    name = "modelish"
    task_family = "reconstruct"

    def __init__(self, conv: Annotated[Spec, Kind("conv")] = "spiralish", latent: int = 8, lr: float = 1e-3):
        self.conv, self.latent, self.lr = conv, latent, lr

    def fit(self, data, ctx) -> None:
        pass

    def state_dict(self) -> dict:
        return {}

    def load_state_dict(self, d: dict, ctx=None) -> None:
        pass


@dataclass
class Opts:
    alpha: float = 1.0
    flag: bool = False


class Taskish:
    """A task-like component."""

    name = "taskish"
    ran: list = []

    def __init__(self, model: Annotated[Spec, Kind("model")] = "modelish",
                 models: Annotated[dict[str, Spec], Kind("model")] | None = None, opts: Opts | None = None,
                 count: int = 1):
        self.model, self.models, self.opts, self.count = model, models, opts, count

    def run(self, ctx):
        ctx.write_json("metrics.json", {"count": self.count})
        Taskish.ran.append(ctx.run_dir)


@hookimpl
def fwk_register_convs():
    return [Spiralish]


@hookimpl
def fwk_register_models():
    return [Modelish]


@hookimpl
def fwk_register_tasks():
    return [Taskish]
