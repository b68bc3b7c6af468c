"""The phantom pipeline, step by step: accumulate -> ground -> pillars -> 3D CNN (dense) ->
refinement (Algorithm 1) -> point labels -> cleaned map; plus, when the survey has reference
labels, the paper's metrics."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from app.core.errors import InputError
from app.core.labels import PillarClass
from app.core.progress import Progress
from app.io.accumulate import AccumulatedMap, accumulate, accumulate_window
from app.io.survey import Survey
from app.pipelines.phantom.classify import classify_dense, classify_windows
from app.pipelines.phantom.config import PhantomConfig
from app.pipelines.phantom.model import DEFAULT_MODEL, load_model
from app.pipelines.phantom.pillars import PillarMap, build_pillar_map, phantom_ground
from app.pipelines.phantom.point_labels import point_labels
from app.pipelines.phantom.priors import apply_priors
from app.pipelines.phantom.refine import refine


@dataclass
class PhantomResult:
    map: AccumulatedMap
    pillar_map: PillarMap
    probabilities: np.ndarray  # (P, 4) CNN posterior under the map priors (one-hot ground if gated)
    classified: np.ndarray  # (P,) bool: the CNN judged the pillar (PillarMap.candidates)
    raw_labels: np.ndarray  # (P,) argmax
    pillar_labels: np.ndarray  # (P,) after refinement
    point_labels: np.ndarray  # (N,) uint8 per accumulated point
    timings: dict[str, float]

    def frame_labels(self) -> dict[str, np.ndarray]:
        return self.map.split(self.point_labels)


class PhantomPipeline:
    def __init__(
        self,
        config: PhantomConfig | None = None,
        model_path: Path | None = None,
        dense: bool = True,
    ):
        self.config = config or PhantomConfig()
        self.model_path = Path(model_path) if model_path is not None else DEFAULT_MODEL
        self.net, self.card = load_model(self.model_path)
        self.dense = dense

    def run(self, survey: Survey, progress: Progress | None = None) -> PhantomResult:
        if progress is not None:
            progress("accumulate", 0.0)
        started = time.perf_counter()
        amap = self.accumulate(survey)
        return self.run_map(amap, progress, {"accumulate": round(time.perf_counter() - started, 3)})

    def accumulate(
        self,
        survey: Survey,
        keep: Callable[[np.ndarray], np.ndarray] | None = None,
        pass_t0: float | None = None,
    ) -> AccumulatedMap:
        """The survey's map with what the network reads (scanner passes when it reads time);
        with `keep`, only the points it selects (a tile's window: `accumulate_window`, a map's
        passes binned from `pass_t0`)."""
        if keep is None:
            amap = accumulate(survey, with_reference=True, with_passes=self.net.passes)
        else:
            amap = accumulate_window(survey, keep, True, self.net.passes, pass_t0)
        if self.net.passes and amap.passes is None:
            raise InputError(
                survey.source,
                f"has no point times; the phantom model {self.model_path.name} reads scanner "
                "passes (time as evidence): run it with a model without time",
            )
        return amap

    def run_map(
        self,
        amap: AccumulatedMap,
        progress: Progress | None = None,
        timings: dict[str, float] | None = None,
    ) -> PhantomResult:
        """The steps after accumulation, on a map already built (a whole survey's, or one
        tile's with its halo: `tiled.py`)."""

        def report(stage: str, fraction: float) -> None:
            if progress is not None:
                progress(stage, fraction)

        cfg = self.config
        if cfg.threads:
            torch.set_num_threads(cfg.threads)
        timings = {} if timings is None else timings
        clock = time.perf_counter()

        def lap(name: str) -> None:
            nonlocal clock
            now = time.perf_counter()
            timings[name] = round(now - clock, 3)
            clock = now

        ground = phantom_ground(amap.xyz, cfg)
        lap("ground")
        pm = build_pillar_map(amap.xyz, ground, cfg, amap.passes)
        lap("pillars")
        which = pm.candidates()  # the rest is plain ground (PillarMap.candidates)
        probs = np.zeros((len(pm.pillars), 4), dtype=np.float32)
        probs[:, PillarClass.ground] = 1.0

        def step(fraction: float) -> None:
            report("classify", fraction)

        if self.dense:
            probs[which] = classify_dense(self.net, pm, cfg.tile_pillars, step, which)
        else:
            probs[which] = classify_windows(self.net, pm, cfg.batch_size, step, which)
        priors = self.card.get("class_priors")
        if priors is not None:
            probs[which] = apply_priors(probs[which], np.asarray(priors), cfg.prior_weight)
        lap("classify")
        raw = probs.argmax(axis=1).astype(np.uint8)
        labels = refine(pm.pillars, raw, cfg.refine_window) if cfg.refine else raw
        lap("refine")
        points = point_labels(pm, labels)
        lap("point_labels")
        report("done", 1.0)
        classified = np.zeros(len(pm.pillars), dtype=bool)
        classified[which] = True
        return PhantomResult(amap, pm, probs, classified, raw, labels, points, timings)
