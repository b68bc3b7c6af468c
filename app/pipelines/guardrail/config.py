"""Parameters of the guardrail pipeline; defaults are Matsumoto, Mori & Masuda's numbers where the
paper has one (0.5 m slices, 30 mm pipe strips, 10 mm beam strips), else this project's (each
step's module says why).

`GuardrailConfig` is what a run takes (`run:guardrail`'s config); its `reconstruction` holds the
reconstruction's settings, one group per step in the paper's order: the rail's course (`curve`),
poles, unit shapes (`units`), their superimposition, pipes, the beam, the test that tells a beam
from pipes (`band`) and the meshes. Each step's function takes its group (`poles.detect_poles`
takes `PoleConfig`, ...). Every number is bounded (`app.core.bounds`, and tighter bounds where a
value would make a step run out of memory or time) and unknown keys are refused.
"""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal

from pydantic import AfterValidator, BaseModel, ConfigDict, Field

from app.core.bounds import Count, Metres, ObjectMetres, Resolution, Seed, Share

Kind = Literal["auto", "pipe", "beam"]

# metres: a pole or pipe radius
Radius = Annotated[float, Field(gt=0.0, le=1.0, allow_inf_nan=False)]


def _ordered(radii: tuple[float, float]) -> tuple[float, float]:
    if radii[0] >= radii[1]:
        raise ValueError(f"the smallest radius {radii[0]} must be below the largest {radii[1]}")
    return radii


# metres: the (smallest, largest) radius of a pole or pipe
RadiusRange = Annotated[tuple[Radius, Radius], AfterValidator(_ordered)]
# degrees of an angle between two directions
Degrees = Annotated[float, Field(ge=0.0, le=180.0, allow_inf_nan=False)]
# iterations of a fit or a filter (each costs a pass over the step's points)
Iterations = Annotated[int, Field(ge=0, le=10_000)]


class _Group(BaseModel):
    model_config = ConfigDict(extra="forbid")


class CurveConfig(_Group):
    """The rail's course in plan view (`rail_curve.rail_curve`)."""

    cell: Resolution = Field(0.5, description="metres: plan cells the course is traced through")
    smooth: int = Field(
        5, ge=1, le=101, description="cells in the moving average that smooths the course"
    )
    extend: ObjectMetres = Field(2.0, ge=0, description="metres: straight extension at both ends")


class PoleConfig(_Group):
    """Pole detection (`poles.detect_poles`, paper 4.1 after Fukano & Masuda 2015)."""

    section_step: ObjectMetres = Field(
        0.05, ge=0.01, description="metres between horizontal section planes (Fukano: 5-10 cm)"
    )
    cluster_gap: ObjectMetres = Field(
        0.3,
        ge=0,
        description="metres along the rail that separate section clusters (wider than a profile "
        "scanner's line spacing at road speed, so rails stay one cluster)",
    )
    max_pole_width: ObjectMetres = Field(
        0.3, gt=0, description="metres: a wider section cluster is a rail or a beam"
    )
    core_halfwidth: ObjectMetres = Field(
        0.1, gt=0, description="metres: a pole's points lie this close to its station"
    )
    column_tol: ObjectMetres = Field(
        0.08, gt=0, description="metres in plan between vertically aligned clusters"
    )
    min_pole_height: ObjectMetres = Field(
        0.15, ge=0, description="metres: vertical extent of a pole's compact column"
    )
    min_sections: Count = Field(3, ge=1, description="sections a pole's column occupies")
    ground_tol: ObjectMetres = Field(
        0.08, ge=0, description="metres: a pole reaches this close to the local ground"
    )
    below_rails: ObjectMetres = Field(
        0.08, ge=0, description="metres: ... and this far below the lowest rail or beam around it"
    )
    ground_window: ObjectMetres = Field(
        1.0, gt=0, description="metres: along-rail half window of the local ground"
    )
    radius_range: RadiusRange = Field(
        (0.02, 0.12), description="metres: plausible pole radii (smallest, largest)"
    )
    radius_prior: Radius = Field(0.04, description="metres: pole radius when no arc fixes one")
    inlier_tol: ObjectMetres = Field(
        0.01, gt=0, description="metres: RANSAC circle inlier distance"
    )
    min_arc: float = Field(
        math.radians(100.0),
        ge=0.0,
        le=2.0 * math.pi,
        allow_inf_nan=False,
        description="radians of arc a circle fit needs to fix a pole's radius (100 degrees)",
    )
    ransac_iterations: int = Field(
        128, ge=1, le=2048, description="3-point circles tried per RANSAC fit"
    )
    infer_missing: bool = Field(
        True, description="add poles in gaps of whole unit lengths and beyond the ends"
    )
    seed: Seed = Field(0, description="random seed of the RANSAC fits")


class UnitConfig(_Group):
    """Unit shapes between consecutive poles (`units.split_units`, paper 4.1-4.2)."""

    pole_margin: ObjectMetres = Field(
        0.05, ge=0, description="metres beyond each pole's radius: a unit includes both its poles"
    )
    min_points: Count = Field(30, ge=1, description="fewer points make no unit worth stacking")


class SuperimposeConfig(_Group):
    """Stacking the unit shapes: rough alignment, then ICP (`superimpose.superimpose`, paper
    4.2)."""

    reference: Count | None = Field(
        None, ge=0, description="unit the others are stacked onto; None: the one with most points"
    )
    max_units: Count | None = Field(
        None,
        ge=1,
        description="stack only the reference and the units nearest it along the rail (the "
        "paper's experiment on how many are needed); None: all",
    )
    icp_distance: ObjectMetres = Field(
        0.05, gt=0, description="metres: ICP correspondence distance (about a pipe diameter)"
    )
    icp_iterations: int = Field(50, ge=1, le=1000, description="ICP iterations")
    max_shift: ObjectMetres = Field(
        0.1, ge=0, description="metres: a larger ICP move is sliding, not correcting: rejected"
    )
    max_rotation_deg: Degrees = Field(5.0, description="degrees: a larger ICP turn is rejected")
    min_fitness: Share = Field(
        0.3, description="share of a unit's points that must find a partner for ICP to count"
    )
    keep_rough_x: bool = Field(
        True, description="drop ICP's move along the rail (the poles place a unit better)"
    )
    max_height_shift: ObjectMetres = Field(
        0.5, ge=0, description="metres: vertical search of the rough alignment"
    )
    max_depth_shift: ObjectMetres = Field(
        0.3, ge=0, description="metres: search of the rough alignment along the plane normal"
    )


class PipeConfig(_Group):
    """Pipe reconstruction on the stacked unit (`pipes.reconstruct_pipes`, paper 4.3)."""

    pole_margin: ObjectMetres = Field(
        0.03, ge=0, description="metres beyond the pole radius removed with the poles"
    )
    strip_width: ObjectMetres = Field(
        0.03, ge=0.005, description="metres: the paper's 30 mm strips along the unit"
    )
    edge_limit: ObjectMetres = Field(
        0.04, gt=0, description="metres: longest Delaunay edge inside one pipe's points"
    )
    min_component_points: Count = Field(
        2, ge=1, description="points of a strip's component that make a centre"
    )
    link_tol: ObjectMetres = Field(
        0.03, gt=0, description="metres: a centre joins a polyline this close to its course"
    )
    max_slope: float = Field(
        2.0, gt=0, le=100.0, allow_inf_nan=False, description="steepest first step (dy / dx)"
    )
    max_skip: Count = Field(
        4, ge=0, description="empty strips a polyline may bridge (sparse scan lines)"
    )
    min_nodes: Count = Field(4, ge=2, description="shorter polylines (in centres) are noise")
    taubin_iterations: Iterations = Field(10, description="passes of Taubin's low-pass filter")
    straight_tol: ObjectMetres = Field(
        0.02, gt=0, description="metres: a polyline this close to its fitted line is straight"
    )
    snap_deg: float = Field(
        5.0,
        ge=0.0,
        le=90.0,
        allow_inf_nan=False,
        description="degrees: lines this near horizontal become horizontal pipes",
    )
    merge_gap: ObjectMetres = Field(
        0.3, ge=0, description="metres between two pieces of one straight pipe"
    )
    connect_dist: ObjectMetres = Field(
        0.15, ge=0, description="metres: ends extend this far to meet poles, pipes, each other"
    )
    extend_straight: ObjectMetres = Field(
        0.35, ge=0, description="metres: ... the ends of straight lines this far"
    )
    radius_share: Share = Field(
        0.5, gt=0, description="q: the band around a skeleton holding this share is q radii wide"
    )
    dense_points: Count = Field(
        2000, ge=1, description="from this many points on, slanted pipes use the circle fit"
    )
    min_radius_points: Count = Field(
        15, ge=1, description="fewer points take the thinnest measured pipe's radius"
    )
    radius_range: RadiusRange = Field(
        (0.005, 0.08), description="metres: radii a pipe is clipped to (smallest, largest)"
    )
    vertical_min_length: ObjectMetres = Field(
        0.3, ge=0, description="metres: a vertical pipe runs at least this far up"
    )


class BeamConfig(_Group):
    """The beam's section curve on the stacked unit (`beams.beam_section`, paper 4.4)."""

    strip: ObjectMetres = Field(
        0.01, ge=0.002, description="metres: the paper's 10 mm horizontal strips"
    )
    min_strip_points: Count = Field(3, ge=1, description="points a strip needs for a vertex")
    max_gap: ObjectMetres = Field(
        0.05, ge=0, description="metres of empty height bridged inside the section"
    )
    taubin_iterations: Iterations = Field(10, description="passes of Taubin's low-pass filter")
    pole_margin: ObjectMetres = Field(
        0.05, ge=0, description="metres beyond the pole (or spacer) removed with it"
    )


class BandConfig(_Group):
    """Telling a beam from pipes: a beam fills a tall band of points (`beams.looks_like_beam`)."""

    slice_width: ObjectMetres = Field(
        0.02, ge=0.005, description="metres: vertical slices across the unit"
    )
    cell: ObjectMetres = Field(0.02, ge=0.005, description="metres: height cells")
    min_share: Share = Field(
        0.5, description="share of the slices that must hold a height cell for the band"
    )
    max_gap_cells: Count = Field(
        2, ge=0, description="empty cells bridged inside the band (self-shadowed folds)"
    )
    min_band: ObjectMetres = Field(
        0.2, ge=0, description="metres of band that make a beam (W-beam ~0.31, pipe <~0.08)"
    )
    pole_margin: ObjectMetres = Field(
        0.05, ge=0, description="metres beyond the pole (or spacer) left out"
    )


class MeshConfig(_Group):
    """The assembled mesh (`meshes`)."""

    tube_segments: int = Field(12, ge=3, le=256, description="sides of a pipe's tube")
    pole_segments: int = Field(16, ge=3, le=256, description="sides of a pole's cylinder")


class ReconstructionConfig(_Group):
    """The reconstruction of one guardrail (`reconstruction.reconstruct_guardrail`)."""

    kind: Kind = Field(
        "auto", description="pipe, beam, or auto: a beam when the stacked unit fills a band"
    )
    curve: CurveConfig = Field(default_factory=CurveConfig, description="the rail's course")
    poles: PoleConfig = Field(default_factory=PoleConfig, description="pole detection")
    units: UnitConfig = Field(default_factory=UnitConfig, description="unit shapes")
    superimpose: SuperimposeConfig = Field(
        default_factory=SuperimposeConfig, description="stacking the unit shapes"
    )
    pipes: PipeConfig = Field(default_factory=PipeConfig, description="pipe reconstruction")
    beams: BeamConfig = Field(default_factory=BeamConfig, description="the beam's section")
    band: BandConfig = Field(default_factory=BandConfig, description="beam or pipes")
    mesh: MeshConfig = Field(default_factory=MeshConfig, description="the assembled mesh")

    def updated(self, **settings: Any) -> ReconstructionConfig:
        """A copy with flat settings applied (`max_units=4`, `kind="pipe"`): a name sets the
        field of that name here or in every group that has one (`pole_margin`: units, pipes,
        beam and band). An unknown name is a TypeError naming the valid ones; a bad value a
        ValidationError naming the field (`superimpose.max_units`)."""
        if not settings:
            return self
        groups = {
            name: type(getattr(self, name))
            for name in type(self).model_fields
            if isinstance(getattr(self, name), BaseModel)
        }
        valid = set(type(self).model_fields).union(*(g.model_fields for g in groups.values()))
        unknown = sorted(set(settings) - valid)
        if unknown:
            names = ", ".join(sorted(valid))
            raise TypeError(f"unknown guardrail parameter(s) {unknown}; valid: {names}")
        values = self.model_dump()
        for key, value in settings.items():
            if key in type(self).model_fields:
                values[key] = value
            for name, group in groups.items():
                if key in group.model_fields:
                    values[name][key] = value
        return ReconstructionConfig.model_validate(values)


# the paper's adjacency correction as read here (correction.py): a guardrail probability of 0.5
# says yes, runs of up to two other slices inside a guardrail are filled, lone slices dropped
# however confident the classifier was (keep_confident None)
PAPER_CORRECTION: dict[str, float | int | None] = {
    "threshold": 0.5, "max_gap": 2, "max_isolated": 1, "keep_confident": None,
}  # fmt: skip


class GuardrailConfig(BaseModel):
    spacing: Resolution = Field(0.5, description="metres: slice length along the trajectory")
    head: Literal["image+geometry", "image", "geometry"] | None = Field(
        None,
        description="classifier inputs: image (the paper), geometry, or both; "
        "default: the model's (its card's default_head)",
    )
    # the adjacency correction (correction.py); unset: the classifier's own, chosen on its
    # validation surveys (its card's `correction`), else the paper's reading (PAPER_CORRECTION)
    threshold: Share | None = Field(
        None, gt=0, lt=1, description="guardrail probability to say yes; default: the model's"
    )
    max_gap: Count | None = Field(
        None, ge=0, description="slices: other slices filled inside a run; default: the model's"
    )
    max_isolated: Count | None = Field(
        None, ge=0, description="slices: guardrail runs this short go; default: the model's"
    )
    keep_confident: Share | None = Field(
        None,
        gt=0,
        le=1,
        description="guardrail probability at which an isolated slice stays a guardrail "
        "(1: none stays); default: the model's, else none",
    )
    min_guardrail_length: Metres = Field(
        3.0, gt=0, description="metres: shorter guardrail runs are not reconstructed"
    )
    join_gap: Metres = Field(2.0, ge=0, description="metres between runs of one guardrail")
    join_lateral: ObjectMetres = Field(0.75, ge=0, description="metres of lateral offset, ditto")
    ground_clearance: ObjectMetres = Field(
        0.1, ge=0, description="metres: points lower above the ground are not modelled"
    )
    reconstruct: bool = True
    reconstruction: ReconstructionConfig = Field(
        default_factory=ReconstructionConfig,
        description="the reconstruction's settings: rail course, poles, units, superimposition, "
        "pipes, beam, beam-or-pipes test, meshes",
    )

    def with_correction(self, card: dict[str, Any]) -> GuardrailConfig:
        """This config with every unset correction setting taken from the classifier's card
        (`correction`, chosen on its validation surveys), else from PAPER_CORRECTION."""
        chosen = card.get("correction") or {}
        values = {
            key: (getattr(self, key) if getattr(self, key) is not None else chosen.get(key, paper))
            for key, paper in PAPER_CORRECTION.items()
        }
        return type(self).model_validate({**self.model_dump(), **values})
