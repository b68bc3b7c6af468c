"""The web app from the command line: `mmsclean serve`, `mmsclean user add` and `mmsclean export`
(from its store, as the dashboard's downloads do). The API is reached only through its app
factory, `app.api.main`."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated

import typer

from app.cli.common import console, err_console

user_app = typer.Typer(help="Manage the web app's users.")


@user_app.command("add")
def user_add(
    name: Annotated[str, typer.Argument(help="login name")],
    role: Annotated[str, typer.Option(help="annotator, reviewer or admin")] = "annotator",
) -> None:
    """Create a user; the password is read from stdin (first line), never from the command."""
    from sqlmodel import Session

    from app.core.errors import ConfigError
    from app.store.db import get_engine
    from app.store.models import Role
    from app.store.users import create_user

    if role not in Role.__members__:
        raise ConfigError("--role", f"must be one of {', '.join(Role.__members__)}, got {role!r}")
    if sys.stdin.isatty():
        import getpass

        password = getpass.getpass(f"password for {name}: ")
    else:
        password = sys.stdin.readline().rstrip("\r\n")
    with Session(get_engine()) as session:
        user = create_user(session, name, password, Role(role))
    console.print(f"created user {user.username} ({user.role.value}), id {user.id}")


EXPORTS = (
    "cleaned-laz", "removed-laz", "classified-laz", "cleaned-pcd", "map-pcd",
    "semantickitti-labels", "guardrails", "pillars-csv", "pillars-npz", "qa-report",
)  # fmt: skip


def export(
    survey: Annotated[str, typer.Argument(help="survey id or name in the web app's store")],
    what: Annotated[str, typer.Argument(help=", ".join(EXPORTS))],
    out: Annotated[Path, typer.Option("--out", "-o", help="file to write")],
    mesh_format: Annotated[str, typer.Option("--mesh-format", help="guardrails: glb or obj")] = (
        "glb"
    ),
    include_model: Annotated[
        bool, typer.Option(help="pillars: add the model's pre-labels to the human labels")
    ] = False,
    source: Annotated[
        str,
        typer.Option(
            help="maps: the run of clutter, phantom, the newest of both, or combined (cleaned /"
            " removed LAZ: what either removed)"
        ),
    ] = "newest",
    overwrite: Annotated[bool, typer.Option(help="replace OUT if it exists")] = False,
) -> None:
    """Export from the web app's store (as the dashboard's downloads do): the cleaned, removed or
    classified map of the newest clutter or phantom run (LAZ with the survey's CRS when it has
    one, or PCD), SemanticKITTI labels of the newest clutter run, approved guardrail meshes,
    pillar labels, the QA report. While review is pending (clutter decisions, work areas not
    signed off, guardrail models) it prints the same warning line as the dashboard (on stderr)
    and exports the current state."""
    import os
    import shutil

    from sqlmodel import Session

    from app.core.errors import ConfigError
    from app.core.settings import get_settings
    from app.reports.combined_maps import write_combined_map
    from app.reports.exports import (
        REMOVERS,
        csv_pieces,
        exported,
        pillar_table,
        write_guardrails_zip,
        write_pillars_npz,
    )
    from app.reports.map_exports import map_with_crs, write_classified_laz, write_map_pcd
    from app.reports.qa_report import build_qa_report
    from app.reports.semantickitti_labels import write_semantickitti_zip
    from app.store.db import get_engine
    from app.store.surveys import find_survey
    from app.store.work_areas import export_readiness

    if what not in EXPORTS:
        raise ConfigError("WHAT", f"must be one of {', '.join(EXPORTS)} (got {what!r})")
    if source not in ("newest", *REMOVERS, "combined"):
        raise ConfigError(
            "--source", f"must be newest, {', '.join(REMOVERS)} or combined (got {source!r})"
        )
    if source == "combined" and what not in ("cleaned-laz", "removed-laz"):
        raise ConfigError("--source", "combined is for cleaned-laz and removed-laz only")
    if mesh_format not in ("glb", "obj"):
        raise ConfigError("--mesh-format", f"must be glb or obj (got {mesh_format!r})")
    if out.exists() and not overwrite:
        raise ConfigError("--out", f"{out} exists; pass --overwrite to replace it")
    if not out.parent.is_dir():
        raise ConfigError("--out", f"{out.parent} is not a folder")
    settings = get_settings()
    partial = out.with_name(f".{out.name}.partial")
    staged = out.with_name(f".{out.name}.partial.laz")  # LasAppender compresses by the suffix
    name, details = what.replace("-", "_"), {}
    try:
        with Session(get_engine()) as session:
            record = find_survey(session, survey)
            warning = export_readiness(session, record.id).warning
            if warning:
                err_console.print(f"warning: {warning}", markup=False, soft_wrap=True)
            if what in ("cleaned-laz", "removed-laz") and source == "combined":
                which = what.split("-")[0]
                jobs, points, crs = write_combined_map(session, settings, record, which, staged)
                shutil.move(staged, partial)
                details = {"source": "combined", "job_ids": [j.id for j in jobs],
                           "points": points, "crs": crs}  # fmt: skip
            elif what in ("cleaned-laz", "removed-laz"):
                which = what.split("-")[0]
                path, job, crs = map_with_crs(session, settings, record, which, source, staged)
                shutil.copyfile(path, partial)
                details = {"job_id": job.id, "file": str(path), "crs": crs}
            elif what == "classified-laz":
                job, points, crs = write_classified_laz(session, settings, record, source, staged)
                shutil.move(staged, partial)
                details = {"job_id": job.id, "points": points, "crs": crs}
            elif what in ("cleaned-pcd", "map-pcd"):
                which = ("cleaned",) if what == "cleaned-pcd" else ("cleaned", "removed")
                job, points = write_map_pcd(session, settings, record, source, which, partial)
                details = {"job_id": job.id, "points": points}
            elif what == "semantickitti-labels":
                manifest = write_semantickitti_zip(session, settings, record, partial)
                details = {"job_id": manifest["job_id"], "frames": len(manifest["frames"])}
            elif what == "guardrails":
                count = write_guardrails_zip(session, record, mesh_format, partial)
                name, details = "guardrails_zip", {"format": mesh_format, "models": count}
            elif what == "qa-report":
                page = build_qa_report(session, settings, record, "mmsclean export")
                partial.write_text(page, encoding="utf-8")
                details = {"bytes": len(page)}
            else:
                table = pillar_table(session, record.id, include_model)
                if what == "pillars-csv":
                    with open(partial, "w", encoding="utf-8", newline="") as f:
                        f.writelines(csv_pieces(table))
                else:
                    write_pillars_npz(table, partial)
                details = {"rows": len(table["cell_id"]), "include_model": include_model}
            label = f"survey {record.id} ({record.name})"
            exported(session, None, record, name, via="command line", out=str(out), **details)
            os.replace(partial, out)
    finally:
        partial.unlink(missing_ok=True)
        staged.unlink(missing_ok=True)
    console.print(f"{out}: {what} of {label}")


def serve(
    host: Annotated[str | None, typer.Option(help="bind address (default 127.0.0.1)")] = None,
    port: Annotated[int | None, typer.Option(help="port (default 8000)")] = None,
) -> None:
    """Start the web app (API, dashboard, viewer); /health answers once it is ready."""
    import uvicorn

    from app.api.main import create_app
    from app.core.settings import get_settings

    settings = get_settings()
    host = host or settings.host
    port = settings.port if port is None else port
    console.print(f"mmsclean: open http://{host}:{port}/ and log in (the viewer opens from there)")
    uvicorn.run(create_app(), host=host, port=port, log_level="info")
