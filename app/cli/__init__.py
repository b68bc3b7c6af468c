"""The `mmsclean` command line: the Typer app `cli`, one module per command group (`surveys`:
info, simulate; `run`; `train`; `evaluate`; `webapp`: user, export, serve), and `main`.

Every user error (`MmscleanError`) ends in one line on stderr and a non-zero exit code, never a
traceback; anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import sys

import typer

from app.cli import evaluate, run, surveys, train, webapp
from app.core.errors import MmscleanError

cli = typer.Typer(
    name="mmsclean",
    help="Clean mobile-mapping point clouds: clutter and phantom removal, guardrail models.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
# registered in the order `mmsclean --help` lists them
cli.command()(surveys.info)
cli.command()(surveys.simulate)
cli.add_typer(run.run_app, name="run")
cli.add_typer(train.train_app, name="train")
cli.add_typer(webapp.user_app, name="user")
cli.command()(evaluate.evaluate)
cli.command()(webapp.export)
cli.command()(webapp.serve)


def main() -> None:
    try:
        cli(standalone_mode=False)
    except MmscleanError as exc:
        print(f"error: {exc.message}", file=sys.stderr)
        sys.exit(exc.exit_code)
    except typer.Abort:
        sys.exit(130)
    except typer.Exit as exc:
        sys.exit(exc.exit_code)
    except typer.TyperException as exc:  # usage errors (missing argument, bad option)
        show = getattr(exc, "show", None)
        if callable(show):
            show()
        else:
            print(f"error: {exc.format_message()}", file=sys.stderr)
        sys.exit(exc.exit_code or 2)
