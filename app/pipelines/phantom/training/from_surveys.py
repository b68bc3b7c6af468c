"""Training from surveys: the class-balanced sample set built from simulated drives and labelled
real sequences (SemanticKITTI), then `train.train`, the model card and the checkpoint: what
`mmsclean train phantom` and the benchmarks run. The only phantom module that simulates.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import torch

from app.core.progress import Progress
from app.core.sensors import SensorKind, kind_of_scanner
from app.core.settings import get_settings
from app.io import open_survey
from app.io.survey import Survey
from app.pipelines.phantom.config import PhantomConfig
from app.pipelines.phantom.model import save_model
from app.pipelines.phantom.network import CLASS_NAMES
from app.pipelines.phantom.priors import class_priors
from app.pipelines.phantom.training.dataset import (
    N_CLASSES,
    LabelledMap,
    Samples,
    balanced,
    concatenate,
    frame_windows,
    labelled_map_from_survey,
    pillar_samples,
)
from app.pipelines.phantom.training.train import TrainConfig, train
from app.simulate.survey import SimulationConfig, simulate

SIM_PRESETS = ("urban", "highway", "mixed")


def street_priors(sources: list[dict]) -> tuple[list[float], str]:
    """The class frequencies of the classified pillars the pipeline moves its softmax to
    (priors.py): of the real training maps when there are any, else of all maps. Simulated
    traffic is denser than a real street's (about 33 % phantom pillars in the simulated 10-frame
    drives, 2-5 % in SemanticKITTI): with the priors of all maps the rotating models held out on
    SemanticKITTI 04 / 05 reached point F 56.1 / 50.9, with the real ones 86.1 / 82.3
    (bench/RESULTS.md)."""
    real = [s for s in sources if s.get("format") != "sim"]
    judged = np.zeros(N_CLASSES)
    for source in real or sources:
        judged += [source["judged_pillars"][name] for name in CLASS_NAMES]
    origin = "real training maps" if real else "all training maps"
    return class_priors(judged).round(5).tolist(), origin


def training_sensor_kind(
    sim_seeds: list[int], semantickitti: list[Path], config: TrainConfig
) -> SensorKind:
    """The one scanner kind a model is trained for: the simulator's scanner, and SemanticKITTI
    sequences are HDL-64E (rotating). Kinds are never mixed: mixed with profile scans, a model
    called the parked cars of the profile scans phantoms."""
    sim_kind = kind_of_scanner(config.scanner) if sim_seeds else None
    if semantickitti and sim_kind is SensorKind.PROFILE:
        raise ValueError(
            "SemanticKITTI sequences are rotating-scanner (HDL-64E) data: train them with "
            "simulated rotating drives (scanner hdl64), not with profile-scanner surveys"
        )
    return SensorKind.ROTATING if semantickitti else (sim_kind or SensorKind.UNKNOWN)


def _sim_folder(cache_dir: Path, scene: str, length: float, seed: int, scanner: str) -> Path:
    variant = "-varied" if scanner == "hdl64" else ""
    return cache_dir / f"sim-{scene}-{length:g}m-{scanner}{variant}-seed{seed}"


def _merge_infos(infos: list[dict], fmt: str, path: Path) -> dict:
    """One entry per map from its per-rotation entries (pillar counts of the first rotation)."""
    first = infos[0]
    samples = {name: sum(i["samples"][name] for i in infos) for name in CLASS_NAMES}
    return {
        "name": first["name"],
        "format": fmt,
        "path": str(path),
        "points": first["points"],
        "pillars": first["pillars"],
        "judged_pillars": first["judged_pillars"],
        "rotations_deg": [i["rotation_deg"] for i in infos],
        "samples": samples,
    }


def _map_count(survey: Survey, config: TrainConfig) -> int:
    """How many labelled maps `_maps_of` makes of the survey (counted without reading points)."""
    if config.frames_per_map and not survey.is_map:
        return math.ceil(len(survey.frames) / config.frames_per_map)
    return 1


def _maps_of(path: Path, fmt: str, config: TrainConfig) -> list[LabelledMap]:
    """The labelled maps of one training survey: the whole survey, or its frame windows."""
    lmap = labelled_map_from_survey(open_survey(path, fmt))
    if config.frames_per_map and lmap.passes is not None:
        return frame_windows(lmap, config.frames_per_map)
    return [lmap]


def build_training_set(
    sim_seeds: list[int],
    semantickitti: list[Path],
    config: TrainConfig | None = None,
    rng: np.random.Generator | None = None,
    sim_length: float = 200.0,
    cache_dir: Path | None = None,
    phantom_config: PhantomConfig | None = None,
    progress: Progress | None = None,
) -> Samples:
    """Class-balanced samples from simulated surveys and SemanticKITTI sequences.

    Simulations (`config.scanner`, no camera; presets urban / highway / mixed cycled over the
    seeds) are written once into `cache_dir` (default `<data dir>/cache/phantom-train`) and reused,
    they are deterministic. Each map gives at most ceil(2 * per_class / maps) samples per class, so
    that no map dominates; a class with fewer pillars than that is taken again from further random
    rotations of the map (up to `config.rotations` in all). The pool is then `balanced`.
    """
    config = config or TrainConfig()
    rng = rng if rng is not None else np.random.default_rng(config.seed)
    phantom_config = phantom_config or PhantomConfig()
    cache_dir = (
        Path(cache_dir) if cache_dir is not None else get_settings().cache_dir / "phantom-train"
    )
    sources: list[tuple[Path, str]] = []
    for i, seed in enumerate(sim_seeds):
        scene = SIM_PRESETS[i % len(SIM_PRESETS)]
        folder = _sim_folder(cache_dir, scene, sim_length, seed, config.scanner)
        if not (folder / "ground_truth" / "simulation.json").is_file():
            cache_dir.mkdir(parents=True, exist_ok=True)
            if progress is not None:
                progress(f"simulate {folder.name}", i / max(len(sim_seeds), 1))
            sim = SimulationConfig(
                scene=scene,
                length=sim_length,
                seed=seed,
                scanner=config.scanner,
                camera=False,
                vary_scanner=config.scanner == "hdl64",  # rotating scanners differ: draw one
            )
            simulate(sim, folder, overwrite=True)
        sources.append((folder, "sim"))
    sources += [(Path(p), "semantickitti") for p in semantickitti]
    if not sources:
        raise ValueError("no training data: give simulation seeds or SemanticKITTI sequences")
    maps = sum(_map_count(open_survey(path, fmt), config) for path, fmt in sources)
    cap = max(1, math.ceil(2 * config.per_class / maps))
    parts: list[Samples] = []
    infos: list[dict] = []
    for k, (path, fmt) in enumerate(sources):
        if progress is not None:
            progress(f"samples {path.name}", k / len(sources))
        for lmap in _maps_of(path, fmt, config):
            taken = np.zeros(N_CLASSES, dtype=np.int64)
            map_infos = []
            for _ in range(config.rotations):
                want = {c: int(max(cap - taken[c], 0)) for c in range(N_CLASSES)}
                if not any(want.values()):
                    break
                part = pillar_samples(
                    lmap, phantom_config, rng, rotate=True, max_per_class=want,
                    context=config.context > 0, passes=config.passes,
                )  # fmt: skip
                taken += np.bincount(part.y, minlength=N_CLASSES)
                map_infos += part.sources
                parts.append(part)
            infos.append(_merge_infos(map_infos, fmt, path))
    pool = concatenate(parts)
    del parts
    out = balanced(pool, config.per_class, rng)
    out.sources = infos
    return out


def train_phantom_model(
    out: Path,
    sim_seeds: list[int],
    semantickitti: list[Path],
    train_config: TrainConfig | None = None,
    progress: Progress | None = None,
    sim_length: float = 200.0,
    cache_dir: Path | None = None,
) -> dict:
    """Build the training set, train, write the checkpoint and its card; returns the card."""
    config = train_config or TrainConfig()
    kind = training_sensor_kind(sim_seeds, semantickitti, config)
    if config.threads:
        torch.set_num_threads(config.threads)
    started = time.perf_counter()
    samples = build_training_set(
        sim_seeds,
        semantickitti,
        config,
        np.random.default_rng(config.seed),
        sim_length=sim_length,
        cache_dir=cache_dir,
        progress=progress,
    )
    build_seconds = time.perf_counter() - started
    result = train(samples, config, progress)
    card = {
        **result.card,
        "sensor_kind": kind.value,
        "build_seconds": round(build_seconds, 1),
        "simulation": {
            "seeds": list(sim_seeds),
            "presets": [SIM_PRESETS[i % len(SIM_PRESETS)] for i in range(len(sim_seeds))],
            "length_m": sim_length,
            "scanner": config.scanner,
        },
        "threads": torch.get_num_threads(),
    }
    card["class_priors"], card["class_priors_from"] = street_priors(samples.sources)
    save_model(Path(out), result.net, card)
    if progress is not None:
        progress("done", 1.0)
    return card
