"""What the store owns on disk: the ids of its jobs (each owns `jobs_dir/<id>`) and every file
path a row names (any column called `*_path`: survey sources, job folders and logs, model
checkpoints, clutter masks, guardrail meshes). Start-up clean-up deletes only what none of these
reaches (`app.api.orphans`)."""

from __future__ import annotations

import sqlalchemy as sa
from sqlmodel import Session, SQLModel

from app.store.models import Job


def job_ids(session: Session) -> set[int]:
    return {int(i) for i in session.connection().execute(sa.select(Job.id)).scalars()}


def referenced_paths(session: Session) -> set[str]:
    """Every non-empty value of every `*_path` column of the store's tables."""
    existing = set(sa.inspect(session.connection()).get_table_names())
    paths: set[str] = set()
    for table in SQLModel.metadata.sorted_tables:
        if table.name not in existing:
            continue
        for column in table.columns:
            if column.name.endswith("_path"):
                query = sa.select(column).where(column.is_not(None)).distinct()
                rows = session.connection().execute(query).scalars()
                paths.update(str(v) for v in rows if v)
    return paths
