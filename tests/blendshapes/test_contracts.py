"""Every built-in blendshape model passes the BlendshapeModelContract: pb (end-to-end and
two-step), pbs (composite, cut-selecting) and dt. Tiny data, one epoch."""
from fwk.testing.blendshapes import BlendshapeModelContract
from fwk_dt import DeformationTransfer
from fwk_pb import PB, PBS

NET = {"name": "vae", "channels": [8], "latent": 4, "sampler": {"name": "quadric", "factors": [4]}}


class TestPBEndToEnd(BlendshapeModelContract):
    component = PB
    params = {"network": NET}


class TestPBTwoStepDR(BlendshapeModelContract):
    component = PB
    params = {"network": NET, "mode": "two-step", "representation": "dr"}


class TestPBS(BlendshapeModelContract):
    component = PBS
    params = {"network": NET, "ks": [0, 10, 40, 10_000]}


class TestDT(BlendshapeModelContract):
    component = DeformationTransfer
    params = {"sources": 0}


class TestDTFromTheMeanSubject(BlendshapeModelContract):
    """Beyond the thesis: the mean training subject as the source (``sources: mean``)."""
    component = DeformationTransfer
    params = {"sources": "mean"}


class TestPBSAnchoredOnDT(BlendshapeModelContract):
    """Beyond the thesis: both networks learn the residual from Deformation Transfer's output."""
    component = PBS
    params = {"network": NET, "ks": [0, 10, 40, 10_000], "anchor": {"name": "dt", "sources": [0, 1]}}


class TestPBSBending(BlendshapeModelContract):
    """Beyond the thesis: the spatial network trained with the bending term."""
    component = PBS
    params = {"network": NET, "ks": [0, 10, 40, 10_000], "bending_weight": 1.0}


class TestPBSShippable(BlendshapeModelContract):
    """The shipped rig model's form (recipes/rig_ict_shipped.yaml): anchored on DT from the mean
    training subject, scaled per channel; its packed state (``Packable``) cuts the basis."""
    component = PBS
    params = {"network": NET, "ks": [0, 10, 40, 10_000], "anchor": {"name": "dt", "sources": "mean"},
              "spatial": {"name": "euclidean", "scaling": "std", "granularity": "channel"},
              "differential": {"name": "dr", "scaling": "std", "granularity": "channel"}}
