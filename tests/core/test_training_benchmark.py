"""benchmarks/training.py's FLOP count: dense products only, a sparse product left out (torch's
counter takes every operand as dense: spiral++'s CSR up-sampling would count 146 GFLOP a step)."""
import torch

from .scripts import load_benchmark


class _Enc(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.w = torch.nn.Parameter(torch.randn(5, 7))

    def forward(self, x):  # (3, 5) @ (5, 7): 2 * 3 * 5 * 7 = 210 FLOP
        return (x @ self.w,)


class _Dec(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.w = torch.nn.Parameter(torch.randn(7, 2))
        dense = torch.zeros(400, 3)
        dense[torch.arange(400), torch.arange(400) % 3] = 1.0
        self.S = dense.to_sparse_csr()  # (400, 3), 400 non-zeros: counted as dense it would add 2 * 400 * 3 * 2

    def forward(self, z):  # (3, 7) @ (7, 2): 84 FLOP, then the sparse product
        return self.S @ (z @ self.w)


def test_gflop_counts_dense_products_and_leaves_sparse_ones_out():
    training = load_benchmark("training")
    enc, dec, x = _Enc(), _Dec(), torch.randn(3, 5)
    assert dec(enc(x)[0]).shape == (400, 2)
    assert training.gflop(enc, dec, x) * 1e9 == 3 * (210 + 84)
    from torch.utils.flop_counter import FlopCounterMode  # what torch alone counts: the sparse product too

    with torch.no_grad(), FlopCounterMode(display=False) as fc:
        dec(enc(x)[0])
    assert fc.get_total_flops() == 210 + 84 + 2 * 400 * 3 * 2


def test_alternate_times_cpu_seconds_or_wall_seconds():
    """benchmarks/_ict.alternate: wall seconds count a sleep, CPU seconds (``cpu=True``) do not; a
    busy loop counts in both."""
    import time

    ict = load_benchmark("_ict")

    def busy():
        t0 = time.process_time()
        while time.process_time() - t0 < 0.02:
            pass

    fns = {"sleep": lambda: time.sleep(0.05), "busy": busy}
    wall, cpu = ict.alternate(fns, 3), ict.alternate(fns, 3, cpu=True)
    assert wall["sleep"] >= 0.05 and cpu["sleep"] < 0.01
    assert cpu["busy"] >= 0.02 and wall["busy"] >= 0.02


def test_cpu_time_refuses_more_than_one_thread(monkeypatch):
    import sys

    import pytest

    training = load_benchmark("training")
    monkeypatch.setattr(torch, "get_num_threads", lambda: 2)
    monkeypatch.setattr(sys, "argv", ["training.py", "--cpu-time"])
    with pytest.raises(SystemExit, match="--cpu-time needs one thread"):
        training.main()
