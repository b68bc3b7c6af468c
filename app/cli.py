"""The `mmsclean` command line.

Every user error (`MmscleanError`) ends in one line on stderr and a non-zero exit code, never a
traceback; anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.table import Table

from app.core.errors import MmscleanError

cli = typer.Typer(
    name="mmsclean",
    help="Clean mobile-mapping point clouds: clutter and phantom removal, guardrail models.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
console = Console()
err_console = Console(stderr=True)

FormatOption = Annotated[
    str, typer.Option("--format", "-f", help="kitti-raw, semantickitti, las, ply, pcd")
]


@cli.command()
def info(
    source: Annotated[Path, typer.Argument(help="survey folder or point-cloud file")],
    fmt: FormatOption,
    as_json: Annotated[bool, typer.Option("--json", help="print JSON instead of a table")] = False,
    check: Annotated[
        bool, typer.Option("--check", help="read every frame: validate data, world bounds")
    ] = False,
) -> None:
    """Summarise a survey: frames, points, time span, trajectory, cameras, reference labels."""
    from rich.progress import Progress

    from app.io import open_survey
    from app.io.summary import check_frames, summarize, summary_rows

    survey = open_survey(source, fmt)
    summary = summarize(survey)
    if check:
        with Progress(console=err_console, transient=True, disable=as_json) as bar:
            task = bar.add_task("reading frames", total=len(survey))
            summary = check_frames(survey, summary, lambda: bar.advance(task))
    if as_json:
        console.print_json(json.dumps(summary.as_dict()))
        return
    table = Table(show_header=False, box=None)
    table.add_column(no_wrap=True)
    table.add_column(overflow="fold")
    for key, value in summary_rows(summary):
        table.add_row(f"[bold]{key}[/bold]", value)
    console.print(table)


@cli.command()
def serve(
    host: Annotated[str | None, typer.Option(help="bind address (default 127.0.0.1)")] = None,
    port: Annotated[int | None, typer.Option(help="port (default 8000)")] = None,
) -> None:
    """Start the web app (API, dashboard, viewer); /health answers once it is ready."""
    import uvicorn

    from app.api.main import create_app
    from app.core.settings import get_settings

    settings = get_settings()
    uvicorn.run(
        create_app(),
        host=host or settings.host,
        port=settings.port if port is None else port,
        log_level="info",
    )


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


if __name__ == "__main__":
    main()
