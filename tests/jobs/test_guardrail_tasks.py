"""`run:guardrail` and `guardrail:rebuild` on a short simulated street with a pipe and a beam
guardrail (synthetic), called directly with a hand-built JobContext."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh
from sqlmodel import select

from app.core.errors import ConfigError, ConflictError, NotFoundError
from app.jobs.guardrail_tasks import (
    STAGE_FILE,
    rebuild_guardrail_models,
    run_guardrail,
)
from app.jobs.registry import check_config, task_for
from app.store.guardrail_review import (
    SliceLabelEdit,
    decide_model,
    list_models,
    put_slice_labels,
)
from app.store.models import (
    AuditEvent,
    GuardrailSlice,
    ModelStatus,
    ModelVersion,
)
from tests.jobs.guardrail_street import Jobs  # its fixtures come through tests/jobs/conftest.py


def test_run_ingests_slices_and_models(jobs: Jobs) -> None:
    result = jobs.run()
    counts = result["counts"]
    with jobs.session() as session:
        rows = session.exec(
            select(GuardrailSlice).where(GuardrailSlice.survey_id == jobs.survey_id)
        ).all()
        models = list_models(session, jobs.survey_id)
        ingest = session.exec(
            select(AuditEvent).where(AuditEvent.action == "guardrail.ingest")
        ).one()
    assert len(rows) == counts["slices"] > 100
    predicted = np.array([r.predicted_label for r in rows])
    corrected = np.array([r.corrected_label for r in rows])
    probability = np.array([r.probability for r in rows])
    assert ((probability >= 0) & (probability <= 1)).all()
    assert (predicted == (probability >= 0.5)).all()  # raw label = thresholded classifier
    assert (np.array([r.label for r in rows]) == corrected).all()  # nobody labelled yet
    assert corrected.sum() == counts["guardrail_slices"]
    assert (predicted != corrected).any()  # the adjacency correction changed something
    # the street's pipe and beam guardrails, each with its three meshes
    assert sorted(m.kind.value for m in models) == ["beam", "pipe"]
    for m in models:
        assert m.status == ModelStatus.pending and m.unit_count >= 1
        assert m.mesh_path.endswith(".glb") and Path(m.mesh_path).is_file()
        assert set(m.params["files"]) == {"glb", "obj", "ply"}
        assert len(trimesh.load(m.params["files"]["ply"], force="mesh").faces) > 0
        assert len(m.params["slices"]) >= 6 and len(m.params["poles"]) >= 2
    for path in result["files"].values():
        assert Path(path).is_file(), path
    assert Path(ingest.payload["stage"]).name == STAGE_FILE
    assert ingest.payload["job_id"] is not None and ingest.user_id == jobs.reviewer.id
    fractions = [f for _, f, _ in jobs.progress]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0


def test_human_labels_survive_a_rerun(jobs: Jobs) -> None:
    jobs.run()
    with jobs.session() as session:
        rows = session.exec(
            select(GuardrailSlice)
            .where(GuardrailSlice.survey_id == jobs.survey_id)
            .order_by(GuardrailSlice.id)
        ).all()
        picked = rows[::40]
        human = {(r.component_id, r.slice_index): 1 - r.label for r in picked}
        edits = [SliceLabelEdit(r.id, r.version, 1 - r.label) for r in picked]
        put_slice_labels(session, jobs.survey_id, edits, jobs.annotator)
    result = jobs.run()
    assert result["counts"]["human_labels_kept"] == len(human)
    with jobs.session() as session:
        after = session.exec(
            select(GuardrailSlice).where(GuardrailSlice.survey_id == jobs.survey_id)
        ).all()
    assert len(after) == len(rows)  # the same survey gives the same slices
    # new ids: a client still holding an old id and version gets 404, never another slice
    assert min(r.id for r in after) > max(r.id for r in rows)
    with jobs.session() as session, pytest.raises(NotFoundError):
        put_slice_labels(
            session, jobs.survey_id, [SliceLabelEdit(rows[1].id, 1, 1)], jobs.annotator
        )
    for r in after:
        key = (r.component_id, r.slice_index)
        if key in human:
            assert (r.label, r.labelled_by) == (human[key], jobs.annotator.id)
        else:
            assert (r.label, r.labelled_by) == (r.corrected_label, None)


def test_rebuild_after_correcting_slices_changes_the_models(jobs: Jobs) -> None:
    jobs.run()
    with jobs.session() as session:
        pipe, beam = sorted(list_models(session, jobs.survey_id), key=lambda m: m.kind.value)[::-1]
        decide_model(
            session, jobs.survey_id, beam.id, beam.version, ModelStatus.approved, jobs.reviewer
        )
        decide_model(
            session, jobs.survey_id, pipe.id, pipe.version, ModelStatus.approved, jobs.reviewer
        )
        # a person says the last two metres of the pipe guardrail are something else
        keys = {tuple(k) for k in pipe.params["slices"]}
        tail = sorted(keys, key=lambda k: k[1])[-4:]
        rows = [
            session.exec(
                select(GuardrailSlice).where(
                    GuardrailSlice.survey_id == jobs.survey_id,
                    GuardrailSlice.component_id == c,
                    GuardrailSlice.slice_index == i,
                )
            ).one()
            for c, i in tail
        ]
        put_slice_labels(
            session,
            jobs.survey_id,
            [SliceLabelEdit(r.id, r.version, 0) for r in rows],
            jobs.annotator,
        )
    result = jobs.rebuild()
    assert result["counts"]["kept"] == 1 and result["counts"]["new"] == 1
    with jobs.session() as session:
        models = {m.kind.value: m for m in list_models(session, jobs.survey_id)}
    # the beam's slices did not change: the approved model stays as it was
    assert models["beam"].id == beam.id and models["beam"].status == ModelStatus.approved
    # the pipe guardrail was rebuilt without the relabelled slices, pending review again
    new_pipe = models["pipe"]
    assert new_pipe.status == ModelStatus.pending
    new_keys = {tuple(k) for k in new_pipe.params["slices"]}
    assert new_keys == keys - set(tail)
    assert new_pipe.params["station_m"][1] < pipe.params["station_m"][1] - 1.5
    assert Path(new_pipe.mesh_path).is_file() and new_pipe.mesh_path != pipe.mesh_path
    assert Path(result["report"]).is_file()


def test_rebuild_with_unchanged_labels_reproduces_the_run(jobs: Jobs) -> None:
    jobs.run()
    with jobs.session() as session:
        before = {m.kind.value: m for m in list_models(session, jobs.survey_id)}
    jobs.rebuild()
    with jobs.session() as session:
        after = {m.kind.value: m for m in list_models(session, jobs.survey_id)}
    assert set(after) == set(before)
    for kind, m in after.items():  # pending ones are replaced by identical reconstructions
        assert m.mesh_path != before[kind].mesh_path  # written by the rebuild job
        assert m.id > max(b.id for b in before.values())  # ids are never handed out twice
        assert m.params["poles"] == before[kind].params["poles"]
        assert m.params["slices"] == before[kind].params["slices"]


def test_bad_config_names_the_field(jobs: Jobs, tmp_path: Path) -> None:
    outside = tmp_path / "elsewhere.pt"
    outside.write_bytes(b"x")
    cases = {
        "config.threshold": {"threshold": 2},
        "config.colour": {"colour": "red"},
        "config.model_path": {"model_path": str(outside)},
        "config.model_id": {"model_id": 12345},
        "config.reconstruction.poles.section_step": {
            "reconstruction": {"poles": {"section_step": 0}}
        },
        "config.reconstruction.pipes.bogus": {"reconstruction": {"pipes": {"bogus": 1}}},
    }
    for field, config in cases.items():
        with pytest.raises(ConfigError) as err:
            run_guardrail(jobs.context("run:guardrail"), config)
        assert err.value.field == field
    with pytest.raises(ConfigError) as err:  # refused when queued, too
        check_config("run:guardrail", {"spacing": 0}, jobs.settings)
    assert err.value.field == "config.spacing"
    with pytest.raises(ConflictError, match="no guardrail run"):
        rebuild_guardrail_models(jobs.context("guardrail:rebuild"), {})
    with pytest.raises(ConfigError) as err:
        rebuild_guardrail_models(jobs.context("guardrail:rebuild"), {"threshold": 0.7})
    assert err.value.field == "config.threshold"


def test_retraining_on_reviewed_slices_registers_a_scored_version(jobs: Jobs) -> None:
    jobs.run()
    with jobs.session() as session:  # a reviewer confirmed every slice
        slices = session.exec(select(GuardrailSlice)).all()
        for s in slices:
            s.labelled_by = jobs.annotator.id
            session.add(s)
        session.commit()
    context = jobs.context("train:guardrail")
    result = task_for("train:guardrail")(context, {"epochs": 3, "block_size": 5.0})
    assert Path(result["files"]["checkpoint"]).is_file()
    with jobs.session() as session:
        versions = session.exec(select(ModelVersion).order_by(ModelVersion.id)).all()
    shipped, new = versions
    assert shipped.name == "shipped:slice_classifier.pt" and new.job_id == context.job_id
    assert new.metrics["validation_slices"] > 0
    not_worse = (new.metrics["validation"]["f1"], new.metrics["validation"]["accuracy"]) >= (
        new.metrics["baseline"]["f1"],
        new.metrics["baseline"]["accuracy"],
    )
    assert new.is_promoted == not_worse == result["promoted"]
    assert new.trained_on["reviewed_slices"] == len(slices)
    with pytest.raises(ConfigError, match="config.epochs"):
        check_config("train:guardrail", {"epochs": 0}, jobs.settings)
