"""fwk.engine.callbacks.SafeCheckpointIO: checkpoints written on a thread of their own, in order,
from a snapshot; their errors raised on the training's thread."""
from __future__ import annotations

import threading

import numpy as np
import pytest
import torch

from fwk.engine.callbacks import SafeCheckpointIO, _snapshot
from fwk.safeio import load_state


def _state(w):
    return {"state_dict": {"w": w}, "optimizer_states": [{"state": {0: {"exp_avg": w * 2}}}],
            "callbacks": {"ck": {"best": [1, 2]}}, "np": np.arange(3.0), "epoch": 4}


def test_a_save_writes_what_the_checkpoint_held_when_it_was_asked(tmp_path, monkeypatch):
    """The write happens later, on the checkpoints' thread; the values are those at the call (the
    parameters and containers training changes meanwhile are copied first)."""
    import fwk.engine.callbacks as cb

    gate = threading.Event()
    real = cb.save_state

    def held_back(path, state):
        gate.wait(10)
        return real(path, state)

    monkeypatch.setattr(cb, "save_state", held_back)
    io = SafeCheckpointIO()
    w = torch.arange(6.0)
    ck = _state(w)
    io.save_checkpoint(ck, tmp_path / "epoch000.ckpt")
    assert not (tmp_path / "epoch000.ckpt").exists()  # queued, not written
    w.add_(100.0)  # the optimiser's next step, in place
    ck["callbacks"]["ck"]["best"].append(3)
    ck["np"][0] = -1.0
    gate.set()
    io.wait()
    back = load_state(tmp_path / "epoch000.ckpt")
    assert torch.equal(back["state_dict"]["w"], torch.arange(6.0))
    assert torch.equal(back["optimizer_states"][0]["state"][0]["exp_avg"], torch.arange(6.0) * 2)
    assert back["callbacks"]["ck"]["best"] == [1, 2] and back["np"][0] == 0.0 and back["epoch"] == 4
    io.teardown()


def test_save_remove_and_link_happen_in_the_order_asked(tmp_path):
    """Lightning's order at an epoch's end: the new epoch file, the older one removed, last.ckpt
    linked to the new one; a load waits for all of them."""
    io = SafeCheckpointIO()
    io.save_checkpoint(_state(torch.ones(3)), tmp_path / "epoch000.ckpt")
    io.link(tmp_path / "epoch000.ckpt", tmp_path / "last.ckpt")
    io.save_checkpoint(_state(torch.full((3,), 2.0)), tmp_path / "epoch001.ckpt")
    io.remove_checkpoint(tmp_path / "epoch000.ckpt")
    io.link(tmp_path / "epoch001.ckpt", tmp_path / "last.ckpt")
    back = io.load_checkpoint(tmp_path / "last.ckpt")
    assert torch.equal(back["state_dict"]["w"], torch.full((3,), 2.0))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["epoch001.ckpt", "last.ckpt"]
    assert (tmp_path / "last.ckpt").samefile(tmp_path / "epoch001.ckpt")
    io.teardown()


def test_a_failed_write_is_raised_by_the_next_call_and_stops_the_ones_behind_it(tmp_path, monkeypatch):
    import fwk.engine.callbacks as cb

    def full(path, state):
        raise OSError(28, "No space left on device")

    io = SafeCheckpointIO()
    monkeypatch.setattr(cb, "save_state", full)
    io.save_checkpoint(_state(torch.ones(2)), tmp_path / "epoch000.ckpt")
    with pytest.raises(OSError, match="No space left"):  # raised by the link if the write failed by then
        io.link(tmp_path / "epoch000.ckpt", tmp_path / "last.ckpt")
        io.wait()
    assert not list(tmp_path.iterdir())  # the link behind the failed write was not made
    monkeypatch.setattr(cb, "save_state", full)
    io.save_checkpoint(_state(torch.ones(2)), tmp_path / "epoch001.ckpt")
    with pytest.raises(OSError, match="No space left"):
        io.teardown()


def test_without_background_the_write_is_done_on_return(tmp_path):
    io = SafeCheckpointIO(background=False)
    io.save_checkpoint(_state(torch.ones(2)), tmp_path / "epoch000.ckpt")
    io.link(tmp_path / "epoch000.ckpt", tmp_path / "last.ckpt")
    assert (tmp_path / "last.ckpt").samefile(tmp_path / "epoch000.ckpt")
    io.teardown()


def test_snapshot_copies_tensors_arrays_and_containers():
    t, a = torch.ones(2, requires_grad=True), np.zeros(2)
    obj = {"t": t, "l": [a, (t, "x")], "n": None}
    s = _snapshot(obj)
    assert s == {"t": s["t"], "l": [s["l"][0], (s["l"][1][0], "x")], "n": None}
    assert s["t"] is not t and not s["t"].requires_grad and s["t"].data_ptr() != t.data_ptr()
    assert s["l"][0] is not a and s["l"] is not obj["l"]
