"""Training slices from simulated surveys: the simulator knows which points are guardrail, so
each slice gets its reference label (most of its points on a guardrail) for free.

One set of simulated surveys per sensor kind (`TRAINING_DATA`), never mixed: `profile`
(VQ-250-like profile scanner, seeds 401-412) and `rotating` (HDL-64E-class scanners drawn from
the seed, `vary_scanner`: 32 / 64 beams, azimuth steps, mounting heights, noise, dropouts;
seeds 701-720 and 780-782, 30 m each (sized so training fits 30 minutes on 2 cores),
highway-heavy presets (highway, interchange) so beam and pipe guardrails, exit ramps and
median barriers appear as a rotating scanner sees them, a few rings at grazing angles). Each
kind has its own held-out seeds (bench/guardrail.py only).

Surveys and their slice samples are cached under `$MMSCLEAN_DATA_DIR/cache/guardrail-train`:
the crop embeddings are the expensive part and never change for a given survey.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.core.progress import Progress
from app.core.settings import get_settings
from app.io import open_survey
from app.pipelines.guardrail.classifier import CropEncoder
from app.pipelines.guardrail.evaluation.reference import point_reference, slice_truth
from app.pipelines.guardrail.segmentation import prepare_slices


@dataclass
class SliceSamples:
    embedding: np.ndarray  # (N, 1280) float32 (zeros where no camera crop shows the slice)
    geometry: np.ndarray  # (N, G) float32
    label: np.ndarray  # (N,) int64: 1 guardrail, 0 other
    group: np.ndarray  # (N,) int64 survey id
    geometry_names: list[str]
    has_crop: np.ndarray | None = None  # (N,) bool: a camera crop shows it; None: every one

    def subset(self, keep: np.ndarray) -> SliceSamples:
        crop = None if self.has_crop is None else self.has_crop[keep]
        return SliceSamples(
            self.embedding[keep],
            self.geometry[keep],
            self.label[keep],
            self.group[keep],
            self.geometry_names,
            crop,
        )

    def with_crop(self) -> SliceSamples:
        """The slices a camera crop shows: all the image heads can learn from."""
        return self if self.has_crop is None else self.subset(self.has_crop)

    @property
    def crop(self) -> np.ndarray:
        """(N,) bool: a camera crop shows the slice (every one when not recorded)."""
        return np.ones(len(self.label), bool) if self.has_crop is None else self.has_crop

    @staticmethod
    def concatenate(parts: list[SliceSamples]) -> SliceSamples:
        """The samples of several surveys as one set (the names of the first)."""
        return SliceSamples(
            np.concatenate([p.embedding for p in parts]),
            np.concatenate([p.geometry for p in parts]),
            np.concatenate([p.label for p in parts]),
            np.concatenate([p.group for p in parts]),
            parts[0].geometry_names,
            np.concatenate([p.crop for p in parts]),
        )


@dataclass(frozen=True)
class SimulatedData:
    """The simulated surveys a classifier for one sensor kind is trained, validated and
    evaluated on; `presets` cycle with the seed (`seed % len(presets)`)."""

    sensor_kind: str
    scanner: str  # the simulator's scanner
    vary_scanner: bool  # rotating: a scanner drawn from the seed
    presets: tuple[str, ...]
    train_seeds: tuple[int, ...]
    validation_seeds: tuple[int, ...]  # for the card and for choosing settings
    held_out_seeds: tuple[int, ...]  # bench/guardrail.py only: never trained on or tuned with
    length: float  # metres per survey

    def preset_of(self, seed: int) -> str:
        return self.presets[seed % len(self.presets)]

    def name(self, seed: int, length: float) -> str:
        """The cached survey's folder name (the profile kind's as before kinds existed)."""
        scanner = self.scanner + ("-varied" if self.vary_scanner else "")
        return f"sim-{self.preset_of(seed)}-{length:g}m-{scanner}-seed{seed}"

    def samples_name(self, seed: int, length: float) -> str:
        """The cached slice samples' file: every slice, with or without a crop ("slices-";
        the older "samples-" files held only the slices with a crop)."""
        scanner = "" if self.sensor_kind == "profile" else f"-{self.scanner}-varied"
        return f"slices-{self.preset_of(seed)}-{length:g}m{scanner}-seed{seed}.npz"


PROFILE_DATA = SimulatedData(
    "profile", "profile", False, ("urban", "highway", "mixed"),
    tuple(range(401, 410)), (410, 411, 412), (501, 502, 503), 100.0,
)  # fmt: skip
# highway-heavy: half the drives are highways (beam guardrails on both edges and the median)
# or interchanges (an exit ramp whose guardrails turn away, a concrete median barrier that is
# not a guardrail), the rest carry pipe and beam guardrails among urban objects (the negatives
# real streets have)
ROTATING_DATA = SimulatedData(
    "rotating", "hdl64", True, ("highway", "interchange", "mixed", "urban"),
    tuple(range(701, 721)), (780, 781, 782), (791, 792, 793), 30.0,
)  # fmt: skip
TRAINING_DATA: dict[str, SimulatedData] = {"profile": PROFILE_DATA, "rotating": ROTATING_DATA}

# the profile kind's, by their names before kinds existed
PRESETS = PROFILE_DATA.presets
TRAIN_SEEDS = PROFILE_DATA.train_seeds  # 9 surveys
VALIDATION_SEEDS = PROFILE_DATA.validation_seeds
HELD_OUT_SEEDS = PROFILE_DATA.held_out_seeds


def training_data(sensor: str = "profile") -> SimulatedData:
    """The simulated surveys of a sensor kind (`profile` or `rotating`)."""
    if str(sensor) not in TRAINING_DATA:
        raise ValueError(f"no simulated guardrail training data for {sensor!r} scanners")
    return TRAINING_DATA[str(sensor)]


def preset_of(seed: int, sensor: str = "profile") -> str:
    return training_data(sensor).preset_of(seed)


def simulated_survey(
    seed: int, length: float, cache: Path | None = None, sensor: str = "profile"
) -> Path:
    """A cached simulated survey with camera and the kind's scanner (deterministic)."""
    from app.simulate.survey import SimulationConfig, simulate

    data = training_data(sensor)
    cache = cache or get_settings().cache_dir / "guardrail-train"
    folder = cache / data.name(seed, length)
    if not folder.is_dir():
        config = SimulationConfig(
            scene=data.preset_of(seed), length=length, seed=seed, scanner=data.scanner,
            camera=True, write_map=False, vary_scanner=data.vary_scanner,
        )  # fmt: skip
        simulate(config, folder)
    return folder


def survey_samples(
    seed: int,
    length: float,
    encoder: CropEncoder,
    cache: Path | None = None,
    sensor: str = "profile",
) -> SliceSamples:
    """The slices of one simulated survey with embeddings, features and reference labels."""
    cache = cache or get_settings().cache_dir / "guardrail-train"
    target = cache / training_data(sensor).samples_name(seed, length)
    if target.is_file():
        z = np.load(target, allow_pickle=False)
        return SliceSamples(
            z["embedding"], z["geometry"], z["label"], z["group"], [str(n) for n in z["names"]],
            z["has_crop"],
        )  # fmt: skip
    folder = simulated_survey(seed, length, cache, sensor)
    survey = open_survey(folder, "sim")
    stage = prepare_slices(survey, encoder)
    label = slice_truth(stage, point_reference(survey, stage.points, "guardrail"))
    # every slice: the geometry head classifies the slices no camera shows (on a rotating
    # scanner most of them), so it learns from them too; the image heads take `with_crop()`
    samples = SliceSamples(
        stage.embedding.astype(np.float32),
        stage.geometry.astype(np.float32),
        label,
        np.full(len(label), seed, dtype=np.int64),
        stage.geometry_names,
        stage.has_crop.astype(bool),
    )
    partial = target.with_suffix(".partial.npz")
    np.savez_compressed(
        partial,
        embedding=samples.embedding,
        geometry=samples.geometry,
        label=samples.label,
        group=samples.group,
        names=np.array(samples.geometry_names),
        has_crop=samples.has_crop,
    )
    os.replace(partial, target)
    return samples


def build_samples(
    seeds: list[int],
    length: float,
    encoder: CropEncoder | None = None,
    progress: Progress | None = None,
    sensor: str = "profile",
) -> SliceSamples:
    encoder = encoder or CropEncoder()
    parts = []
    for i, seed in enumerate(seeds):
        if progress:
            progress(f"survey {seed}", i / max(len(seeds), 1))
        parts.append(survey_samples(seed, length, encoder, sensor=sensor))
    return SliceSamples.concatenate(parts)
