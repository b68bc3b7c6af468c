"""`mmsclean evaluate`: score contract labels (OUT/labels/<frame>.npy) against a survey's
reference labels, whoever wrote them: an mmsclean run, another tool writing the same contract,
or labels edited by hand. Each pipeline is scored with the functions its own reports use, so
a run's report.json and `evaluate` on its labels agree:

- clutter (0 kept, 1 removed): the paper's error matrix and SA / DA / AA, inside the view of
  the survey's first camera (as the pipeline segments it) and on the full map;
- phantom (0 ground, 1 high, 2 short, 3 phantom): per-class precision / recall / F of the points
  in the pillar layer (default pillar settings) against the reference pillar classes, and
  phantom-point detection;
- guardrail (0 other, 1 guardrail): point precision / recall / F against the simulator's
  guardrails or SemanticKITTI's fence class, over every point.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from app.core.errors import InputError
from app.geometry.projection import project
from app.io.survey import Frame, Survey
from app.metrics.classification import binary_scores

PIPELINES = {"clutter": 2, "phantom": 4, "guardrail": 2}  # name -> number of label values


def read_frame_labels(run: Path, survey: Survey, pipeline: str) -> list[np.ndarray]:
    """Per frame of `survey`, its labels from `run/labels/<frame>.npy` (or `run/<frame>.npy`),
    checked: present, one value per raw point, values the pipeline knows."""
    run = Path(run)
    folder = run / "labels" if (run / "labels").is_dir() else run
    if not folder.is_dir():
        raise InputError(run, "is not a folder of labels (expected labels/<frame>.npy inside)")
    values = PIPELINES[pipeline]
    out = []
    for frame in survey.frames:
        path = folder / f"{frame.frame_id}.npy"
        if not path.is_file():
            raise InputError(path, f"is missing: no labels for frame {frame.frame_id}")
        try:
            labels = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise InputError(path, f"is not a readable .npy array ({exc})") from None
        expected = point_count(frame)
        if labels.ndim != 1 or len(labels) != expected:
            raise InputError(
                path, f"holds {labels.shape} labels, frame {frame.frame_id} has {expected} points"
            )
        if not np.issubdtype(labels.dtype, np.integer):
            raise InputError(path, f"holds {labels.dtype} values, expected integer labels")
        if len(labels) and (labels.min() < 0 or labels.max() >= values):
            raise InputError(
                path, f"holds labels outside 0..{values - 1} ({pipeline}: {labels.max()} found)"
            )
        out.append(labels.astype(np.uint8))
    return out


def evaluate_labels(survey: Survey, pipeline: str, labels: list[np.ndarray]) -> dict:
    """The metrics of `labels` (per frame, contract values) on `survey`'s reference labels."""
    if pipeline not in PIPELINES:
        raise InputError(None, f"unknown pipeline {pipeline!r} (one of {', '.join(PIPELINES)})")
    if not survey.reference_label_kinds:
        raise InputError(survey.source, "has no reference labels to evaluate against")
    if pipeline == "clutter":
        return _clutter(survey, labels)
    if pipeline == "phantom":
        return _phantom(survey, labels)
    return _guardrail(survey, labels)


def camera_view(survey: Survey) -> list[np.ndarray]:
    """Per frame, the points that project into the survey's first camera (frames without its
    image: none), as the clutter pipeline's masking sees them."""
    camera = next(iter(survey.cameras.values()), None)
    out: list[np.ndarray] = []
    for frame in survey.frames:
        if camera is None or camera.name not in frame.image_paths:
            out.append(np.zeros(point_count(frame), dtype=bool))
            continue
        xyz = frame.points().xyz
        seen = project(xyz, camera.P, camera.T_cam_sensor, camera.width, camera.height)
        out.append(seen.in_image)
    return out


def point_count(frame: Frame) -> int:
    """The frame's raw points: from its header when the reader knows it, else by reading it."""
    return frame.point_count if frame.point_count is not None else len(frame.points().xyz)


def _clutter(survey: Survey, labels: list[np.ndarray]) -> dict:
    from app.pipelines.clutter.run import reference_metrics

    metrics = reference_metrics(survey, [lab == 1 for lab in labels], camera_view(survey))
    if metrics is None:
        raise InputError(survey.source, "has no semantic reference labels (clutter needs them)")
    return metrics


def _phantom(survey: Survey, labels: list[np.ndarray]) -> dict:
    from app.core.labels import PillarClass
    from app.io.accumulate import accumulate
    from app.metrics.classification import confusion_matrix, scores_from_confusion
    from app.pipelines.phantom.config import PhantomConfig
    from app.pipelines.phantom.evaluation.classification_metrics import (
        PAPER_OVERALL_EXCLUDES,
        phantom_point_scores,
    )
    from app.pipelines.phantom.evaluation.reference import (
        reference_pillar_labels,
        static_and_moving,
    )
    from app.pipelines.phantom.network import CLASS_NAMES
    from app.pipelines.phantom.pillars import build_pillar_map, phantom_ground
    from app.pipelines.phantom.point_labels import point_labels

    amap = accumulate(survey, with_reference=True)
    if "semantic" not in amap.reference:
        raise InputError(survey.source, "has no semantic reference labels (phantom needs them)")
    cfg = PhantomConfig()
    ground = phantom_ground(amap.xyz, cfg)
    pm = build_pillar_map(amap.xyz, ground, cfg)
    semantic, moving = static_and_moving(amap.reference)
    reference = point_labels(pm, reference_pillar_labels(pm, semantic, moving))
    predicted = np.concatenate(labels)
    in_layer = pm.point_pillar >= 0
    confusion = confusion_matrix(reference, predicted, 4, mask=in_layer)
    names = list(CLASS_NAMES)
    return {
        "points": int(len(predicted)),
        "points_in_pillar_layer": int(in_layer.sum()),
        "point": scores_from_confusion(
            confusion, names, macro_exclude=PAPER_OVERALL_EXCLUDES
        ).as_dict(),
        "phantom_points": phantom_point_scores(
            semantic, moving, in_layer, predicted == PillarClass.phantom
        ).as_dict(),
    }


def _guardrail(survey: Survey, labels: list[np.ndarray]) -> dict:
    from app.pipelines.guardrail.evaluation.reference import (
        DESCRIPTIONS,
        guardrail_truth,
        reference_kind,
    )

    kind = reference_kind(survey.reference_label_kinds)
    if kind is None:
        raise InputError(survey.source, "has no guardrail or semantic reference labels")
    truth = [guardrail_truth(kind, f.reference_labels()[kind]) for f in survey.frames]
    reference = DESCRIPTIONS[kind]
    predicted = np.concatenate(labels) == 1
    return {
        "reference": reference,
        "points": int(len(predicted)),
        "point": binary_scores(np.concatenate(truth), predicted).as_dict(),
    }
