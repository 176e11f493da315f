"""fwk.native: plugins' C++ kernels built on first use, refused cleanly where they cannot build,
rebuilt when the shared header changes; torch's stale build locks removed."""
import os
import time
from pathlib import Path

import torch

from fwk import native


def test_a_stale_build_lock_is_removed_and_a_fresh_one_kept(tmp_path):
    lock = tmp_path / "lock"
    lock.write_text("")
    native.clear_stale_lock(tmp_path)
    assert lock.exists(), "a build running now keeps its lock"
    old = time.time() - native.STALE_LOCK_SECONDS - 60
    os.utime(lock, (old, old))
    native.clear_stale_lock(tmp_path)
    assert not lock.exists()


def _extension(tmp_path, body="int twice(int a) { return 2 * a; }\n"):
    src = tmp_path / "k.cpp"
    src.write_text('#include "fwk_native.h"\n' + body
                   + "PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) { m.def(\"twice\", &twice); }\n")
    return native.Extension(f"fwk_test_native_{abs(hash(str(tmp_path))) % 10**8}", [src], label="test",
                            env="FWK_TEST_NATIVE")


def test_no_compiler_is_one_line_and_the_torch_code(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("CXX", str(tmp_path / "no-such-compiler"))
    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path / "ext"))
    ext = _extension(tmp_path)
    x = torch.zeros(2)
    assert not ext.usable(x) and not ext.available()
    assert ext.failed
    err = capsys.readouterr().err
    assert err.count("native kernels unavailable") == 1, err
    assert ext.load() is None and capsys.readouterr().err == "", "the reason is printed once"


def test_usable_only_for_float32_cpu_outside_autocast_and_when_enabled(tmp_path, monkeypatch):
    ext = _extension(tmp_path)
    ext._module = object()  # as if built: usable() is about the arguments from here on
    x = torch.zeros(2)
    assert ext.usable(x)
    assert not ext.usable(x.double())
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert not ext.usable(x)
    monkeypatch.setenv("FWK_TEST_NATIVE", "0")
    assert not ext.usable(x) and not ext.available()


def test_the_headers_digest_is_a_build_flag(tmp_path, monkeypatch):
    """torch keys its cache by sources and flags, not included headers: the header's digest is a
    define, so another header gives another build. Checked on the flags, without compiling."""
    import hashlib

    seen = []
    import torch.utils.cpp_extension as ce

    monkeypatch.setattr(ce, "load", lambda **kw: seen.append(kw["extra_cflags"]) or object())
    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path / "ext"))
    header = (native.HEADER_DIR / "fwk_native.h").read_bytes()
    _extension(tmp_path).load()
    assert f"-DFWK_NATIVE_H={hashlib.sha256(header).hexdigest()[:16]}" in seen[0]


def test_processes_that_start_together_take_turns_and_one_says_it_compiles(tmp_path, monkeypatch, capsys):
    """The build lock (flock) lets one build; the next finds the module built and says nothing.
    Two threads with their own Extension objects stand in for two processes (flock locks belong to
    each open file, so they exclude each other within one process too); torch's build is replaced
    by one that takes a second and writes the module."""
    import threading

    import torch.utils.cpp_extension as ce

    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path / "ext"))
    building = []

    def fake_load(name, build_directory, **kw):
        building.append(name)
        assert len(building) == 1 or (Path(build_directory) / f"{name}.so").exists(), "two builds at once"
        time.sleep(1.0)
        (Path(build_directory) / f"{name}.so").write_text("")
        return object()

    monkeypatch.setattr(ce, "load", fake_load)
    exts = [_extension(tmp_path) for _ in range(2)]
    threads = [threading.Thread(target=e.load) for e in exts]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert all(e.failed is None and e._module is not None for e in exts)
    assert capsys.readouterr().err.count("compiling its native kernels") == 1


# ---- differentiable: a custom op's autograd without torch's per-call Python wrapper
@torch.library.custom_op("fwk_test::scaled_square", mutates_args=())
def _scaled_square(x: torch.Tensor, a: torch.Tensor, k: float) -> torch.Tensor:
    return k * a * x * x


@_scaled_square.register_fake
def _(x, a, k):
    return torch.empty_like(x)


def _square_setup(ctx, inputs, output):
    x, a, k = inputs
    ctx.save_for_backward(x, a)
    ctx.k = k


def _square_backward(ctx, g):
    x, a = ctx.saved_tensors
    need_x, need_a = ctx.needs_input_grad[:2]
    return (2 * ctx.k * a * x * g if need_x else None), ((ctx.k * x * x * g).sum(0) if need_a else None), None


_scaled_square.register_autograd(_square_backward, setup_context=_square_setup)
_fast_square = native.differentiable(_scaled_square)


def test_differentiable_gives_the_ops_values_and_gradients():
    torch.manual_seed(0)
    x = torch.randn(5, 3, dtype=torch.float64, requires_grad=True)
    a = torch.randn(3, dtype=torch.float64, requires_grad=True)
    y, y_op = _fast_square(x, a, 0.5), _scaled_square(x, a, 0.5)
    assert torch.equal(y, y_op) and torch.equal(y, 0.5 * a * x * x)
    g = torch.randn_like(y)
    assert all(torch.equal(u, v) for u, v in zip(torch.autograd.grad(y, (x, a), g),
                                                 torch.autograd.grad(y_op, (x, a), g)))
    assert torch.autograd.gradcheck(lambda x, a: _fast_square(x, a, 0.5), (x, a))
    # an input that needs no gradient gets none (the op's backward is asked as the op would ask it)
    (gx,) = torch.autograd.grad(_fast_square(x, a.detach(), 0.5).sum(), (x,))
    assert torch.allclose(gx, a * x)
    assert _fast_square.op is _scaled_square and _fast_square.__name__ == "scaled_square"


def test_differentiable_skips_the_dispatcher_only_when_nothing_intercepts_it():
    from torch._subclasses.fake_tensor import FakeTensorMode
    from torch.utils._python_dispatch import TorchDispatchMode

    class Seen(TorchDispatchMode):
        def __init__(self):
            super().__init__()
            self.ops = []

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            self.ops.append(str(func))
            return func(*args, **(kwargs or {}))

    x, a = torch.randn(4, 2, requires_grad=True), torch.randn(2)
    with Seen() as seen:  # a flop counter, a tracer: the op is called through the dispatcher, and seen
        y = _fast_square(x, a, 2.0)
    assert any("fwk_test.scaled_square" in op for op in seen.ops)
    assert torch.allclose(y, 2 * a * x * x)
    with torch.profiler.profile() as prof:  # a plain call: the op's implementation straight away
        _fast_square(x, a, 2.0).sum().backward()
    assert not any(e.name.startswith("fwk_test::scaled_square") for e in prof.events())
    with FakeTensorMode() as mode:  # fake tensors: the op's fake
        yf = _fast_square(mode.from_tensor(x), mode.from_tensor(a), 2.0)
    assert yf.shape == x.shape


def test_differentiable_refuses_an_op_without_a_gradient():
    @torch.library.custom_op("fwk_test::no_gradient", mutates_args=())
    def no_gradient(x: torch.Tensor) -> torch.Tensor:
        return x.clone()

    try:
        native.differentiable(no_gradient)
    except ValueError as e:
        assert "fwk_test::no_gradient" in str(e) and "register_autograd" in str(e)
    else:
        raise AssertionError("an op without register_autograd was accepted")


def test_differentiable_takes_parameters_as_plain_tensors_and_names_its_backward():
    x, a = torch.nn.Parameter(torch.randn(4, 2)), torch.nn.Parameter(torch.randn(2))
    with torch.profiler.profile() as prof:
        _fast_square(x, a, 2.0).sum().backward()
    names = {e.name for e in prof.events()}
    assert not any(n.startswith("fwk_test::scaled_square") for n in names), "a parameter took the dispatcher"
    assert "fwk_test_scaled_squareBackward" in names
    assert torch.allclose(a.grad, (2 * x * x).sum(0).detach())


def test_differentiable_falls_back_to_the_op_where_torch_keeps_its_parts_elsewhere(monkeypatch):
    class Elsewhere:  # a custom op of a torch without CustomOpDef's private attributes
        def __call__(self, x):
            return 2 * x

    op = Elsewhere()
    assert native.differentiable(op) is op
    monkeypatch.setattr(native, "_dispatch_modes", None)  # no way to see dispatch modes: always the dispatcher
    x = torch.randn(3, 2, requires_grad=True)
    with torch.profiler.profile() as prof:
        y = _fast_square(x, torch.ones(2), 1.0)
    assert any(e.name.startswith("fwk_test::scaled_square") for e in prof.events())
    assert torch.allclose(y, x * x)


def test_reduce_adds_the_threads_accumulators_in_thread_order(tmp_path, torch_threads, monkeypatch):
    """``fwk_native::reduce`` (the header's sum of per-thread accumulators): ((a_0 + a_1) + a_2) ... float for float,
    as torch's sum over dimension 0 adds them, for 1-4 accumulators of sizes around its parallel grain, on 1 and 2
    threads; one accumulator is returned as it is."""
    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path / "ext"))  # a build of its own, left in tmp_path
    src = tmp_path / "r.cpp"
    src.write_text('#include "fwk_native.h"\n'
                   "torch::Tensor reduce(torch::Tensor acc) { return fwk_native::reduce(acc); }\n"
                   'PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) { m.def("reduce", &reduce); }\n')
    ext = native.Extension(f"fwk_test_reduce_{abs(hash(str(tmp_path))) % 10**8}", [src], label="test",
                           env="FWK_TEST_NATIVE")
    mod = ext.load()
    assert mod is not None, ext.failed
    g = torch.Generator().manual_seed(0)
    for threads in (1, 2):
        torch.set_num_threads(threads)
        for nt, shape in ((2, (3089, 128)), (3, (7, 5)), (4, (16385,)), (2, (1,))):
            acc = torch.randn(nt, *shape, generator=g) * torch.logspace(-20, 20, nt)[(...,) + (None,) * len(shape)]
            want = acc[0].clone()
            for t in range(1, nt):
                want = want + acc[t]
            got = mod.reduce(acc)
            assert got.shape == shape and torch.equal(got.view(torch.int32), want.view(torch.int32))
            assert torch.equal(got, acc.sum(0))
    one = torch.randn(1, 4, 3)
    assert torch.equal(mod.reduce(one), one[0])
