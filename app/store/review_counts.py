"""Counts of the review state of one survey (labels per user and class, clutter decisions,
guardrail verdicts), as the QA report shows them."""

from __future__ import annotations

from sqlmodel import Session, col, func, select

from app.store.models import (
    ClutterDecision,
    ClutterInstance,
    Decision,
    GuardrailModel,
    ModelStatus,
    PillarLabel,
    User,
)


def pillar_label_counts(session: Session, survey_id: int) -> list[tuple[str | None, str, int, int]]:
    """(user name, source, label, count) over the survey's pillar labels; the user name is None
    for model labels and for labels of deleted users."""
    return list(
        session.exec(
            select(User.username, PillarLabel.source, PillarLabel.label, func.count())
            .select_from(PillarLabel)
            .outerjoin(User, col(User.id) == col(PillarLabel.user_id))
            .where(PillarLabel.survey_id == survey_id)
            .group_by(User.username, PillarLabel.source, PillarLabel.label)
        ).all()
    )


def clutter_instance_count(session: Session, survey_id: int) -> int:
    """How many clutter instances the survey's runs proposed."""
    return int(
        session.exec(
            select(func.count())
            .select_from(ClutterInstance)
            .where(ClutterInstance.survey_id == survey_id)
        ).one()
    )


def clutter_decision_counts(session: Session, survey_id: int) -> dict[Decision, int]:
    """How many of the survey's clutter instances were approved / rejected."""
    return dict(
        session.exec(
            select(ClutterDecision.decision, func.count())
            .join(ClutterInstance, col(ClutterInstance.id) == col(ClutterDecision.instance_id))
            .where(ClutterInstance.survey_id == survey_id)
            .group_by(ClutterDecision.decision)
        ).all()
    )


def guardrail_status_counts(session: Session, survey_id: int) -> dict[ModelStatus, int]:
    """How many of the survey's guardrail models are approved / rejected / pending."""
    return dict(
        session.exec(
            select(GuardrailModel.status, func.count())
            .where(GuardrailModel.survey_id == survey_id)
            .group_by(GuardrailModel.status)
        ).all()
    )
