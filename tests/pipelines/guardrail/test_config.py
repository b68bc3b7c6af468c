"""The guardrail's settings: one nested config, every field bounded, unknown keys refused, flat
names mapped onto the groups that have them."""

from __future__ import annotations

import math

import pytest
from pydantic import BaseModel, ValidationError

from app.pipelines.guardrail.config import GuardrailConfig, ReconstructionConfig


def test_every_setting_has_a_description_and_the_groups_refuse_unknown_keys() -> None:
    cfg = ReconstructionConfig()
    groups = [getattr(cfg, name) for name in ReconstructionConfig.model_fields]
    groups = [g for g in groups if isinstance(g, BaseModel)]
    assert len(groups) == 8
    for group in groups:
        for name, field in type(group).model_fields.items():
            assert field.description, f"{type(group).__name__}.{name}"
        with pytest.raises(ValidationError, match="Extra inputs"):
            type(group).model_validate({"no_such_setting": 1})
    with pytest.raises(ValidationError, match=r"reconstruction\.poles\.bogus"):
        GuardrailConfig.model_validate({"reconstruction": {"poles": {"bogus": 1}}})


@pytest.mark.parametrize(
    ("values", "field"),
    [
        ({"poles": {"section_step": 1e-6}}, "poles.section_step"),
        ({"poles": {"ransac_iterations": 10**7}}, "poles.ransac_iterations"),
        ({"poles": {"radius_range": (0.2, 0.1)}}, "poles.radius_range"),
        ({"superimpose": {"max_units": 0}}, "superimpose.max_units"),
        ({"pipes": {"strip_width": math.inf}}, "pipes.strip_width"),
        ({"pipes": {"min_nodes": 1}}, "pipes.min_nodes"),
        ({"band": {"cell": 0.0}}, "band.cell"),
        ({"mesh": {"tube_segments": 10**6}}, "mesh.tube_segments"),
        ({"kind": "fence"}, "kind"),
    ],
)
def test_out_of_bounds_values_name_their_field(values: dict, field: str) -> None:
    with pytest.raises(ValidationError) as err:
        ReconstructionConfig.model_validate(values)
    assert ".".join(str(p) for p in err.value.errors()[0]["loc"]).startswith(field)


def test_flat_settings_reach_every_group_that_has_them() -> None:
    cfg = ReconstructionConfig().updated(pole_margin=0.02, max_units=3, kind="pipe")
    assert cfg.kind == "pipe" and cfg.superimpose.max_units == 3
    assert cfg.units.pole_margin == cfg.pipes.pole_margin == 0.02
    assert cfg.beams.pole_margin == cfg.band.pole_margin == 0.02
    assert ReconstructionConfig().updated() == ReconstructionConfig()
    with pytest.raises(TypeError, match="unknown guardrail parameter"):
        ReconstructionConfig().updated(no_such_option=1)
    with pytest.raises(ValidationError, match=r"superimpose\.max_units"):
        ReconstructionConfig().updated(max_units=-1)


def test_a_saved_run_config_without_reconstruction_settings_still_loads() -> None:
    old = GuardrailConfig().model_dump()
    old.pop("reconstruction")
    assert GuardrailConfig.model_validate(old).reconstruction == ReconstructionConfig()
    again = GuardrailConfig.model_validate_json(GuardrailConfig().model_dump_json())
    assert again == GuardrailConfig()
