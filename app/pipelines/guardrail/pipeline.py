"""The guardrail pipeline, in the paper's order: road removal -> connected components -> 0.5 m
slices -> camera crops -> slice classifier -> adjacency correction -> guardrail points ->
poles, unit shapes, superimposition, pipe / beam reconstruction -> meshes."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from app.core.progress import Progress, Stopwatch, no_progress
from app.core.sensors import SensorKind
from app.io.survey import Survey
from app.pipelines.guardrail.classifier import CropEncoder, load_heads, predict
from app.pipelines.guardrail.config import GuardrailConfig, ReconstructionConfig
from app.pipelines.guardrail.correction import correct_labels
from app.pipelines.guardrail.segmentation import SLICE_STEPS, SliceStage, prepare_slices
from app.pipelines.guardrail.slices import SliceSet
from app.pipelines.tiling import placed

MODELS = Path(__file__).resolve().parents[3] / "models" / "guardrail"
DEFAULT_MODEL = MODELS / "slice_classifier.pt"  # profile scanners (simulated VQ-250 surveys)
ROTATING_MODEL = MODELS / "slice_classifier_rotating.pt"  # rotating scanners (HDL-64E-like)
# the shipped classifier a run picks for each sensor kind (app.pipelines.sensor_models)
SHIPPED: dict[SensorKind, Path] = {
    SensorKind.PROFILE: DEFAULT_MODEL,
    SensorKind.ROTATING: ROTATING_MODEL,
}


@dataclass
class GuardrailInstance:
    """One guardrail: its slices and points (indices into the points it was built from: the
    stage's, or its own slices' where they were read for it alone)."""

    id: str
    slices: np.ndarray
    points: np.ndarray
    model: object | None = None  # ReconstructedGuardrail when reconstructed
    error: str | None = None  # why reconstruction failed, when it did
    files: dict[str, str] | None = None  # its meshes, where a rebuild wrote them ({format: path})


@dataclass
class GuardrailResult:
    stage: SliceStage
    probability: np.ndarray  # (K,) guardrail probability per slice
    raw_labels: np.ndarray  # (K,) bool before correction
    slice_labels: np.ndarray  # (K,) bool after correction
    point_labels: np.ndarray  # (N,) uint8 per point of stage.points: 1 guardrail
    guardrails: list[GuardrailInstance]
    frame_ids: list[str]
    frame_sizes: list[int]
    timings: dict[str, float] = field(default_factory=dict)

    def frame_labels(self) -> dict[str, np.ndarray]:
        """The contract's labels: per frame, one uint8 per raw point, 1 = guardrail."""
        pts = self.stage.points
        sizes = zip(self.frame_ids, self.frame_sizes, strict=True)
        out = {f: np.zeros(n, dtype=np.uint8) for f, n in sizes}
        for i, frame_id in enumerate(self.frame_ids):
            sel = pts.frame == i
            out[frame_id][pts.index[sel]] = self.point_labels[sel]
        return out


class GuardrailPipeline:
    def __init__(self, config: GuardrailConfig | None = None, model_path: Path | None = None):
        self.config = config or GuardrailConfig()
        self.model_path = Path(model_path or DEFAULT_MODEL)
        self.heads, self.card = load_heads(self.model_path)
        # the correction settings left unset are the classifier's own (chosen with it)
        self.config = self.config.with_correction(self.card)
        # the head asked for, else the model's default (the one that holds on real data)
        self.head: str = self.config.head or self.card.get("default_head") or "image+geometry"
        if self.head not in self.heads:
            from app.core.errors import ConfigError

            known = ", ".join(self.heads)
            problem = f"{self.model_path} has no {self.head!r} head ({known})"
            raise ConfigError("head", problem)

    def run(self, survey: Survey, progress: Progress | None = None) -> GuardrailResult:
        cfg = self.config
        report = progress or no_progress
        uses_image = "image" in self.head
        encoder = CropEncoder() if uses_image and survey.cameras else None
        stage = prepare_slices(survey, encoder, cfg.spacing, placed(report, SLICE_STEPS))
        clock = Stopwatch()
        with clock("classify"):
            report("classifier", 0.7)
            probability, raw, corrected = self.label(stage)
        point_labels = slice_point_labels(stage.slices, corrected)
        guardrails = self.instances(stage, corrected)
        if cfg.reconstruct:
            with clock("reconstruction"):
                for i, g in enumerate(guardrails):
                    report("reconstruction", 0.8 + 0.2 * i / max(len(guardrails), 1))
                    self.reconstruct(stage, g)
        timings = {**stage.timings, **clock.rounded()}
        frames = list(survey.frames)
        sizes = np.bincount(stage.points.frame, minlength=len(frames))
        frame_sizes = [
            int(f.point_count) if f.point_count is not None else int(s)
            for f, s in zip(frames, sizes, strict=True)
        ]
        report("done", 1.0)
        return GuardrailResult(
            stage, probability, raw, corrected, point_labels, guardrails,
            [f.frame_id for f in frames], frame_sizes, timings,
        )  # fmt: skip

    def label(
        self, stage: SliceStage, head: str | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(probability, raw, corrected) per slice: `classify`, the threshold, then the
        adjacency correction."""
        cfg = self.config
        probability = self.classify(stage, head)
        raw = probability >= cfg.threshold
        corrected = correct_labels(
            stage.slices, raw, max_gap=cfg.max_gap, max_isolated=cfg.max_isolated,
            keep=confident(probability, cfg.keep_confident),
        ).astype(bool)  # fmt: skip
        return probability, raw, corrected

    def classify(self, stage: SliceStage, head: str | None = None) -> np.ndarray:
        """Guardrail probability per slice: the head named (default: the run's, `self.head`)
        where the slice has a crop (or the head needs none), the geometry head elsewhere."""
        name = head or self.head
        k = len(stage.slices)
        probability = np.zeros(k)
        head_model = self.heads[name]
        needs_image = "image" in name
        with_image = stage.has_crop if needs_image else np.ones(k, dtype=bool)
        if with_image.any():
            probability[with_image] = predict(
                head_model, stage.embedding[with_image], stage.geometry[with_image]
            )[:, 1]
        rest = ~with_image
        if rest.any():
            fallback = self.heads["geometry"]
            probability[rest] = predict(fallback, stage.embedding[rest], stage.geometry[rest])[:, 1]
        return probability

    def instances(self, stage: SliceStage, labels: np.ndarray) -> list[GuardrailInstance]:
        """Guardrails from the slice labels (see `group_guardrails`)."""
        return group_guardrails(stage.slices, stage.road.above_ground, labels, self.config)

    def reconstruct(self, stage: SliceStage, guardrail: GuardrailInstance) -> None:
        reconstruct_instance(
            stage.points.xyz, stage.trajectory, guardrail, self.config.reconstruction
        )


def confident(probability: np.ndarray, keep_confident: float | None) -> np.ndarray | None:
    """Slices the adjacency correction never drops as isolated (None: no such slice)."""
    if keep_confident is None:
        return None
    return np.nan_to_num(np.asarray(probability, dtype=np.float64), nan=0.0) >= keep_confident


def slice_point_labels(s: SliceSet, labels: np.ndarray) -> np.ndarray:
    """(N,) uint8 per point the slices index: its slice's label, 0 outside every slice."""
    out = np.zeros(len(s.point_slice), dtype=np.uint8)
    inside = s.point_slice >= 0
    out[inside] = labels[s.point_slice[inside]]
    return out


def group_guardrails(
    s: SliceSet, above_ground: np.ndarray, labels: np.ndarray, cfg: GuardrailConfig
) -> list[GuardrailInstance]:
    """Guardrails of the slice labels (`guardrail_groups`) with their points.
    `above_ground` is the height above ground of every point `s` indexes."""
    return [
        GuardrailInstance(guardrail_id(i), members, rail_points(s, above_ground, members, cfg))
        for i, members in enumerate(guardrail_groups(s, labels, cfg))
    ]


def guardrail_groups(s: SliceSet, labels: np.ndarray, cfg: GuardrailConfig) -> list[np.ndarray]:
    """Per guardrail, its slices: guardrail slices grouped by (component, side), then groups on
    one side joined when they follow each other along the road (gap <= `join_gap`) at the same
    lateral offset (within `join_lateral`): a rail broken into several components by a
    gap in the scan is still one guardrail. Runs shorter than `min_guardrail_length` are
    not modelled. Slices only: no point is read."""
    keep = np.flatnonzero(labels)
    if len(keep) == 0:
        return []
    keys = np.stack([s.component[keep], s.side[keep]], axis=1)
    groups = [keep[(keys == key).all(axis=1)] for key in np.unique(keys, axis=0)]
    groups = _join_groups(groups, s.station, s.lateral, s.side, cfg.join_gap, cfg.join_lateral)
    min_slices = int(np.ceil(cfg.min_guardrail_length / s.spacing))
    # along the road, then across it: the points in the same order however the slices were
    # numbered (a tiled run's components are numbered per tile), so the seeded reconstruction
    # sees the same input
    return [
        members[np.lexsort((s.lateral[members], s.station_index[members]))]
        for members in sorted(groups, key=lambda m: float(s.station[m].min()))
        if len(members) >= min_slices
    ]


def rail_points(
    s: SliceSet, above_ground: np.ndarray, members: np.ndarray, cfg: GuardrailConfig
) -> np.ndarray:
    """The points of a guardrail's slices (`members`), without those at ground level (the ground
    under the rail)."""
    points = np.concatenate([s.points(int(k)) for k in members])
    return points[above_ground[points] > cfg.ground_clearance]


def reconstruct_instance(
    xyz: np.ndarray, trajectory: np.ndarray, g: GuardrailInstance, config: ReconstructionConfig
) -> None:
    """Fill `g.model` from its points, or `g.error` with why it could not be reconstructed."""
    from app.pipelines.guardrail.reconstruction import reconstruct_guardrail

    try:
        g.model = reconstruct_guardrail(xyz[g.points], trajectory, config)
    except (ValueError, RuntimeError) as exc:  # too few poles, degenerate unit ...
        g.error = str(exc).splitlines()[0] if str(exc) else type(exc).__name__


@dataclass
class ReconstructionInput:
    """What grouping and reconstruction need, without the survey or the classifier: the slices
    compacted to their own points, so that corrected slice labels can be rebuilt into
    guardrails later (the web app saves one per run; see `save` / `load`)."""

    slices: SliceSet  # indices are into `xyz`
    xyz: np.ndarray  # (M, 3) float64 world: the points of all slices
    above_ground: np.ndarray  # (M,) float64
    trajectory: np.ndarray  # (T, 3) sensor positions in drive order
    config: GuardrailConfig

    @classmethod
    def of(
        cls, stage: SliceStage, config: GuardrailConfig, slices: np.ndarray | None = None
    ) -> ReconstructionInput:
        """The stage's slices (`slices`: these only, in this order) with their points."""
        s = stage.slices
        picked = np.arange(len(s)) if slices is None else np.asarray(slices, dtype=np.int64)
        counts = np.diff(s.offsets)[picked]
        offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        # the picked slices' runs of `s.indices`, one after the other
        within = np.arange(offsets[-1]) - np.repeat(offsets[:-1], counts)
        points = s.indices[np.repeat(s.offsets[picked], counts) + within]
        compact = SliceSet(
            spacing=s.spacing,
            point_slice=np.repeat(np.arange(len(picked), dtype=np.int64), counts),
            indices=np.arange(len(points), dtype=np.int64),
            offsets=offsets,
            component=s.component[picked], station_index=s.station_index[picked],
            station=s.station[picked], centre=s.centre[picked], lateral=s.lateral[picked],
            side=s.side[picked], direction=s.direction[picked],
            point_station=s.point_station[points], point_lateral=s.point_lateral[points],
        )  # fmt: skip
        return cls(
            compact,
            stage.points.xyz[points].astype(np.float64),
            stage.road.above_ground[points].astype(np.float64),
            np.asarray(stage.trajectory, dtype=np.float64)[:, :3],
            config,
        )

    def save(self, path: Path) -> Path:
        """One .npz (written atomically: a half-written file never has the final name)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        arrays = {f"slices.{k}": getattr(self.slices, k) for k in _SLICE_ARRAYS}
        tmp = path.with_name(path.name + ".part")
        with tmp.open("wb") as f:
            np.savez(
                f, xyz=self.xyz, above_ground=self.above_ground, trajectory=self.trajectory,
                spacing=np.float64(self.slices.spacing),
                config=np.array(self.config.model_dump_json()), **arrays,
            )  # fmt: skip
        tmp.replace(path)
        return path

    @classmethod
    def save_parts(cls, path: Path, parts: list[Path], components: list[np.ndarray]) -> Path:
        """An index of stage parts (`save`d files beside it, e.g. a tiled run's tiles): every
        part's slices, with `components` (per part, the run's component number of each of its
        slices), while the points stay in the parts (`load` reads them). Small: per slice."""
        path = Path(path)
        arrays: dict[str, list[np.ndarray]] = {k: [] for k in _PER_SLICE}
        counts = []
        for part, numbers in zip(parts, components, strict=True):
            with np.load(part, allow_pickle=False) as z:
                for key in _PER_SLICE:
                    arrays[key].append(numbers if key == "component" else z[f"slices.{key}"])
                counts.append(np.diff(z["slices.offsets"]))
                head = {k: z[k] for k in ("spacing", "config", "trajectory")}
        sizes = np.concatenate(counts) if counts else np.zeros(0, np.int64)
        tmp = path.with_name(path.name + ".part")
        with tmp.open("wb") as f:
            np.savez(
                f, **head, parts=np.array([str(Path(p).relative_to(path.parent)) for p in parts]),
                part_slices=np.array([len(c) for c in counts], dtype=np.int64),
                **{"slices.offsets": np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)},
                **{f"slices.{k}": np.concatenate(v) for k, v in arrays.items()},
            )  # fmt: skip
        tmp.replace(path)
        return path

    @classmethod
    def load(
        cls, path: Path, slices_only: bool = False, points_of: np.ndarray | None = None
    ) -> ReconstructionInput:
        """`slices_only`: the per-slice arrays without the points (cheap: for label previews);
        `points_of` (K,) bool: every slice, with the points of these only (a rebuild needs the
        guardrail slices' points, not the survey's). A step that reads points several times
        opens the stage once (`StoredStage`)."""
        stage = StoredStage.open(path)
        return stage.index if slices_only else stage.with_points(points_of)


@dataclass
class StoredStage:
    """A stored stage (`ReconstructionInput.save` / `save_parts`) opened once: its slices held
    without their points (`index`), the points read for the slices a step asks, from the parts
    that hold them (`with_points`). A rebuild asks once per guardrail and reads the index once:
    its per-slice arrays grow with the survey, not with one guardrail."""

    path: Path
    index: ReconstructionInput  # every slice, no points
    parts: list[str] | None  # the parts' files beside the index (None: one file holds all)
    part_slices: np.ndarray | None  # (P,) slices of each part
    counts: np.ndarray | None  # (K,) points of each slice

    @classmethod
    def open(cls, path: Path) -> StoredStage:
        path = Path(path).resolve()  # a cluster's workers read the parts from its folder
        with np.load(path, allow_pickle=False) as z:
            if "parts" not in z.files:
                return cls(path, _one_file(z, slices_only=True), None, None, None)
            per_slice = {k: z[f"slices.{k}"] for k in _PER_SLICE}
            counts = np.diff(z["slices.offsets"])
            none_i, none_f = np.zeros(0, np.int64), np.zeros(0)
            slices = SliceSet(
                spacing=float(z["spacing"]), point_slice=none_i, indices=none_i,
                offsets=np.zeros(len(counts) + 1, np.int64), **per_slice,
                point_station=none_f, point_lateral=none_f,
            )  # fmt: skip
            config = GuardrailConfig.model_validate_json(str(z["config"]))
            index = ReconstructionInput(slices, np.zeros((0, 3)), none_f, z["trajectory"], config)
            return cls(path, index, [str(p) for p in z["parts"]], z["part_slices"], counts)

    def with_points(self, wanted: np.ndarray | None = None) -> ReconstructionInput:
        """Every slice, with the points of the `wanted` ones ((K,) bool; None: all) read part
        by part; a stage of one file is read whole."""
        if self.parts is None or self.counts is None or self.part_slices is None:
            with np.load(self.path, allow_pickle=False) as z:
                return _one_file(z, slices_only=False)
        k = len(self.counts)
        wanted = np.ones(k, bool) if wanted is None else np.asarray(wanted, dtype=bool)
        if len(wanted) != k:
            raise ValueError(f"{len(wanted)} slices asked of {k}")
        columns: dict[str, list[np.ndarray]] = {c: [] for c in _POINT_COLUMNS}
        starts = np.concatenate([[0], np.cumsum(self.part_slices)])
        for name, a, b in zip(self.parts, starts[:-1], starts[1:], strict=True):
            chosen = wanted[a:b]
            if chosen.any():
                with np.load(self.path.parent / name, allow_pickle=False) as part:
                    keep = chosen[part["slices.point_slice"]]
                    for c in _POINT_COLUMNS:
                        columns[c].append(part[c][keep])
        counts = np.where(wanted, self.counts, 0)
        offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        m = int(offsets[-1])
        points = {c: np.concatenate(v) if v else np.zeros(0) for c, v in columns.items()}
        held = self.index.slices
        slices = replace(
            held, point_slice=np.repeat(np.arange(k, dtype=np.int64), counts),
            indices=np.arange(m, dtype=np.int64), offsets=offsets,
            point_station=points["slices.point_station"],
            point_lateral=points["slices.point_lateral"],
        )  # fmt: skip
        xyz = points["xyz"].reshape(-1, 3)
        return replace(self.index, slices=slices, xyz=xyz, above_ground=points["above_ground"])

    def sampled(self, cap: int) -> tuple[np.ndarray, np.ndarray]:
        """(xyz, slice of each point) of at most `cap` slice points, evenly spread over the
        slices in order (the same ones every time), read part by part: what a view of every
        slice shows without holding every slice's points."""
        if self.parts is None or self.counts is None or self.part_slices is None:
            with np.load(self.path, allow_pickle=False) as z:
                point_slice = z["slices.point_slice"]
                picked = _evenly(np.flatnonzero(point_slice >= 0), cap)
                return z["xyz"][picked], point_slice[picked]
        total = int(self.counts.sum())
        picked = np.linspace(0, total - 1, min(cap, total)).astype(np.int64)
        first_slice = np.concatenate([[0], np.cumsum(self.part_slices)])
        first_point = np.concatenate([[0], np.cumsum(self.counts)])[first_slice]
        xyz, slices = [np.zeros((0, 3))], [np.zeros(0, np.int64)]
        for p, name in enumerate(self.parts):
            at = picked[(picked >= first_point[p]) & (picked < first_point[p + 1])]
            if len(at):
                with np.load(self.path.parent / name, allow_pickle=False) as part:
                    xyz.append(part["xyz"][at - first_point[p]])
                    slices.append(part["slices.point_slice"][at - first_point[p]] + first_slice[p])
        return np.concatenate(xyz), np.concatenate(slices)


def _evenly(indices: np.ndarray, cap: int) -> np.ndarray:
    """At most `cap` of `indices`, evenly spread."""
    if len(indices) <= cap:
        return indices
    return indices[np.linspace(0, len(indices) - 1, cap).astype(np.int64)]


def _one_file(z: Any, slices_only: bool) -> ReconstructionInput:
    """A stage `save`d as one file; `slices_only`: without its points."""
    empty = {"slices.point_slice": np.int64, "slices.indices": np.int64,
             "slices.point_station": np.float64, "slices.point_lateral": np.float64,
             "above_ground": np.float64}  # fmt: skip

    def part(key: str) -> np.ndarray:
        if slices_only and key == "xyz":
            return np.zeros((0, 3))
        if slices_only and key in empty:
            return np.zeros(0, dtype=empty[key])
        return z[key]

    arrays = {k: part(f"slices.{k}") for k in _SLICE_ARRAYS}
    slices = SliceSet(spacing=float(z["spacing"]), **arrays)
    config = GuardrailConfig.model_validate_json(str(z["config"]))
    return ReconstructionInput(slices, part("xyz"), part("above_ground"), z["trajectory"], config)


_SLICE_ARRAYS = (
    "point_slice", "indices", "offsets", "component", "station_index", "station", "centre",
    "lateral", "side", "direction", "point_station", "point_lateral",
)  # fmt: skip
_PER_SLICE = _SLICE_ARRAYS[3:10]  # one value per slice (after the offsets)
_POINT_COLUMNS = ("xyz", "above_ground", "slices.point_station", "slices.point_lateral")


def rebuild_guardrails(
    saved: ReconstructionInput | StoredStage | Path,
    labels: np.ndarray,
    config: GuardrailConfig | None = None,
    progress: Progress | None = None,
    write: Callable[[GuardrailInstance], dict[str, str]] | None = None,
    map_each: Callable[..., Iterator[GuardrailInstance]] | None = None,
) -> list[GuardrailInstance]:
    """Guardrails (grouped, joined and reconstructed as in a run) from given slice labels, e.g.
    the labels a human corrected; `config` defaults to the run's (grouped only, with their
    points, where its `reconstruct` is off).

    `saved` in memory, or a stored one (`save` / `save_parts`, its path or opened): then the
    grouping reads its slices only, and each guardrail's points are read for it alone. With
    `write` (its meshes to disk: `GuardrailInstance.files`), each guardrail is written as soon
    as it is reconstructed and its mesh let go. Stored and written, a run holds one guardrail at
    a time, however long the survey.

    With `map_each` (a tiled run's `map_tiles`: `fn(spec, shared, [items])`, results as they
    finish) and a stage stored in parts by several tiles, the guardrails are rebuilt there side
    by side (a cluster's workers read their points from the parts and write their meshes);
    else one after the other here (a survey of one tile never starts a cluster for this)."""
    if isinstance(saved, (str, Path)):
        saved = StoredStage.open(Path(saved))
    stored = saved if isinstance(saved, StoredStage) else None
    index = saved if stored is None else stored.index
    cfg = config or index.config
    report = progress or (lambda stage, fraction: None)
    labels = np.asarray(labels).astype(bool)
    if len(labels) != len(index.slices):
        raise ValueError(f"{len(labels)} labels for {len(index.slices)} slices")
    groups = guardrail_groups(index.slices, labels, cfg)
    spec = (cfg, write)
    tiled = stored is not None and stored.parts is not None and len(stored.parts) > 1
    if tiled and map_each is not None and len(groups) > 1:
        built = {}
        for g in map_each(rebuild_one, spec, (stored, groups), list(range(len(groups)))):
            built[g.id] = g
            report("reconstruction", len(built) / len(groups))
        guardrails = [built[guardrail_id(i)] for i in range(len(groups))]
    else:
        guardrails = []
        for i in range(len(groups)):
            report("reconstruction", i / max(len(groups), 1))
            guardrails.append(rebuild_one(spec, (stored or index, groups), i))
    report("done", 1.0)
    return guardrails


def guardrail_id(number: int) -> str:
    return f"guardrail_{number:03d}"


def rebuild_one(
    spec: tuple[GuardrailConfig, Callable[[GuardrailInstance], dict[str, str]] | None],
    shared: tuple[ReconstructionInput | StoredStage, list[np.ndarray]],
    number: int,
) -> GuardrailInstance:
    """Guardrail `number` of `rebuild_guardrails`' groups: its points (read for it alone from a
    stored stage), its reconstruction and, with a writer, its meshes written and let go."""
    (cfg, write), (saved, groups) = spec, shared
    members = groups[number]
    held = saved
    if isinstance(saved, StoredStage):
        wanted = np.zeros(len(saved.index.slices), dtype=bool)
        wanted[members] = True
        held = saved.with_points(wanted)
    points = rail_points(held.slices, held.above_ground, members, cfg)
    g = GuardrailInstance(guardrail_id(number), members, points)
    if cfg.reconstruct:
        reconstruct_instance(held.xyz, held.trajectory, g, cfg.reconstruction)
    if write is not None and g.model is not None:
        g.files = write(g)
        g.model = g.model.without_mesh()  # type: ignore[attr-defined]
    return g


def _join_groups(
    groups: list[np.ndarray],
    station: np.ndarray,
    lateral: np.ndarray,
    side: np.ndarray,
    max_gap: float,
    max_lateral: float,
) -> list[np.ndarray]:
    """Merge slice groups that continue each other along the road (loop over groups only)."""
    spans = [(float(station[g].min()), float(station[g].max())) for g in groups]
    lats = [float(np.median(lateral[g])) for g in groups]
    sides = [int(side[g[0]]) for g in groups]
    parent = list(range(len(groups)))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i in range(len(groups)):
        for j in range(i + 1, len(groups)):
            gap = max(spans[i][0], spans[j][0]) - min(spans[i][1], spans[j][1])
            if sides[i] == sides[j] and gap <= max_gap and abs(lats[i] - lats[j]) <= max_lateral:
                parent[root(i)] = root(j)
    merged: dict[int, list[np.ndarray]] = {}
    for i, g in enumerate(groups):
        merged.setdefault(root(i), []).append(g)
    return [np.sort(np.concatenate(parts)) for parts in merged.values()]
