"""The rows the exports read: approved guardrail models with their approver, and the pillar
labels with their labeller (the writers in `app.reports.exports` turn them into files)."""

from __future__ import annotations

from datetime import datetime

from sqlmodel import Session, col, select

from app.store.models import GuardrailModel, LabelSource, ModelStatus, PillarLabel, User

PillarLabelRow = tuple[int, int, str, float | None, str | None, datetime]


def approved_guardrail_models(
    session: Session, survey_id: int
) -> list[tuple[GuardrailModel, str | None]]:
    """The survey's approved guardrail models by guardrail index, each with the user name of
    whoever approved it (None once that user is deleted)."""
    return list(
        session.exec(
            select(GuardrailModel, User.username)
            .outerjoin(User, col(User.id) == col(GuardrailModel.decided_by))
            .where(
                GuardrailModel.survey_id == survey_id,
                GuardrailModel.status == ModelStatus.approved,
            )
            .order_by(col(GuardrailModel.guardrail_index))
        ).all()
    )


def pillar_label_rows(
    session: Session, survey_id: int, include_model: bool
) -> list[PillarLabelRow]:
    """(cell id, label, source, confidence, user name, updated at) of the survey's pillar labels,
    ordered by cell id then source; human labels only unless `include_model`."""
    query = (
        select(
            PillarLabel.cell_id,
            PillarLabel.label,
            PillarLabel.source,
            PillarLabel.confidence,
            User.username,
            PillarLabel.updated_at,
        )
        .outerjoin(User, col(User.id) == col(PillarLabel.user_id))
        .where(PillarLabel.survey_id == survey_id)
        .order_by(col(PillarLabel.cell_id), col(PillarLabel.source))
    )
    if not include_model:
        query = query.where(PillarLabel.source == LabelSource.human)
    return list(session.exec(query).all())
