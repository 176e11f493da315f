"""Resume says from which epoch it continues and leaves one epoch checkpoint; progress as plain
lines (epoch, losses, elapsed, time left), at most one every few seconds, where no bar is drawn."""
from __future__ import annotations

import io
import shutil
from types import SimpleNamespace

import torch

from fwk.engine import ProgressLines, fit
from fwk.engine.callbacks import duration
from fwk.engine.trainer import prune_checkpoints
from fwk.runs import make_test_context
from regression import _data, _module


def _ctx(tmp_path, epochs, **kw):
    return make_test_context(tmp_path, epochs=epochs, batch_size=8, lr=1e-2, lr_decay=0.9, **kw)


def _ckpts(ctx):
    return sorted(p.name for p in (ctx.run_dir / "checkpoints" / "reg").iterdir())


def test_resume_from_an_epoch_file_says_so_and_leaves_one_epoch_checkpoint(tmp_path):
    """last.ckpt cut short (a copy of the run, which holds it as a file of its own, stopped while
    writing it): the run continues from epoch001.ckpt, says so, and ends with last.ckpt and the
    newest epoch file only (the stale one removed), again one file under two names."""
    train, val = _data()
    ctx = _ctx(tmp_path, 2)
    fit(_module(), train, val, ctx, "reg")
    d = ctx.run_dir / "checkpoints" / "reg"
    last = d / "last.ckpt"
    assert last.samefile(d / "epoch001.ckpt") and not last.is_symlink()  # written once (LinkedLastCheckpoint)
    cut = last.read_bytes()[:100]
    last.unlink()
    last.write_bytes(cut)
    ctx.resume = True
    m = fit(_module(), train, val, ctx, "reg", ctx.train.replace(epochs=4))
    assert m.steps == 2 * 4  # epochs 3 and 4
    log = ctx.log_file.read_text()
    assert "reg: resuming from epoch001.ckpt: 2 of 4 epochs done, continuing with epoch 3" in log
    assert _ckpts(ctx) == ["epoch003.ckpt", "last.ckpt"]
    assert last.samefile(d / "epoch003.ckpt")


def test_resume_of_a_finished_or_absent_training_says_so(tmp_path):
    train, val = _data()
    ctx = _ctx(tmp_path, 2)
    fit(_module(), train, val, ctx, "reg")
    d = ctx.run_dir / "checkpoints" / "reg"
    shutil.copy(d / "epoch001.ckpt", d / "epoch000.ckpt")  # left by a kill between save and removal
    ctx.resume = True
    fit(_module(), train, val, ctx, "reg")
    assert "reg: training finished before (2 epochs); loaded from last.ckpt" in ctx.log_file.read_text()
    assert _ckpts(ctx) == ["epoch001.ckpt", "last.ckpt"]
    fresh = _ctx(tmp_path / "fresh", 1)
    fresh.resume = True
    fit(_module(), train, val, fresh, "reg")  # nothing to resume: a fresh start, without a word
    assert "resum" not in (fresh.log_file.read_text() if fresh.log_file.exists() else "")
    broken = _ctx(tmp_path / "broken", 1)
    (broken.run_dir / "checkpoints" / "reg").mkdir(parents=True)
    (broken.run_dir / "checkpoints" / "reg" / "last.ckpt").write_bytes(b"cut")
    broken.resume = True
    fit(_module(), train, val, broken, "reg")
    assert "reg: no readable checkpoint to resume from; training from epoch 1" in broken.log_file.read_text()


def test_prune_keeps_the_newest_epoch_files(tmp_path):
    for name in ("epoch002.ckpt", "epoch010.ckpt", "epoch009.ckpt", "last.ckpt", "other.txt"):
        (tmp_path / name).write_text("x")
    removed = prune_checkpoints(tmp_path, 2)
    assert sorted(p.name for p in removed) == ["epoch002.ckpt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["epoch009.ckpt", "epoch010.ckpt", "last.ckpt", "other.txt"]
    prune_checkpoints(tmp_path, 1)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["epoch010.ckpt", "last.ckpt", "other.txt"]


# ----------------------------------------------------------------------------- progress lines

class Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def _trainer(epoch=0, batches=10, metrics=None, stop=False):
    return SimpleNamespace(current_epoch=epoch, num_training_batches=batches, callback_metrics=metrics or {},
                           should_stop=stop, is_global_zero=True)


def test_progress_lines_against_a_naive_schedule():
    """3 epochs of 10 batches, one batch per second: a line at the start, then at most one
    every 5 s (at the first batch end or epoch end 5 s after the previous line; an epoch's last
    batch leaves it to the epoch's end, which has the losses), and the last epoch's line
    always; the time left is the rate so far times the batches left."""
    clock, out = Clock(), io.StringIO()
    cb = ProgressLines("ae", 3, every_s=5.0, out=out, clock=clock)
    cb.on_train_start(_trainer(), None)
    expected, last = [0.0], 0.0
    for epoch in range(3):
        for b in range(10):
            clock.t += 1.0
            cb.on_train_batch_end(_trainer(epoch), None, None, None, b)
            if b < 9 and clock.t - last >= 5.0:
                expected.append(clock.t)
                last = clock.t
        metrics = {"train_loss": torch.tensor(0.5 / (epoch + 1)), "val_loss": torch.tensor(0.25)}
        cb.on_train_epoch_end(_trainer(epoch, metrics=metrics), None)
        if epoch == 2 or clock.t - last >= 5.0:
            expected.append(clock.t)
            last = clock.t
    lines = out.getvalue().splitlines()
    assert len(lines) == len(expected) == 7, lines
    assert lines[0] == "[ae] training 3 epochs, 10 batches each"
    assert lines[1] == "[ae] epoch 1/3, batch 5/10, 5 s elapsed, about 25 s left"
    assert lines[2] == "[ae] epoch 1/3, train_loss 0.5, val_loss 0.25, 10 s elapsed, about 20 s left"
    assert lines[-1] == "[ae] epoch 3/3, train_loss 0.1667, val_loss 0.25, 30 s elapsed"


def test_progress_lines_are_rate_limited_at_epoch_ends_and_say_early_stopping():
    clock, out = Clock(), io.StringIO()
    cb = ProgressLines("net", 100, every_s=5.0, out=out, clock=clock)
    cb.on_train_start(_trainer(batches=1), None)
    for epoch in range(12):
        clock.t += 1.0
        cb.on_train_epoch_end(_trainer(epoch, batches=1, stop=epoch == 11), None)
    lines = out.getvalue().splitlines()
    assert lines[1] == "[net] epoch 5/100, 5 s elapsed, about 1 min 35 s left"
    assert lines[2] == "[net] epoch 10/100, 10 s elapsed, about 1 min 30 s left"
    assert lines[3] == "[net] epoch 12/100 (stopping early), 12 s elapsed"
    assert len(lines) == 4


def test_durations_read_like_a_person_writes_them():
    assert [duration(s) for s in (0, 42.4, 60, 185, 3600, 7620)] == \
        ["0 s", "42 s", "1 min 00 s", "3 min 05 s", "1 h 00 min", "2 h 07 min"]


def test_fit_prints_progress_lines_where_no_bar_is_drawn(tmp_path, capsys):
    """Not quiet, stderr not a terminal (pytest captures it): plain lines on stdout, the start
    and the last epoch at least."""
    train, val = _data()
    ctx = _ctx(tmp_path, 2)
    ctx.quiet = False
    fit(_module(), train, val, ctx, "reg")
    out = capsys.readouterr().out.splitlines()
    lines = [ln for ln in out if ln.startswith("[reg] ")]
    assert lines[0] == "[reg] training 2 epochs, 4 batches each"
    assert lines[-1].startswith("[reg] epoch 2/2, train_loss ") and ", val_loss " in lines[-1]
    assert lines[-1].endswith(" elapsed")
