"""Which model may run on which survey (app.pipelines.sensor_models)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from app.core.sensors import SensorKind
from app.pipelines.phantom.model import DEFAULT_MODEL, PAPER_MODEL
from app.pipelines.sensor_models import (
    ModelChoice,
    NoModelForSensorError,
    card_sensor_kind,
    choose_shipped,
    require_known_kind,
)


@pytest.mark.parametrize("checkpoint", [DEFAULT_MODEL, PAPER_MODEL])
def test_the_shipped_phantom_models_are_for_profile_scanners(checkpoint: Path) -> None:
    card = json.loads(checkpoint.with_suffix(".card.json").read_text())
    assert card_sensor_kind(card) == SensorKind.PROFILE


def test_a_card_tells_its_kind_by_its_training_data() -> None:
    assert card_sensor_kind({"sensor_kind": "rotating"}) == SensorKind.ROTATING
    real_only = {"simulation": {"seeds": []}, "training_sources": [{"format": "semantickitti"}]}
    assert card_sensor_kind(real_only) == SensorKind.ROTATING
    assert card_sensor_kind({"simulation": {"seeds": [1], "scanner": "hdl64"}}) == "rotating"
    assert card_sensor_kind({}) == SensorKind.UNKNOWN


def test_no_model_for_the_kind_is_one_line(tmp_path: Path) -> None:
    shipped = {SensorKind.PROFILE: DEFAULT_MODEL, SensorKind.ROTATING: tmp_path / "missing.pt"}
    with pytest.raises(NoModelForSensorError, match="no phantom model for rotating scanners"):
        choose_shipped("phantom", shipped, "survey s", SensorKind.ROTATING)
    with pytest.raises(NoModelForSensorError, match="sensor kind is unknown"):
        require_known_kind("s", SensorKind.UNKNOWN)
    picked = choose_shipped("phantom", shipped, "survey s", SensorKind.PROFILE)
    assert picked.path == DEFAULT_MODEL and not picked.off_domain


def test_off_domain_is_reported() -> None:
    choice = ModelChoice(DEFAULT_MODEL, SensorKind.PROFILE, SensorKind.ROTATING, forced=True)
    report = choice.report()
    assert report["off_domain"] and "off-domain" in report["warning"]
    same = ModelChoice(DEFAULT_MODEL, SensorKind.PROFILE, SensorKind.PROFILE, forced=True)
    assert "warning" not in same.report()


def test_a_semantickitti_sequence_gets_the_rotating_model_by_itself(real_data: Path) -> None:
    from app.io import open_survey
    from app.pipelines.phantom.model import ROTATING_MODEL, SHIPPED, read_card
    from app.pipelines.sensor_models import choose_model

    survey = open_survey(real_data / "semantickitti" / "sequences" / "05", "semantickitti")
    choice = choose_model("phantom", SHIPPED, survey, read_card)
    assert choice.path == ROTATING_MODEL and not choice.forced and not choice.off_domain
    assert card_sensor_kind(read_card(ROTATING_MODEL)) == SensorKind.ROTATING
