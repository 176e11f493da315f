"""Plugins' C++ kernels (and fwk's own, ``fwk.native.ops``: the L1 loss of every training step),
compiled on first use (``torch.utils.cpp_extension``), and the helpers they share (``fwk_native.h``:
the BLAS call, per-thread accumulators summed in thread order, argument checks, and ``tall_mm`` /
``tall_tn``: products (R x K) @ (K x N) with R large and K, N small in row blocks that stay in cache,
one single-threaded BLAS call each, because MKL runs such shapes at 6-25 GFLOP/s on 2 threads and
2-6x slower or faster by orientation alone).

A plugin declares its kernels once, ``KERNELS = Extension("fwk_vcconv_native", [Path(__file__).with_name(
"native.cpp")], label="vcconv", env="FWK_VCCONV_NATIVE")``, and asks ``KERNELS.usable(x, w)`` before
each call: True when the variable is not 0, the module built, and every tensor is a float32 CPU
tensor outside autocast; otherwise the plugin runs its torch code. The module is built with
``-O3 -fopenmp`` against the header folder (``HEADER_DIR``) into a folder per torch version under
torch's extension cache (``TORCH_EXTENSIONS_DIR``): torch keys its cache by the sources and flags,
not by its own version, and not by included headers, so the header's digest is passed as a
define and a changed header rebuilds. A build takes 40-60 s, once per machine and torch version
(a C++ compiler and ninja: ``.ci/run`` and fwk's dependencies bring them). When it fails, the
reason is printed once and kept in ``Extension.failed``. A build lock older than
``STALE_LOCK_SECONDS`` is a build that was killed: torch would wait for it forever, so it is
removed. Processes that start together (a run's models side by side) take turns on a lock of
fwk's own, so one builds and says so, and the others find the module built.

Plugins declare their kernels as ``torch.library.custom_op`` operators (schema, fake, flop formula, gradient)
and call them through ``differentiable(op)``: the same values and gradients, without the Python that torch
wraps around each call of a custom op under autograd (about 40 us a call; a training step of vcconv at the
chapter 5 width makes 31 calls forward and as many backward).
"""
from __future__ import annotations

import contextlib
import hashlib
import os
import sys
import threading
import time
from pathlib import Path

import torch

#: the folder of ``fwk_native.h``, on every extension's include path
HEADER_DIR = Path(__file__).resolve().parent
#: a build lock older than this is a build that was killed (a build takes about 40 s)
STALE_LOCK_SECONDS = 600


def _say(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def clear_stale_lock(build: Path, label: str = "native kernels") -> None:
    """Removes torch's build lock in ``build`` when the build that took it was killed long ago:
    torch's ``FileBaton`` would otherwise wait for it without end."""
    lock = Path(build) / "lock"
    try:
        if time.time() - lock.stat().st_mtime > STALE_LOCK_SECONDS:
            lock.unlink()
            _say(f"{label}: removed a stale build lock {lock} (a build killed earlier)")
    except FileNotFoundError:
        pass


@contextlib.contextmanager
def _build_lock(build: Path):
    """An exclusive lock on ``build`` across processes (``flock``: released by the kernel when its
    holder dies, so never stale), held while a process builds or loads the module there: the
    models a run fits side by side start at once, and without it each said it was compiling while
    one compiled and the other waited on torch's own lock. Where ``fcntl`` is missing, no lock."""
    try:
        import fcntl
    except ImportError:  # not POSIX: torch's own lock still keeps two builds apart
        yield
        return
    with open(Path(build) / "fwk-build.lock", "w") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


class Extension:
    """One plugin's compiled kernels: ``name`` (the module's name, unique), ``sources`` (C++ files),
    ``label`` (how messages name it), ``env`` (the variable that turns it off with 0)."""

    def __init__(self, name: str, sources: list[Path], label: str, env: str):
        self.name, self.sources, self.label, self.env = name, [Path(s) for s in sources], label, env
        self.failed: str | None = None
        self._module = None
        self._lock = threading.Lock()

    def enabled(self) -> bool:
        """Whether the plugin may use the kernels (its variable is not 0)."""
        return os.environ.get(self.env, "1") != "0"

    def build_folder(self) -> Path:
        from torch.utils.cpp_extension import get_default_build_root

        tag = "".join(ch if ch.isalnum() else "_" for ch in torch.__version__)
        return Path(os.environ.get("TORCH_EXTENSIONS_DIR") or get_default_build_root()) / f"{self.name}_{tag}"

    def load(self):
        """The compiled module, or None (the reason in ``failed``, printed once)."""
        if self._module is not None or self.failed is not None:
            return self._module
        with self._lock:
            if self._module is not None or self.failed is not None:
                return self._module
            try:
                from torch.utils.cpp_extension import load

                header = HEADER_DIR / "fwk_native.h"
                digest = hashlib.sha256(header.read_bytes()).hexdigest()[:16]
                build = self.build_folder()
                build.mkdir(parents=True, exist_ok=True)
                clear_stale_lock(build, self.label)
                so = build / f"{self.name}.so"
                newest = max(p.stat().st_mtime for p in [*self.sources, header])
                with _build_lock(build):  # one process builds; the others then find it built and say nothing
                    if not so.exists() or so.stat().st_mtime < newest:
                        _say(f"{self.label}: compiling its native kernels into {build} (once per machine and torch "
                             "version, about a minute)")
                    self._module = load(name=self.name, sources=[str(s) for s in self.sources],
                                        build_directory=str(build), extra_include_paths=[str(HEADER_DIR)],
                                        extra_cflags=["-O3", "-fopenmp", f"-DFWK_NATIVE_H={digest}"],
                                        extra_ldflags=["-fopenmp"], verbose=False)
            except Exception as e:  # no compiler, no ninja, a torch without BLAS symbols: the torch code runs
                last = str(e).strip().splitlines()[-1] if str(e).strip() else ""
                self.failed = f"{type(e).__name__}: {last}"
                _say(f"{self.label}: native kernels unavailable ({self.failed}); {self.label} runs its torch code "
                     "(slower)")
        return self._module

    def available(self) -> bool:
        """True when the kernels are enabled and built (building them on the first call)."""
        return self.enabled() and self.load() is not None

    def usable(self, *tensors) -> bool:
        """The kernels apply: enabled, built, and every tensor a float32 CPU tensor, outside autocast."""
        if torch.is_autocast_enabled("cpu"):
            return False
        if not all(t.device.type == "cpu" and t.dtype == torch.float32 for t in tensors):
            return False
        return self.available()


_PLAIN = (torch.Tensor, torch.nn.Parameter)  # a Parameter overrides neither __torch_function__ nor dispatch
_dispatch_modes = getattr(torch._C, "_len_torch_dispatch_stack", None)  # private: without it, always the dispatcher


def _plain(args) -> bool:
    """Whether a call can skip the dispatcher: no TorchDispatchMode is active (a flop counter, fake
    tensors) and every tensor argument is a plain tensor or a parameter (not
    a subclass that intercepts calls)."""
    if _dispatch_modes is None or _dispatch_modes():
        return False
    return all(type(a) in _PLAIN for a in args if isinstance(a, torch.Tensor))


def differentiable(op):
    """A ``torch.library.custom_op`` (``op``, with ``register_autograd``) as a function with the same
    arguments, the same result and the same gradient, that a training step calls for less: a plain
    ``torch.autograd.Function`` whose forward runs op's own implementation straight away, and op
    itself (through the dispatcher) when something intercepts the dispatcher (``_plain``), so that
    ``torch.utils.flop_counter`` and fake tensors still see ``op`` (tested; fwk does not use
    torch.compile, and it is not tested with it). The Function saves and differentiates with op's
    ``setup_context`` and ``backward``.

    Why: torch's autograd for a custom op is Python built around each call (a generated Function,
    the dispatcher entered twice, the schema's defaults filled in): about 40 us a call more than this
    (measured: 29 against 12 us forward, on a kernel of 2 us, and about 27 us more backward). The
    chapter 5 width's step makes 31 such calls forward and as many backward: 1.05-1.07x the step in
    most of six runs alternating in one process (2 threads, 2026-12-07; docs/methods/autoencoders.md
    "Speed")."""
    try:
        impl, setup, backward = op._init_fn, op._setup_context_fn, op._backward_fn
        namespace, name = op._namespace, op._name
    except AttributeError:  # a torch whose CustomOpDef keeps them elsewhere: the op itself, at its per-call cost
        return op
    if setup is None or backward is None:
        raise ValueError(f"{op._qualname}: register_autograd first")

    def forward(ctx, *args):
        out = impl(*args) if _plain(args) else op(*args)
        setup(ctx, args, out)
        return out

    # named after the op, so that profiles name it and its backward (``<namespace>_<name>Backward``)
    Call = type(f"{namespace}_{name}", (torch.autograd.Function,),
                {"forward": staticmethod(forward), "backward": staticmethod(lambda ctx, *grads: backward(ctx, *grads))})

    def call(*args):
        return Call.apply(*args)

    call.__name__ = name
    call.__doc__ = impl.__doc__
    call.op = op
    return call
