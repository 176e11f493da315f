"""What fwk checks of a plugin before it trains or loads data (issue 30, item 3): each with the
one-line message a plugin author reads."""
from __future__ import annotations

import pytest
import torch
from torch import nn

from fwk.errors import PluginError
from fwk.protocols import CONV_BUILD_ARGS, Conv, plays
from fwk.recipes import Spec, make_spec
from fwk.testing.model import tiny_fit_data


# ----------------------------------------------------------------------------- conv output shapes

class Narrow(nn.Module):
    """A conv that returns one channel too few (a plugin author's slip)."""

    name = "narrow"
    build_args = CONV_BUILD_ARGS
    strided = False

    def __init__(self, in_channels: int, out_channels: int, hierarchy=None, level: int = 0, short: int = 1):
        super().__init__()
        self.lin = nn.Linear(in_channels, out_channels - short)

    def reset_parameters(self) -> None:
        self.lin.reset_parameters()

    def forward(self, x):
        return self.lin(x)


class Raising(Narrow):
    """A conv whose forward fails."""

    name = "raising"

    def forward(self, x):
        raise ValueError("index 7 is out of bounds\nsecond line")


def _ae(conv_cls, **params):
    from fwk.plugins import get_registry

    reg = get_registry()
    model = reg.get("model", "ae")
    assert plays(conv_cls, Conv)
    conv = Spec("conv", conv_cls.name, {}, conv_cls, "models.ae.network.conv")
    sampler = make_spec("sampler", {"name": "simple", "levels": 2}, "models.ae.network.sampler", reg)
    return model(conv=conv, sampler=sampler, channels=[8, 16], latent=4, **params)


@pytest.fixture(scope="module")
def template():
    return tiny_fit_data(n_subjects=4).template


@pytest.mark.parametrize("layout", [{}, {"fully_convolutional": True}, {"latent_vertices": 2}])
def test_a_conv_of_the_wrong_width_stops_the_build_in_one_line(template, layout):
    m = _ae(Narrow, **layout)
    with pytest.raises(PluginError) as e:
        m.build_encoder(template, 3)
    msg = str(e.value)
    assert "\n" not in msg
    assert msg.startswith("models.ae.network.conv: conv 'narrow'")
    assert "at level " in msg and ("encoder" in msg or "strided" in msg), msg
    n0 = template.n_vertices
    if not layout:  # the first encoder conv: level 0, 3 -> 8 channels, 7 came back
        assert f"(1, {n0}, 3) to (1, {n0}, 7), expected (1, {n0}, 8)" in msg, msg


def test_the_decoder_output_conv_is_checked(template):
    m = _ae(Narrow)
    with pytest.raises(PluginError, match=r"conv 'narrow' .* at level \d, decoder block"):
        m.build_decoder(template, 3)


def test_a_conv_whose_forward_raises_is_named(template):
    with pytest.raises(PluginError) as e:
        _ae(Raising).build_encoder(template, 3)
    msg = str(e.value)
    assert "\n" not in msg and "conv 'raising'" in msg and "at level 0" in msg
    assert "raised ValueError: index 7 is out of bounds" in msg


def test_the_check_leaves_the_random_stream_alone(template):
    """Building checks each conv on zeros: the same seed gives the same weights and the same draws
    after the build, and the convs keep their train mode."""
    out = []
    for _ in range(2):
        torch.manual_seed(0)
        net = _ae_ok().build_encoder(template, 3)
        out.append(([p.detach().clone() for p in net.parameters()], torch.rand(3)))
        assert all(m.training for m in net.modules())
    (pa, ra), (pb, rb) = out
    assert torch.equal(ra, rb) and all(torch.equal(p, q) for p, q in zip(pa, pb))


def _ae_ok():
    from fwk.plugins import get_registry

    reg = get_registry()
    model = reg.get("model", "ae")
    conv = make_spec("conv", "spiral++", "models.ae.conv", reg)  # name-ok: a built-in conv to compare with
    sampler = make_spec("sampler", "quadric", "models.ae.sampler", reg)  # name-ok: its sampler
    return model(conv=conv, sampler=sampler, channels=[8, 16], latent=4)
