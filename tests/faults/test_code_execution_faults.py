"""No code runs when fwk opens a file (issue 25, item 1): a pickle payload planted in a model file,
a checkpoint, a cache entry or another file of a run directory never runs, through ``fwk apply``,
``fwk sample``, ``fwk report``, ``fwk run --resume`` and a recipe's ``run:`` key (task ``edit``).
Each case ends in a clean refusal (exit 2, at most 3 lines on stderr, no traceback) or in correct
operation, and the file the payload would create does not exist."""
from __future__ import annotations

import hashlib
import hmac
import io
import json
import os
import pickle
import shutil
import subprocess
import sys

import numpy as np
import pytest
import torch

from fwk.cache import Cache
from fwk.cli import main
from fwk.errors import FwkError
from fwk.safeio import load_state
from tests.faults.common import models
from tests.faults.run_fixtures import (_pickled, blendshapes_run, copy_run, edit_recipe, fwk_sub,  # noqa: F401
                                       marker, pca_run, refused, sample, trained_run)


class Payload:
    """What a hostile file holds: unpickling it runs ``touch MARKER``."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def test_the_payload_is_live(tmp_path):
    """The payload these tests plant does run when unpickled: its absence below means something."""
    m = tmp_path / "ran"
    torch.load(io.BytesIO(_pickled({"x": Payload(m)})), weights_only=False)
    assert m.exists()


# ------------------------------------------------------------------------------- model files

@pytest.mark.parametrize("layout", ["pickle-as-safetensors", "old-pt"])
def test_model_file_payload(pca_run, tmp_path, env, capsys, marker, layout):
    """A pickled state with a payload beside the real tensors, as the model file (under the new
    name, or under an earlier version's ``models/pca.pt``): sample, resume and a recipe's
    ``run:`` refuse it in one line; report (which opens no model) works."""
    d = copy_run(pca_run[0], tmp_path)
    state = load_state(d / "models" / "pca.safetensors")
    bad = _pickled({**state, "x": Payload(marker)})
    if layout == "old-pt":
        (d / "models" / "pca.safetensors").unlink()
        (d / "models" / "pca.pt").write_bytes(bad)
    else:
        (d / "models" / "pca.safetensors").write_bytes(bad)
    capsys.readouterr()
    refused(capsys, sample(d, tmp_path), "fwk convert", "--trust", "pca")
    refused(capsys, main(["--quiet", "run", "--resume", str(d)]), "fwk convert", "--trust")
    refused(capsys, edit_recipe(d, tmp_path), "fwk convert", "--trust")
    assert main(["--quiet", "report", str(d)]) == 0


def test_apply_refuses_a_model_file_payload(blendshapes_run, tmp_path, env, capsys, marker):
    d = copy_run(blendshapes_run[0], tmp_path)
    state = load_state(d / "models" / "dt.safetensors")
    (d / "models" / "dt.safetensors").unlink()
    (d / "models" / "dt.pt").write_bytes(_pickled({**state, "x": Payload(marker)}))
    capsys.readouterr()
    rc = main(["--quiet", "apply", str(d), str(blendshapes_run[1]), "--out", str(tmp_path / "out")])
    refused(capsys, rc, "dt.pt", "fwk convert")


def test_cli_refusal_in_a_subprocess(pca_run, tmp_path, env, marker):
    """The real command line: exit 2, one line, no traceback."""
    d = copy_run(pca_run[0], tmp_path)
    (d / "models" / "pca.safetensors").write_bytes(_pickled({"x": Payload(marker)}))
    p = subprocess.run([sys.executable, "-m", "fwk", "sample", str(d), "--out", str(tmp_path / "s")],
                       env=env, capture_output=True, text=True, timeout=120)
    assert p.returncode == 2 and len(p.stderr.strip().splitlines()) == 1 and "Traceback" not in p.stderr, p.stderr


# ------------------------------------------------------------------------------- checkpoints

def test_checkpoint_payload_is_refused_on_resume(trained_run, tmp_path, env, capsys, marker):
    """A run killed before its network's model file was saved resumes from the checkpoint: a
    pickled ``last.ckpt`` (an earlier version's, or planted) is refused, never unpickled, and so
    is a pickled epoch file behind a damaged ``last.ckpt`` (where resume falls back to it)."""
    d = copy_run(trained_run[0], tmp_path)
    (d / "models" / "mlp.safetensors").unlink()
    (d / "metrics.json").unlink()
    (ck,) = (d / "checkpoints").rglob("last.ckpt")
    good = load_state(ck)
    ck.write_bytes(_pickled({**good, "x": Payload(marker)}))
    capsys.readouterr()
    refused(capsys, main(["--quiet", "run", "--resume", str(d)]), "last.ckpt", "fwk convert")
    ck.write_bytes(ck.read_bytes()[:100])  # damaged: the epoch file serves
    (ep,) = ck.parent.glob("epoch*.ckpt")
    ep.write_bytes(_pickled({**good, "x": Payload(marker)}))
    refused(capsys, main(["--quiet", "run", "--resume", str(d)]), ep.name, "fwk convert")


def test_checkpoint_payload_of_a_finished_model(trained_run, tmp_path, env, capsys, marker):
    """Pickled checkpoints beside finished models: ``--resume`` refuses the run before it opens
    anything (its files are an earlier version's, or planted); ``sample`` and ``report``, which
    read model files only, work; a recipe's ``run:`` opens no checkpoint either."""
    d = copy_run(trained_run[0], tmp_path)
    for ck in (d / "checkpoints").rglob("*.ckpt"):
        ck.write_bytes(_pickled({"x": Payload(marker)}))
    capsys.readouterr()
    refused(capsys, main(["--quiet", "run", "--resume", str(d)]), ".ckpt", "fwk convert")
    assert not (d / "FAILED").exists()  # refused before anything was written
    assert sample(d, tmp_path) == 0
    assert main(["--quiet", "report", str(d)]) == 0 and models(d) == trained_run[1]
    capsys.readouterr()
    # edit needs a band model: the PCA and MLP run is refused for that, after every model loaded
    refused(capsys, edit_recipe(d, tmp_path), "no dsm model to edit")


# ------------------------------------------------------------------------------- the cache

def _forge(cache_root, marker):
    """Every pickled entry of the cache replaced by a payload, with the SHA-256 the cache checked
    before and an HMAC under a key that is not the user's (what someone else can write)."""
    n = 0
    for b in cache_root.rglob("*.bin"):
        data = pickle.dumps(Payload(marker))
        b.write_bytes(data)
        b.with_suffix(".sha256").write_text(hashlib.sha256(data).hexdigest())
        mac = hmac.new(b"not the user's key" * 4, f"fwk-cache/1\0{b.parent.name}\0{b.stem}\0".encode(),
                       hashlib.sha256)
        mac.update(data)
        b.with_suffix(".hmac").write_text(mac.hexdigest())
        n += 1
    for a in cache_root.rglob("*.npy"):  # an object array: numbers only are read (allow_pickle=False)
        buf = io.BytesIO()
        np.save(buf, np.array([Payload(marker)], dtype=object), allow_pickle=True)
        a.write_bytes(buf.getvalue())
        a.with_suffix(".sha256").write_text(hashlib.sha256(buf.getvalue()).hexdigest())
        n += 1
    return n


def test_cache_entry_payload_unit(tmp_path, capsys, marker):
    c = Cache(tmp_path / "cache")
    assert c.get_or_build("ns", ("k",), lambda: {"a": np.arange(3)})["a"].tolist() == [0, 1, 2]
    assert _forge(tmp_path / "cache", marker) == 1
    capsys.readouterr()
    v = c.get_or_build("ns", ("k",), lambda: {"a": np.arange(3)})
    assert v["a"].tolist() == [0, 1, 2]
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not unpickled, rebuilt" in err, err


def test_cache_payload_through_apply_sample_and_resume(blendshapes_run, pca_run, tmp_path, env, capsys, marker):
    """The obj-topology entries ``fwk apply`` reads (in a new process: nothing memoised), and the
    synthetic heads' array ``fwk sample`` and ``--resume`` read: planted, they are rebuilt with one
    warning line each, never unpickled, and the commands work."""
    d = copy_run(blendshapes_run[0], tmp_path)
    cache = tmp_path / "cache"
    shutil.copytree(blendshapes_run[0].parents[1] / "cache", cache)
    assert _forge(cache, marker) >= 1
    rc, err = fwk_sub(env, "apply", d, blendshapes_run[1], "--out", tmp_path / "out")
    assert rc == 0 and "not unpickled, rebuilt" in err and "Traceback" not in err, err
    assert list((tmp_path / "out").rglob("*.obj"))
    p = copy_run(pca_run[0], tmp_path)
    shutil.rmtree(cache)
    shutil.copytree(pca_run[0].parents[1] / "cache", cache)
    assert _forge(cache, marker) >= 1
    assert sample(p, tmp_path) == 0
    assert "rebuilt" in capsys.readouterr().err
    assert _forge(cache, marker) >= 1
    assert main(["--quiet", "run", "--resume", str(p)]) == 0 and models(p) == pca_run[1]
    assert "rebuilt" in capsys.readouterr().err


def test_cache_key_others_can_read_is_refused(blendshapes_run, tmp_path, env, monkeypatch):
    """A key file others may read or write is refused in one line (with it, anyone could forge
    entries); so is one another user owns (root only: chown)."""
    key = tmp_path / "key"
    key.write_text("k" * 64)
    key.chmod(0o644)
    monkeypatch.setenv("FWK_KEY_FILE", str(key))
    with pytest.raises(FwkError, match="chmod 600"):
        Cache(tmp_path / "c").store("ns", "k", 1)
    assert not list((tmp_path / "c").rglob("*.bin"))
    rc, err = fwk_sub({**env, "FWK_KEY_FILE": str(key)}, "apply", blendshapes_run[0], blendshapes_run[1],
                      "--out", tmp_path / "out")
    assert rc == 2 and len(err.strip().splitlines()) == 1 and str(key) in err and "chmod 600" in err, err
    if os.getuid() == 0:
        key.chmod(0o600)
        os.chown(key, 12345, -1)
        monkeypatch.setenv("FWK_KEY_FILE", str(key))
        with pytest.raises(FwkError, match="another user"):
            Cache(tmp_path / "c2").store("ns", "k", 1)


def test_cache_key_is_created_private(tmp_path, monkeypatch):
    key = tmp_path / "cfg" / "fwk" / "cache.key"
    monkeypatch.setenv("FWK_KEY_FILE", str(key))
    c = Cache(tmp_path / "c")
    c.store("ns", "k", {"v": 1})
    assert key.stat().st_mode & 0o777 == 0o600 and c.load("ns", "k") == {"v": 1}


# ------------------------------------------------------------------------------- other run files

def test_npz_payload_in_a_run(pca_run, tmp_path, env, capsys, marker):
    """``stats/preprocess.npz`` with a pickled object array: never unpickled (sample and a recipe's
    ``run:`` refuse it naming the file; resume recomputes the preprocessing and works)."""
    d = copy_run(pca_run[0], tmp_path)
    buf = io.BytesIO()
    np.savez(buf, mean_neutral=np.array([Payload(marker)], dtype=object))
    (d / "stats" / "preprocess.npz").write_bytes(buf.getvalue())
    capsys.readouterr()
    refused(capsys, sample(d, tmp_path), "preprocess.npz")
    refused(capsys, edit_recipe(d, tmp_path), "preprocess.npz")
    assert main(["--quiet", "run", "--resume", str(d)]) == 0 and models(d) == pca_run[1]


# ------------------------------------------------------------------------------- fwk convert

def test_convert_old_run(trained_run, tmp_path, env, capsys):
    """A run as an earlier fwk wrote it (pickled models and checkpoints, no recipe hash) is
    refused until ``fwk convert RUN --trust``; after it the run opens with identical metrics.
    Without --trust nothing is unpickled."""
    from fwk.lifecycle import open_run

    d = copy_run(trained_run[0], tmp_path)
    run = open_run(d)
    for label in run.specs:  # as earlier versions saved them: torch.save(model.state_dict())
        torch.save(run.model(label).state_dict(), d / "models" / f"{label}.pt")
        (d / "models" / f"{label}.safetensors").unlink()
    for ck in (d / "checkpoints").rglob("*.ckpt"):  # and as Lightning's TorchCheckpointIO did
        torch.save(load_state(ck), ck)
    v = json.loads((d / "versions.json").read_text())
    v.pop("recipe_sha256")
    (d / "versions.json").write_text(json.dumps(v))
    (d / "metrics.json").unlink()  # recomputed by the resume below: the same numbers or the test fails
    capsys.readouterr()
    refused(capsys, main(["--quiet", "run", "--resume", str(d)]), "fwk convert", "--trust")
    refused(capsys, main(["convert", str(d)]), "--trust", "runs any code")
    assert len(list((d / "models").glob("*.pt"))) == 2
    assert main(["convert", str(d), "--trust"]) == 0
    out = capsys.readouterr().out
    assert "unpickling" in out and "runs any code" in out
    assert not list((d / "models").glob("*.pt")) and len(list((d / "models").glob("*.safetensors"))) == 2
    assert "recipe_sha256" in json.loads((d / "versions.json").read_text())
    assert main(["--quiet", "run", "--resume", str(d)]) == 0
    assert models(d) == trained_run[1]
    assert main(["convert", str(d)]) == 0 and "nothing to convert" in capsys.readouterr().out


def test_convert_refuses_what_is_not_plain_data(pca_run, tmp_path, env, capsys):
    d = copy_run(pca_run[0], tmp_path)
    state = load_state(d / "models" / "pca.safetensors")
    (d / "models" / "pca.safetensors").unlink()
    torch.save({**state, "path": __import__("pathlib").Path("/x")}, d / "models" / "pca.pt")
    capsys.readouterr()
    refused(capsys, main(["convert", str(d), "--trust"]), "pca.pt", "nothing converted")
    assert (d / "models" / "pca.pt").exists()
