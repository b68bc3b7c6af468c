"""Training slices from simulated surveys: the simulator knows which points are guardrail, so
each slice gets its reference label (most of its points on a guardrail) for free.

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
    embedding: np.ndarray  # (N, 1280) float32
    geometry: np.ndarray  # (N, G) float32
    label: np.ndarray  # (N,) int64: 1 guardrail, 0 other
    group: np.ndarray  # (N,) int64 survey id
    geometry_names: list[str]

    def subset(self, keep: np.ndarray) -> SliceSamples:
        return SliceSamples(
            self.embedding[keep],
            self.geometry[keep],
            self.label[keep],
            self.group[keep],
            self.geometry_names,
        )


PRESETS = ("urban", "highway", "mixed")  # seeds cycle through them
TRAIN_SEEDS = tuple(range(401, 410))  # 9 surveys
VALIDATION_SEEDS = (410, 411, 412)  # for the card and for choosing settings
HELD_OUT_SEEDS = (501, 502, 503)  # bench/guardrail.py only: never trained on or tuned with


def preset_of(seed: int) -> str:
    return PRESETS[seed % len(PRESETS)]


def simulated_survey(seed: int, length: float, cache: Path | None = None) -> Path:
    """A cached simulated survey with camera and profile scanner (deterministic)."""
    from app.simulate.survey import SimulationConfig, simulate

    cache = cache or get_settings().cache_dir / "guardrail-train"
    folder = cache / f"sim-{preset_of(seed)}-{length:g}m-profile-seed{seed}"
    if not folder.is_dir():
        config = SimulationConfig(
            scene=preset_of(seed), length=length, seed=seed, scanner="profile", camera=True,
            write_map=False,
        )  # fmt: skip
        simulate(config, folder)
    return folder


def survey_samples(
    seed: int, length: float, encoder: CropEncoder, cache: Path | None = None
) -> SliceSamples:
    """The slices of one simulated survey with embeddings, features and reference labels."""
    cache = cache or get_settings().cache_dir / "guardrail-train"
    target = cache / f"samples-{preset_of(seed)}-{length:g}m-seed{seed}.npz"
    if target.is_file():
        z = np.load(target, allow_pickle=False)
        return SliceSamples(
            z["embedding"], z["geometry"], z["label"], z["group"], [str(n) for n in z["names"]]
        )
    folder = simulated_survey(seed, length, cache)
    survey = open_survey(folder, "sim")
    stage = prepare_slices(survey, encoder)
    label = slice_truth(stage, point_reference(survey, stage.points, "guardrail"))
    # slices no image shows whole cannot teach the image heads: leave them out
    keep = stage.has_crop
    samples = SliceSamples(
        stage.embedding[keep],
        stage.geometry[keep],
        label[keep],
        np.full(int(keep.sum()), seed, dtype=np.int64),
        stage.geometry_names,
    )
    partial = target.with_suffix(".partial.npz")
    np.savez_compressed(
        partial,
        embedding=samples.embedding,
        geometry=samples.geometry,
        label=samples.label,
        group=samples.group,
        names=np.array(samples.geometry_names),
    )
    os.replace(partial, target)
    return samples


def build_samples(
    seeds: list[int],
    length: float,
    encoder: CropEncoder | None = None,
    progress: Progress | None = None,
) -> SliceSamples:
    encoder = encoder or CropEncoder()
    parts = []
    for i, seed in enumerate(seeds):
        if progress:
            progress(f"survey {seed}", i / max(len(seeds), 1))
        parts.append(survey_samples(seed, length, encoder))
    return SliceSamples(
        np.concatenate([p.embedding for p in parts]),
        np.concatenate([p.geometry for p in parts]),
        np.concatenate([p.label for p in parts]),
        np.concatenate([p.group for p in parts]),
        parts[0].geometry_names,
    )
