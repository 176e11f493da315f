"""Threads that wait sleep instead of spinning: the OpenMP and BLAS wait policy, set on ``import fwk``.

By default a thread of an OpenMP or OpenBLAS pool that runs out of work spins for a while
before it sleeps (libgomp: about 300,000 iterations; OpenBLAS: 2^28 CPU cycles, about 0.1 s).
On a machine where another process also computes, those spinning threads hold cores that the
threads with work (this process's and the other's) need: a vcconv VAE step beside a 2-thread
NumPy matmul loop took 20 times its time alone (issue 25). So fwk sets, before torch or NumPy
load their libraries (they read these variables once, when loaded):

* ``OMP_WAIT_POLICY=PASSIVE``: libgomp (torch's OpenMP, which also runs MKL's threads in the
  torch CPU wheels) and LLVM/Intel OpenMP sleep at once when idle;
* ``OPENBLAS_THREAD_TIMEOUT=4``: OpenBLAS (NumPy's and SciPy's ``scipy-openblas``) spins 2^4
  cycles, its minimum, instead of 2^28 before it sleeps.

``benchmarks/load.py`` measures that each takes effect (the CPU a process burns while its pools
are idle) and what it changes.

The user's environment wins: a variable already set is left as it is, and a user who set
``OMP_WAIT_POLICY`` to anything but ``PASSIVE`` chose how threads wait, so fwk then sets
nothing. A library loaded before fwk (``import torch`` before ``import fwk``) has already
read its settings: ``loaded_before`` names it, and such a program should set the variables
itself (or import fwk first). Every fwk entry point (the ``fwk`` command, ``python -m fwk``,
``python -m fwk.engine.distributed``, ``import fwk``) imports this package first, so there the
settings apply; child processes (DDP ranks, Ray workers) inherit them.

This module imports nothing beyond ``os`` and ``sys``.
"""
from __future__ import annotations

import os
import sys

#: the variables fwk sets where the user has not, and their values
DEFAULTS = {"OMP_WAIT_POLICY": "PASSIVE", "OPENBLAS_THREAD_TIMEOUT": "4"}

#: the libraries' Python modules whose thread pools read the variables when they load
LIBRARIES = ("torch", "numpy", "scipy")

added: dict[str, str] = {}  # what apply() set in this process (absent: the user's own, or not set)
loaded_before: list[str] = []  # the LIBRARIES already imported when apply() first ran


def apply(environ=None, modules=None) -> dict[str, str]:
    """Set the wait-policy variables the user has not set (see the module docstring); returns
    those it set. Idempotent. ``environ`` and ``modules`` default to ``os.environ`` and
    ``sys.modules`` (arguments for tests)."""
    env = os.environ if environ is None else environ
    mods = sys.modules if modules is None else modules
    chosen = (env.get("OMP_WAIT_POLICY") or "").strip()
    if chosen and chosen.upper() != "PASSIVE":
        return {}  # the user chose another policy: theirs for every pool
    skip = {"OPENBLAS_THREAD_TIMEOUT"} if "GOTO_THREAD_TIMEOUT" in env else set()  # OpenBLAS reads either name
    now = {}
    for key, value in DEFAULTS.items():
        if key not in env and key not in skip:
            env[key] = value
            now[key] = value
    if environ is None:
        if not added and now:
            loaded_before[:] = [m for m in LIBRARIES if m in mods]
        added.update(now)
    return now
