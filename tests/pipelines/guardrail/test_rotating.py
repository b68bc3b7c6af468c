"""Guardrail classifiers per sensor kind (issue 16): the training data's scanner, the shipped
rotating classifier's card, and a run on a rotating survey picking it (synthetic)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from app.core.sensors import SensorKind
from app.io import open_survey
from app.pipelines.guardrail.classifier import (
    EMBEDDING,
    SliceHead,
    read_classifier_card,
    save_heads,
)
from app.pipelines.guardrail.config import GuardrailConfig
from app.pipelines.guardrail.pipeline import (
    DEFAULT_MODEL,
    ROTATING_MODEL,
    SHIPPED,
    GuardrailPipeline,
)
from app.pipelines.guardrail.scan_points import load_scan_points, rotating_layout
from app.pipelines.guardrail.training.dataset import (
    HELD_OUT_SEEDS,
    PROFILE_DATA,
    ROTATING_DATA,
    TRAIN_SEEDS,
    TRAINING_DATA,
    VALIDATION_SEEDS,
    SliceSamples,
    simulated_survey,
    training_data,
)
from app.pipelines.guardrail.training.train import train_guardrail_model
from app.pipelines.sensor_models import card_sensor_kind, choose_model
from tests.pipelines.guardrail.test_correction_choice import validation_parts

SAMPLE = Path(__file__).resolve().parents[3] / "data_samples" / "urban-60m"


@pytest.fixture(scope="module")
def rotating_survey(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """6 m of a rotating-kind training survey: seed 704 is a highway seen by a varied scanner."""
    return simulated_survey(704, 6.0, tmp_path_factory.mktemp("cache"), sensor="rotating")


def test_rotating_training_data_is_a_varied_hdl64_with_camera(rotating_survey: Path) -> None:
    info = json.loads((rotating_survey / "ground_truth" / "simulation.json").read_text())
    assert rotating_survey.name == "sim-highway-6m-hdl64-varied-seed704"
    assert info["scanner"] == "hdl64" and info["config"]["vary_scanner"]
    assert info["config"]["camera"] and info["config"]["scene"] == "highway"
    # the scanner drawn from the seed puts its points on its own lattice, not HDL-64E's
    survey = open_survey(rotating_survey, "sim")
    elevations, columns, _ = rotating_layout(survey)
    params = info["scanner_params"]
    assert len(elevations) == params["beams"]
    assert columns == round(360 / params["azimuth_step_deg"])
    lattice = load_scan_points(survey).lattice
    assert lattice is not None and lattice.kind == "rotating" and lattice.n_cols == columns
    assert lattice.row.max() < params["beams"] and lattice.col.max() < columns


def test_profile_training_data_is_as_before() -> None:
    assert training_data() is PROFILE_DATA and PROFILE_DATA.scanner == "profile"
    assert PROFILE_DATA.name(401, 100.0) == "sim-mixed-100m-profile-seed401"
    assert PROFILE_DATA.samples_name(401, 100.0) == "slices-mixed-100m-seed401.npz"
    seeds = (TRAIN_SEEDS, VALIDATION_SEEDS, HELD_OUT_SEEDS)
    assert seeds == (tuple(range(401, 410)), (410, 411, 412), (501, 502, 503))
    with pytest.raises(ValueError, match="no simulated guardrail training data"):
        training_data("unknown")


def test_rotating_data_is_highway_heavy_and_its_own() -> None:
    presets = [ROTATING_DATA.preset_of(s) for s in ROTATING_DATA.train_seeds]
    highways = presets.count("highway") + presets.count("interchange")
    assert highways >= len(presets) / 2 and {"urban", "mixed", "interchange"} <= set(presets)
    held_out = {ROTATING_DATA.preset_of(s) for s in ROTATING_DATA.held_out_seeds}
    assert {"highway", "interchange"} <= held_out
    assert "highway" in {ROTATING_DATA.preset_of(s) for s in ROTATING_DATA.held_out_seeds}
    profile = {*PROFILE_DATA.train_seeds, *PROFILE_DATA.validation_seeds}
    assert not profile & {*ROTATING_DATA.train_seeds, *ROTATING_DATA.validation_seeds}


@pytest.mark.parametrize("data", TRAINING_DATA.values(), ids=TRAINING_DATA.keys())
def test_held_out_seeds_are_refused_for_training(data, tmp_path: Path) -> None:
    assert not {*data.held_out_seeds} & {*data.train_seeds, *data.validation_seeds}
    with pytest.raises(ValueError, match="held out"):
        train_guardrail_model(tmp_path / "m.pt", [data.held_out_seeds[0]], sensor=data.sensor_kind)


@pytest.mark.parametrize("kind", [SensorKind.PROFILE, SensorKind.ROTATING])
def test_the_shipped_classifiers_say_their_kind(kind: SensorKind) -> None:
    card = read_classifier_card(SHIPPED[kind])
    assert card_sensor_kind(card) == kind
    assert card["default_head"] in {"image+geometry", "image", "geometry"}


def test_run_guardrail_picks_the_classifier_of_the_survey_kind(rotating_survey: Path) -> None:
    survey = open_survey(rotating_survey, "sim")
    choice = choose_model("guardrail", SHIPPED, survey, read_classifier_card)
    assert choice.path == ROTATING_MODEL and choice.model_kind == SensorKind.ROTATING
    assert not choice.off_domain and not choice.forced
    if SAMPLE.is_dir():  # the shipped profile-scanner sample
        profile = choose_model(
            "guardrail", SHIPPED, open_survey(SAMPLE, "sim"), read_classifier_card
        )
        assert profile.path == DEFAULT_MODEL and not profile.off_domain


def test_the_card_records_the_kind_its_scanner_and_default_head(monkeypatch, tmp_path) -> None:
    """`train guardrail --sensor rotating` without the simulations (samples stubbed)."""
    asked = []

    def samples(seeds, length, progress=None, sensor="profile"):
        asked.append((list(seeds), length, sensor))
        rng = np.random.default_rng(len(asked))
        label = (np.arange(40) % 4 == 0).astype(np.int64)
        geometry = rng.normal(0, 1, (40, 3)).astype(np.float32) + label[:, None]
        embedding = rng.normal(0, 1, (40, EMBEDDING)).astype(np.float32)
        crop = np.arange(40) < 30  # ten slices no camera shows
        return SliceSamples(
            embedding, geometry, label, np.zeros(40, np.int64), ["a", "b", "c"], crop
        )

    monkeypatch.setattr("app.pipelines.guardrail.training.train.build_samples", samples)
    validated = []

    def validation(model, seeds, length, sensor):
        validated.append((list(seeds), length, sensor))
        return validation_parts()

    monkeypatch.setattr("app.pipelines.guardrail.training.train.validation_slices", validation)
    card = train_guardrail_model(tmp_path / "r.pt", epochs=1, sensor="rotating")
    data = ROTATING_DATA
    assert asked == [
        (list(data.train_seeds), data.length, "rotating"),
        (list(data.validation_seeds), data.length, "rotating"),
    ]
    assert card["sensor_kind"] == "rotating" and card["held_out_seeds"] == [791, 792, 793]
    assert card["training"]["scanner"] == "hdl64" and card["training"]["vary_scanner"]
    assert card["default_head"] == "geometry" and card["training"]["class_balance"] == 0.0
    # the geometry head learns from every slice, the image heads from those with a crop
    assert (card["training"]["slices"], card["training"]["slices_with_crop"]) == (40, 30)
    scores = card["validation"]["scores"]
    assert scores["geometry"]["support"] == 10 and scores["image"]["support"] == 8
    assert card_sensor_kind(read_classifier_card(tmp_path / "r.pt")) == SensorKind.ROTATING
    # the correction is chosen on the validation surveys, after training, into the card
    assert validated == [(list(data.validation_seeds), data.length, "rotating")]
    assert read_classifier_card(tmp_path / "r.pt")["correction"] == card["correction"]
    assert card["correction"]["validation_slice_f"] == 100.0


def test_a_run_uses_the_model_default_head_unless_told(tmp_path: Path) -> None:
    heads = {name: SliceHead(name, 3) for name in ("image+geometry", "image", "geometry")}
    path = save_heads(tmp_path / "m.pt", heads, {"default_head": "geometry"})
    assert GuardrailPipeline(GuardrailConfig(), path).head == "geometry"
    assert GuardrailPipeline(GuardrailConfig(head="image"), path).head == "image"
    older = save_heads(tmp_path / "old.pt", heads, {})  # cards before default_head counted
    assert GuardrailPipeline(GuardrailConfig(), older).head == "image+geometry"
