"""Figures for the README (synthetic data): a camera frame of the sample survey with its
instance masks, and a top-down view of a phantom-rich simulated map (120 m of the `mixed` street
with the profile scanner: oncoming traffic, a queue at a red light, a tram) coloured by the
phantom paper's pillar classes.

Usage: .venv/bin/python docs/make_figures.py
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import cv2
import numpy as np

from app.core.labels import CLUTTER_SEMANTIC
from app.geometry.trajectory import station_offsets
from app.io import open_survey
from app.simulate.survey import SimulationConfig, simulate

DOCS = Path(__file__).resolve().parent
# the phantom paper's colours: dark grey ground, light grey high, black short, blue phantom
PILLAR_COLORS = np.array([[90, 90, 90], [200, 200, 200], [20, 20, 20], [30, 110, 255]], np.uint8)


def mask_overlay(survey_dir: Path, frame_id: str) -> np.ndarray:
    """The camera image with each movable object (the clutter paper's classes) tinted in a
    colour of its own instance and outlined: the masks the clutter pipeline has to find."""
    image = cv2.imread(str(survey_dir / "image_02" / "data" / f"{frame_id}.png"))
    masks = survey_dir / "ground_truth" / "masks"
    semantic = cv2.imread(str(masks / f"{frame_id}_semantic.png"), cv2.IMREAD_UNCHANGED)
    instance = cv2.imread(str(masks / f"{frame_id}_instance.png"), cv2.IMREAD_UNCHANGED)
    clutter = np.isin(semantic, [int(c) for c in CLUTTER_SEMANTIC]) & (instance > 0)
    hues = (instance.astype(np.int64) * 47) % 180  # a stable, distinct hue per instance
    hsv = np.stack([hues, np.full_like(hues, 230), np.full_like(hues, 255)], -1).astype(np.uint8)
    tint = cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR).astype(np.float64)
    out = image.astype(np.float64)
    out[clutter] = 0.4 * out[clutter] + 0.6 * tint[clutter]
    out = out.astype(np.uint8)
    edges = cv2.morphologyEx(
        (instance * clutter).astype(np.float32), cv2.MORPH_GRADIENT, np.ones((3, 3))
    )
    out[edges > 0] = (255, 255, 255)
    return out


def top_down(survey_dir: Path, metres_per_pixel: float = 0.1, right: float = 9.0, left=20.0):
    """Accumulated world points seen from above, coloured by pillar class (higher points last),
    from `right` metres right of the trajectory to `left` metres left of it, below roofs."""
    survey = open_survey(survey_dir, "sim")
    xyz, pillar = [], []
    for frame in survey.frames:
        xyz.append(frame.world_points().xyz)
        pillar.append(frame.reference_labels()["pillar_class"])
    xyz, pillar = np.concatenate(xyz), np.concatenate(pillar)
    _, lateral = station_offsets(xyz, survey.poses()[:, :3, 3])
    keep = (lateral > -right) & (lateral < left) & (xyz[:, 2] < survey.poses()[:, 2, 3].max() + 2)
    xyz, pillar = xyz[keep], pillar[keep]
    order = np.argsort(xyz[:, 2])
    xyz, pillar = xyz[order], pillar[order]
    lo = xyz[:, :2].min(axis=0)
    cols = ((xyz[:, 0] - lo[0]) / metres_per_pixel).astype(int)
    rows = ((xyz[:, 1] - lo[1]) / metres_per_pixel).astype(int)
    h, w = rows.max() + 1, cols.max() + 1
    image = np.full((h, w, 3), 255, np.uint8)
    image[h - 1 - rows, cols] = PILLAR_COLORS[pillar][:, ::-1]
    return image


def main() -> None:
    sample = DOCS.parent / "data_samples" / "urban-60m"
    cv2.imwrite(str(DOCS / "sim_frame_masks.png"), mask_overlay(sample, "0000000020"))
    config = SimulationConfig(scene="mixed", length=120.0, seed=2, scanner="profile", camera=False)
    with tempfile.TemporaryDirectory() as tmp:
        simulate(config, Path(tmp) / "mixed")
        cv2.imwrite(str(DOCS / "sim_map_pillars.png"), top_down(Path(tmp) / "mixed"))


if __name__ == "__main__":
    main()
