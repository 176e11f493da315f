"""The ``fwk`` command: list | show | run | eval | report | sample | apply | rig | pack | register | view.

A user's mistake (an FwkError) prints one line and exits 2; ``--debug`` shows the traceback.
The folders a command writes into (``--runs-dir``, ``$FWK_RUNS_DIR``, ``$FWK_CACHE``) are
checked before it starts (``fwk.paths.check_dir``).
"""
from __future__ import annotations

import argparse
import inspect
import os
import select
import sys
import textwrap

from .apply import add_apply_parser, add_register_parser, run_apply, run_register
from .convert import add_convert_parser, run_convert
from .engine.threads import ENV_THREADS, register
from .errors import FwkError, Terminated
from .evaluation.cli_eval import add_eval_parser, run_eval
from .evaluation.cli_report import add_report_parser, run_report
from .generate import add_sample_parser, run_sample
from . import __version__
from .pack import RIG_KIND, add_pack_parser, add_rig_parser, card_summary, read_card, run_pack, run_rig, show_card, shipped
from .hookspecs import KINDS
from .plugins import get_registry
from .registry import did_you_mean
from .runs import check_cache_dir, execute
from .view import add_view_parser, run_view

#: Subcommands whose logic lives in their own modules: name -> (add its parser, run it).
EXTRA_COMMANDS = {
    "eval": (add_eval_parser, run_eval),
    "report": (add_report_parser, run_report),
    "sample": (add_sample_parser, run_sample),
    "apply": (add_apply_parser, run_apply),
    "rig": (add_rig_parser, run_rig),
    "pack": (add_pack_parser, run_pack),
    "register": (add_register_parser, run_register),
    "view": (add_view_parser, run_view),
    "convert": (add_convert_parser, run_convert),
}


#: Subcommands that compute: their processes register, so that concurrent fwk processes share
#: the cores (fwk.engine.threads) instead of oversubscribing them.
COMPUTING = ("run", "eval", "sample", "apply", "register", "rig", "pack")


def _threads(value: str) -> str:
    if value != "auto" and not (value.isdigit() and int(value) >= 1):
        raise argparse.ArgumentTypeError(f"expected a number of threads >= 1 or auto, got {value!r}")
    return value


def cmd_list(args) -> int:
    """``fwk list [--kind KIND]``: one row per registered component, broken plugins on stderr."""
    reg = get_registry()
    known = [*KINDS, RIG_KIND]
    kinds = [args.kind] if args.kind else known
    if args.kind and args.kind not in known:
        raise FwkError(f"--kind {args.kind}: unknown kind{did_you_mean(args.kind, known)} (kinds: {', '.join(known)})")
    rows = []
    for kind in kinds:
        if kind == RIG_KIND:  # the rig models that ship with fwk (fwk rig; fwk show rig NAME)
            models = shipped()
            rows += [(name, RIG_KIND, "fwk", __version__, card_summary(read_card(folder)))
                     for name, folder in models.items()]
            if not models:
                rows.append(("-", RIG_KIND, "-", "-", "(no rig model ships with this installation)"))
            continue
        entries = [e for e in reg if e.kind == kind]
        rows += [(e.name, e.kind, e.plugin, e.version, e.summary) for e in entries]
        if not entries:
            rows.append(("-", kind, "-", "-", "(no component of this kind is registered)"))
    head = ("name", "kind", "plugin", "version", "summary")
    widths = [max(len(str(r[i])) for r in [head, *rows]) for i in range(4)]
    print("  ".join(h.ljust(w) for h, w in zip(head[:4], widths)) + "  " + head[4])
    for r in rows:
        print("  ".join(str(c).ljust(w) for c, w in zip(r[:4], widths)) + "  " + r[4])
    for b in reg.broken:
        print(f"broken plugin {b.plugin}: {b.error}", file=sys.stderr)
    return 0


def describe(kind: str, name: str) -> str:
    """What ``fwk show KIND NAME`` prints: summary, constructor parameters, the module's docs."""
    reg = get_registry()
    entry = reg.entry(kind, name)
    cls = entry.component
    lines = [f"{kind} {name}  (plugin {entry.plugin} {entry.version})".rstrip(), ""]
    doc = inspect.getdoc(cls) or ""
    lines += [doc, ""] if doc else []
    sig = inspect.signature(cls.__init__)  # justified: the constructor is the recipe schema (fwk.hookspecs)
    lines.append("parameters:")
    any_p = False
    supplied = tuple(getattr(cls, "build_args", ()))  # given by the model that builds it, not a recipe key
    for pname, p in sig.parameters.items():
        if pname == "self" or pname in supplied or p.kind in (p.VAR_POSITIONAL, p.VAR_KEYWORD):
            continue
        any_p = True
        ann = "" if p.annotation is p.empty else (p.annotation if isinstance(p.annotation, str) else inspect.formatannotation(p.annotation))
        default = "(required)" if p.default is p.empty else f"= {p.default!r}"
        lines.append(f"  {pname}: {ann} {default}".replace(":  ", ": "))
    if not any_p:
        lines.append("  (none)")
    if supplied:
        lines.append(f"supplied by the model that builds it (not recipe keys): {', '.join(supplied)}")
    module = sys.modules.get(cls.__module__)
    mdoc = inspect.getdoc(module) if module else None
    if mdoc:
        lines += ["", "method:", textwrap.indent(mdoc, "  ")]
    return "\n".join(lines)


def cmd_show(args) -> int:
    """``fwk show KIND NAME``."""
    if args.kind == RIG_KIND:  # a shipped rig model (or a folder written by fwk pack): its card
        print(show_card(args.name))
        return 0
    if args.kind not in KINDS:
        raise FwkError(f"unknown kind {args.kind!r}{did_you_mean(args.kind, KINDS)} (kinds: {', '.join(KINDS)})")
    print(describe(args.kind, args.name))
    return 0


def _seeds(value: str) -> str:
    """The recipe value of ``--seeds 3`` (3: seeds 0, 1, 2), ``--seeds 0,4,7`` ([0, 4, 7]: those
    seeds) or ``--seeds 5,`` ([5]); the recipe checks the seeds (``fwk.recipes.parse_seeds``)."""
    listed = "," in value
    parts = [p.strip() for p in value.split(",") if p.strip() or not listed]
    if not parts or not all(p.isdigit() for p in parts) or (not listed and int(parts[0]) < 1):
        raise argparse.ArgumentTypeError(f"expected a number of seeds >= 1 or a list like 0,1,2, got {value!r}")
    return f"[{', '.join(str(int(p)) for p in parts)}]" if listed else str(int(parts[0]))


def cmd_run(args) -> int:
    """``fwk run RECIPE [key=value ...] [--resume RUN_DIR] [--seeds N|S,S,...]``: prints the run
    directory."""
    if not args.recipe and not args.resume:
        raise FwkError("fwk run: give a recipe file, or --resume RUN_DIR")
    recipe = args.recipe
    overrides = list(args.overrides or [])
    if args.seeds is not None:  # the recipe's `seeds:` (fwk.seeds); recipe.yaml records it
        if args.resume:
            raise FwkError("--seeds: a resumed run keeps the seeds it started with (its recipe.yaml)")
        overrides.append(f"seeds={args.seeds}")
    if recipe and "=" in recipe and not os.path.exists(recipe):
        raise FwkError(f"fwk run: the first argument must be a recipe file, got {recipe!r}")
    run_dir = execute(recipe, overrides, runs_dir=args.runs_dir, resume=args.resume, quiet=args.quiet,
                      device=args.device)
    print(run_dir)
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The ``fwk`` argument parser with every subcommand."""
    p = argparse.ArgumentParser(prog="fwk", description="Deep 3D morphable models of registered face meshes.")
    p.add_argument("--debug", action="store_true", help="show tracebacks of errors")
    p.add_argument("--quiet", action="store_true", help="no progress bars or messages")
    p.add_argument("--threads", type=_threads, metavar="N",
                   help=f"threads per process (sets ${ENV_THREADS}); default: the cores shared among the "
                        "live fwk processes, or $OMP_NUM_THREADS where set")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    sp = sub.add_parser("list", help="list registered components")
    sp.add_argument("--kind", help=f"one of: {', '.join([*KINDS, RIG_KIND])} ({RIG_KIND}: the rig models fwk ships)")
    sp.set_defaults(func=cmd_list)
    sp = sub.add_parser("show", help="describe a component (KIND NAME) or a rig model (rig NAME)")
    sp.add_argument("kind")
    sp.add_argument("name")
    sp.set_defaults(func=cmd_show)
    sp = sub.add_parser("run", help="run a recipe: fwk run RECIPE [key=value ...] [--resume RUN_DIR]")
    sp.add_argument("recipe", nargs="?")
    sp.add_argument("overrides", nargs="*", metavar="key=value")
    sp.add_argument("--resume", metavar="RUN_DIR", help="continue a killed run to the same final result")
    sp.add_argument("--runs-dir", help="where run directories go (default ./runs or $FWK_RUNS_DIR)")
    sp.add_argument("--device", choices=["cpu", "cuda"], help="default: cuda when available")
    sp.add_argument("--seeds", type=_seeds, metavar="N|S,S,...",
                    help="train every model once per seed on one split: N seeds 0..N-1, or a list "
                         "(the recipe's seeds:; docs/recipes.md)")
    sp.set_defaults(func=cmd_run)
    for add, run in EXTRA_COMMANDS.values():
        add(sub).set_defaults(func=run)
    return p


def _reader_gone() -> bool:
    """Whether stdout is a pipe whose reader has gone away (``fwk list | head``; POSIX poll); if
    so, stdout is pointed at /dev/null, so that the flush at exit does not fail again."""
    try:
        fd = sys.stdout.fileno()
        poll = select.poll()
        poll.register(fd, select.POLLOUT)
        if not any(event & select.POLLERR for _, event in poll.poll(0)):
            return False
        os.dup2(os.open(os.devnull, os.O_WRONLY), fd)
        return True
    except (OSError, ValueError):  # stdout is no file descriptor (captured, embedded)
        return False


def main(argv=None) -> int:
    """Run ``fwk`` with ``argv`` (default: the command line); returns the exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in argv
    if "--quiet" in argv and argv.index("--quiet") > 0:  # accept --quiet anywhere
        argv.remove("--quiet")
        argv.insert(0, "--quiet")
    if debug:
        argv.remove("--debug")
        argv.insert(0, "--debug")
    for i, a in enumerate(argv):  # accept --threads N / --threads=N anywhere
        if a == "--threads" and i > 0 and i + 1 < len(argv):
            argv[:0] = [argv.pop(i), argv.pop(i)]
            break
        if a.startswith("--threads=") and i > 0:
            argv.insert(0, argv.pop(i))
            break
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.quiet:
        os.environ["FWK_QUIET"] = "1"
    if args.threads:
        os.environ[ENV_THREADS] = args.threads
    if args.command in COMPUTING:
        register()  # counted by other fwk processes until this one exits
    try:
        if args.command in COMPUTING and args.command != "run":  # `fwk run` checks its folders itself
            check_cache_dir()
        status = int(args.func(args) or 0)
        sys.stdout.flush()  # a reader that went away shows here, not at exit
        return status
    except BrokenPipeError:
        if not _reader_gone():  # another pipe broke: a bug, shown as such
            raise
        return 1  # `fwk list | head`: the reader has what it wanted
    except FwkError as exc:
        if debug:
            raise
        print(f"fwk: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("fwk: interrupted", file=sys.stderr)
        return 130
    except Terminated:
        print("fwk: terminated (SIGTERM)", file=sys.stderr)
        return 143


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
