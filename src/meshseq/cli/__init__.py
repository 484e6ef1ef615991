"""The ``meshseq`` command line: a thin layer over the library.

Each command group lives in its own module and registers on ``app``. A ``MeshseqError`` (a user's
mistake) is printed as one line, ``meshseq: error: ...``, with exit status 2 and no traceback;
``MeshseqWarning``s are printed as ``meshseq: warning: ...``.
"""

from __future__ import annotations

import sys
import warnings

import typer

from meshseq.errors import MeshseqError, MeshseqWarning

app = typer.Typer(
    name="meshseq",
    help="Learn 3D mesh animation sequences and synthesize new ones (ACAP features + BD-LSTM).",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def _show_warning(message, category, filename, lineno, file=None, line=None):
    if issubclass(category, MeshseqWarning):
        print(f"meshseq: warning: {message}", file=sys.stderr)
    else:
        print(f"meshseq: warning: {category.__name__}: {message}", file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    """Entry point of the console script; returns the exit status."""
    from meshseq.cli import acap_cmds, train_cmds, view_cmds  # noqa: F401  (register commands)

    warnings.showwarning = _show_warning
    try:
        app(args=argv, standalone_mode=False)
    except MeshseqError as err:
        print(f"meshseq: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("meshseq: interrupted", file=sys.stderr)
        return 130
    except typer.Exit as ex:
        return ex.exit_code
    except Exception as err:  # click usage errors
        import click

        if isinstance(err, click.exceptions.ClickException):
            err.show()
            return err.exit_code
        if isinstance(err, click.exceptions.Abort):
            return 1
        raise
    return 0


def run() -> None:
    sys.exit(main())
