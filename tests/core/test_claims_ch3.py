"""benchmarks/claims_ch3.py reads a chapter 3 grid run and decides C1/C2 per conv by the sign of
differences of means: checked on a fake run whose answers are known."""
import json

from .scripts import load_benchmark


def _module():
    return load_benchmark("claims_ch3")


def _member(run, name, l1, dame, l2=None, fmpd=None, network="ae"):
    """A finished member; ``network``: the training record's name (vcconv's AE trains "ae/vae")."""
    d = run / name
    d.mkdir(parents=True)
    res = {"test": {k: {"mean": v} for k, v in {"l1": l1, "l2": l2 or l1 ** 2, "dame": dame,
                                                  "fmpd": fmpd or dame}.items()}}
    t = {"epochs_run": 20, "max_epochs": 50, "stopped_by": "early_stopping", "plateau": "plateau"}
    (d / "metrics.json").write_text(json.dumps({"models": {"ae": res}, "training": {"networks": {network: t}},
                                                "timing": {"ae": {"fit_s": 60.0}}}))


def test_c1_and_c2_per_conv(tmp_path, capsys):
    run = tmp_path / "plateau-1"
    # spiral: the thesis's pattern (Std. best L1, DR best DAME; Std. beats raw on both)
    _member(run, "spiral-euclidean", 3.0, 0.5)
    _member(run, "spiral-euclidean-std", 2.0, 0.4)
    _member(run, "spiral-dr-norm", 2.5, 0.1)
    # lsa: DR best on everything (C1 fails on L1), raw Euclidean better DAME than Std. (C2 fails)
    _member(run, "lsa-euclidean", 3.0, 0.3)
    _member(run, "lsa-euclidean-std", 2.9, 0.4)
    _member(run, "lsa-dr-norm", 1.0, 0.1, network="ae/vae")  # a network of another kind inside the model
    _member(run, "feast-euclidean", 3.0, 0.3)  # incomplete conv
    assert _module().main([str(run)]) == 0
    out = capsys.readouterr().out
    assert "| spiral | yes | yes | yes | yes | yes | yes |" in out
    assert "| lsa | no | no | yes | yes | yes | no |" in out
    assert "| feast | incomplete |" in out and "| vcconv | euclidean | missing |" in out
    assert "holds for 1 of 2 complete convs; C2 (Std. lowers both L1 and DAME) for 1 of 2." in out
