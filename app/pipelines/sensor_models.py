"""Which model may run on which survey: every learned model is trained for one sensor kind
(`app.core.sensors`), and a run on a survey of another kind is off-domain (a profile-scanner
phantom model scored point F about 1.5 on real HDL-64E maps). A run picks the model of the
survey's kind by itself; with none it stops with one line that says how to get one; a model
forced on it by hand runs, and its report says off-domain. Never a silent off-domain run.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from app.core.errors import MmscleanError
from app.core.sensors import KNOWN_KINDS, SensorKind, kind_of_scanner
from app.io.sensor_kind import detect_sensor_kind
from app.io.survey import Survey


class NoModelForSensorError(MmscleanError):
    """No model of the survey's sensor kind, or the survey's kind is not known."""

    exit_code = 2
    http_status = 409


def card_sensor_kind(card: Mapping[str, Any]) -> SensorKind:
    """The sensor kind a model was trained for: its card's `sensor_kind`, else told by its
    training data (the simulator's scanner; SemanticKITTI sequences are HDL-64E)."""
    if card.get("sensor_kind") in {k.value for k in KNOWN_KINDS}:
        return SensorKind(card["sensor_kind"])
    simulation = card.get("simulation") or {}
    if simulation.get("seeds"):
        return kind_of_scanner(simulation.get("scanner"))
    formats = {s.get("format") for s in card.get("training_sources", []) if isinstance(s, dict)}
    if formats and formats <= {"semantickitti", "kitti-raw"}:
        return SensorKind.ROTATING
    return SensorKind.UNKNOWN


@dataclass(frozen=True)
class ModelChoice:
    """The checkpoint a run uses and why."""

    path: Path
    model_kind: SensorKind  # what the model was trained for
    survey_kind: SensorKind  # what the survey was recorded with
    forced: bool  # named by hand (--model, a job's model_id), not picked by kind

    @property
    def off_domain(self) -> bool:
        return self.model_kind != self.survey_kind

    def report(self) -> dict[str, Any]:
        """The run report's entry: the kinds, and a warning when off-domain."""
        entry: dict[str, Any] = {
            "sensor_kind": self.model_kind.value,
            "survey_sensor_kind": self.survey_kind.value,
            "chosen": "by hand" if self.forced else "by the survey's sensor kind",
            "off_domain": self.off_domain,
        }
        if self.off_domain:
            survey = (
                "a survey of unknown sensor kind"
                if self.survey_kind is SensorKind.UNKNOWN
                else f"a {self.survey_kind.value}-scanner survey"
            )
            entry["warning"] = (
                f"off-domain: a model for {self.model_kind.value} scanners ran on {survey}; "
                "its labels are not to be trusted"
            )
        return entry


def how_to_get_one(pipeline: str, kind: SensorKind) -> str:
    train = {
        "phantom": "label pillars in the viewer and retrain (train:phantom)",
        "guardrail": "review guardrail slices in the viewer and retrain (train:guardrail)",
    }.get(pipeline, "train one")
    return f"{train}, or force a model by hand (--model / model_id; the report flags it off-domain)"


def require_known_kind(survey_name: str, kind: SensorKind, reason: str = "") -> None:
    """A run needs the survey's kind to pick its model."""
    if kind is SensorKind.UNKNOWN:
        why = f" ({reason})" if reason else ""
        raise NoModelForSensorError(
            f"survey {survey_name}: its sensor kind is unknown{why}; declare it: "
            "--sensor rotating|profile, or the survey's sensor field in the app"
        )


def choose_shipped(
    pipeline: str, shipped: Mapping[SensorKind, Path], what: str, kind: SensorKind
) -> ModelChoice:
    """The shipped model for KIND (a known kind: `require_known_kind` first); one-line error
    when there is none. `what` names what the model is for, e.g. "survey s05"."""
    path = shipped.get(kind)
    if path is None or not Path(path).is_file():
        raise NoModelForSensorError(
            f"no {pipeline} model for {kind.value} scanners ({what}): "
            + how_to_get_one(pipeline, kind)
        )
    return ModelChoice(Path(path), kind, kind, forced=False)


def forced_choice(path: Path, card: Mapping[str, Any], survey_kind: SensorKind) -> ModelChoice:
    """A model named by hand: it runs whatever its kind; the report says when off-domain."""
    return ModelChoice(Path(path), card_sensor_kind(card), survey_kind, forced=True)


def choose_model(
    pipeline: str,
    shipped: Mapping[SensorKind, Path],
    survey: Survey,
    card_of: Callable[[Path], Mapping[str, Any]],
    model_path: Path | None = None,
    sensor: SensorKind | None = None,
) -> ModelChoice:
    """A command-line run's model: `model_path` forced by hand, else the shipped model of the
    survey's kind (`sensor` as declared, else told by the survey's reader or point times)."""
    if sensor is None or sensor is SensorKind.UNKNOWN:
        detection = detect_sensor_kind(survey)
        sensor, reason = detection.kind, detection.reason
    else:
        reason = "declared"
    if model_path is not None:
        return forced_choice(model_path, card_of(Path(model_path)), sensor)
    require_known_kind(survey.name, sensor, reason)
    return choose_shipped(pipeline, shipped, f"survey {survey.name}", sensor)
