"""The ``meshseq`` command line: a thin layer over the library.

Each command group lives in its own module with a ``register(subparsers)`` function that adds
its sub-commands; a sub-command's handler takes the parsed ``argparse.Namespace`` and returns an
exit status (or None for 0). A ``MeshseqError`` (a user's mistake) is printed as one line,
``meshseq: error: ...``, with exit status 2 and no traceback; ``MeshseqWarning``s are printed as
``meshseq: warning: ...``.
"""

from __future__ import annotations

import argparse
import importlib
import signal
import sys
import warnings

from meshseq import __version__
from meshseq.errors import MeshseqError, MeshseqWarning

#: Modules of meshseq.cli that register sub-commands, in the order --help lists them.
COMMAND_MODULES = ("acap_cmds", "train_cmds", "synth_cmds", "view_cmds", "demo_cmds", "bodies_cmds",
                   "addon_cmds")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="meshseq",
        description="Learn 3D mesh animation sequences and synthesize new ones "
        "(ACAP deformation features + bidirectional LSTM, Qiao et al. AAAI 2019).",
        epilog="DATA, wherever a command takes it: a folder of OBJ/PLY/OFF frames, a .npz with "
        "'vertices' (T,V,3) and 'faces' (F,3), a Dyna-style FILE.h5:SEQUENCE, several mesh files, "
        "a glTF morph animation (ANIM.glb, ANIM.glb:MESH), a USD stage (SHOT.usda, "
        "SHOT.usda:/PRIM/PATH), or an MDD/PC2 point cache with its base mesh (BASE.obj:CACHE.pc2, "
        "or CACHE.pc2 with CACHE.obj beside it).",
    )
    parser.add_argument("--version", action="version", version=f"meshseq {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(f"meshseq.cli.{name}").register(sub)
    return parser


def _show_warning(message, category, filename, lineno, file=None, line=None):
    prefix = "" if issubclass(category, MeshseqWarning) else f"{category.__name__}: "
    print(f"meshseq: warning: {prefix}{message}", file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    """Run the command line with ``argv`` (default: sys.argv[1:]); returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 1
    old_showwarning = warnings.showwarning
    warnings.showwarning = _show_warning
    # SIGTERM unwinds like Ctrl-C, so temporary outputs are removed (atomic writes leave nothing)
    old_term = signal.signal(signal.SIGTERM, _terminate) if _main_thread() else None
    try:
        status = args.func(args)
    except MeshseqError as err:
        print(f"meshseq: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("meshseq: interrupted", file=sys.stderr)
        return 130
    finally:
        warnings.showwarning = old_showwarning
        if old_term is not None:
            signal.signal(signal.SIGTERM, old_term)
    return int(status or 0)


def _terminate(signum, frame):
    raise KeyboardInterrupt


def _main_thread() -> bool:
    import threading

    return threading.current_thread() is threading.main_thread()


def run() -> None:
    """Console-script entry point."""
    sys.exit(main())
