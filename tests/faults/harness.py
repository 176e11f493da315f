"""Run ``fwk`` in a subprocess that kills itself with SIGKILL at a chosen point (the fault suite).

    python tests/faults/harness.py POINT N [fwk arguments...]

POINT is where the process dies, on the N-th time it gets there (nothing in fwk knows about
this: the points are installed here by wrapping fwk's and Lightning's own functions):

    cache-hash   a cache entry of the synthetic dataset written, its SHA-256 not yet (data loading)
    train        just after the N-th training checkpoint is saved and on disk (training)
    train-queued just after the N-th training checkpoint is queued, before it is written (fwk writes
                 checkpoints on a thread of their own: SafeCheckpointIO)
    evaluate     at the N-th evaluation of a model on a split (evaluation)
    term         like evaluate, but the signal is SIGTERM (a scheduler's time limit)
    train-term   like train, but the signal is SIGTERM
    report       metrics.json written; report.md's temporary file written, not yet renamed
                 into place (report; a write cut in the middle)
    never        not at all (a plain run, for runs started side by side)
"""
from __future__ import annotations

import os
import signal
import sys
from pathlib import Path


def _die_on(n: int, sig=signal.SIGKILL):
    count = [0]

    def hit() -> None:
        count[0] += 1
        if count[0] >= n:
            sys.stdout.flush()
            sys.stderr.flush()
            os.kill(os.getpid(), sig)

    return hit


def install(point: str, n: int) -> None:
    """Wrap the function at ``point`` so that the process dies there the ``n``-th time."""
    hit = _die_on(n, signal.SIGTERM if point.endswith("term") else signal.SIGKILL)
    if point == "cache-hash":
        import fwk.cache as cache

        write = cache.atomic_write_bytes

        def atomic_write_bytes(path, data):
            if Path(path).suffix == ".sha256" and "synthetic-heads" in str(path):
                hit()
            return write(path, data)

        cache.atomic_write_bytes = atomic_write_bytes
    elif point in ("train", "train-term", "train-queued"):
        from lightning.pytorch import Trainer

        save = Trainer.save_checkpoint

        def save_checkpoint(self, *a, **k):
            out = save(self, *a, **k)
            if point != "train-queued":  # the checkpoint on disk (or the point would be train-queued)
                self.strategy.checkpoint_io.wait()
            hit()
            return out

        Trainer.save_checkpoint = save_checkpoint
    elif point in ("evaluate", "term"):
        import fwk.evaluation as ev

        summary = ev.evaluate_summary

        def evaluate_summary(*a, **k):
            hit()
            return summary(*a, **k)

        ev.evaluate_summary = evaluate_summary
    elif point == "report":
        replace = os.replace

        def replace_(src, dst, **k):
            if Path(dst).name == "report.md":
                hit()
            return replace(src, dst, **k)

        os.replace = replace_
    elif point != "never":
        raise SystemExit(f"harness: unknown point {point!r}")


if __name__ == "__main__":
    install(sys.argv[1], int(sys.argv[2]))
    from fwk.cli import main

    sys.exit(main(sys.argv[3:]))
