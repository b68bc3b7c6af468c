"""Vehicle shapes: evidence that an object-sized cluster is a vehicle, from its 3D points alone.

The camera misses vehicles: in deep shadow or low light, and classes a Cityscapes-trained
network never learnt (trailers, site machines, caravans). They are vehicle-shaped all the same:
a body 3-12 m long and 1.5-2.6 m wide, most of its points between knee and roof height, closed
down to the wheels, nothing above 4 m, and smooth panels where a hedge or a tree is a scatter.
`shape_inputs` measures one frame's clusters twice: 19 summary features (footprint along its
own axes, height bands, eigenvalue shape) and `SHAPE_POINTS` of its points in the cluster's own
frame (centred, turned onto its long axis, heights above the ground). `VehicleShapes` is a
small PointNet (a shared per-point MLP, max-pooled) beside an MLP over the summary, trained on
the simulator's labelled objects (`training/shapes.py`, rotating scanners of 32 and 64 beams);
a cluster's long axis has no front, so it averages the four mirror images. Tracks average its
probability over their frames, weighed by the frames' points (`tracking.py`).
"""

from __future__ import annotations

import datetime
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from app.core.errors import InputError
from app.pipelines.checkpoints import card_of, load_checkpoint

MODELS = Path(__file__).resolve().parents[3] / "models" / "clutter"
ROTATING_MODEL = MODELS / "vehicle_shapes_rotating.pt"  # rotating scanners (HDL-64E-like)
BANDS = (0.1, 0.5, 1.0, 1.5, 2.0, 2.5, 3.5)  # metres above the ground: height band edges
FEATURES = (
    "log_points", "range", "length", "width", "top", "bottom", "height",
    *(f"band_{lo:g}_{hi:g}" for lo, hi in zip(BANDS[:-1], BANDS[1:], strict=True)),
    f"band_above_{BANDS[-1]:g}", "linearity", "planarity", "scattering", "normal_z",
    "log_density",
)  # fmt: skip
HIDDEN = 32
SHAPE_POINTS = 128  # points per cluster the point branch sees (drawn with repeats when fewer)
POINT_WIDTHS = (32, 64, 128)  # the shared per-point MLP
BATCH = 1024  # clusters per forward pass
# metres: a vehicle seen from any side spans at least its width (>= 1.4 m for the narrowest
# car) along one of its axes; a narrower cluster (a pole, a sign, a trunk) is none, whatever the
# network says (on real scans it has called such clusters vehicles)
MIN_VEHICLE_SPAN = 1.2
# the four mirror images of a cluster's own frame (its long axis has no front, no left)
MIRRORS = ((1.0, 1.0), (-1.0, 1.0), (1.0, -1.0), (-1.0, -1.0))


@dataclass
class ShapeInputs:
    """What the classifier reads per cluster of one frame; NaN rows for clusters not chosen."""

    features: np.ndarray  # (C, len(FEATURES)) float32
    points: np.ndarray  # (C, SHAPE_POINTS, 3) float32: along, across, height above the ground


def shape_inputs(
    xyz: np.ndarray,
    label: np.ndarray,
    above_ground: np.ndarray,
    chosen: np.ndarray,
    seed: int = 0,
) -> ShapeInputs:
    """Both inputs per cluster of one frame (sensor coordinates), NaN rows for clusters not
    `chosen` or without points. One pass of bincounts, no loop over clusters; the points are
    drawn with a generator of `seed`, so a frame's inputs do not depend on the run."""
    count = len(chosen)
    out = np.full((count, len(FEATURES)), np.nan, dtype=np.float32)
    points = np.full((count, SHAPE_POINTS, 3), np.nan, dtype=np.float32)
    use = (label >= 0) & chosen[np.where(label >= 0, label, 0)]
    if count == 0 or not use.any():
        return ShapeInputs(out, points)
    lab, p, h = label[use], xyz[use].astype(np.float64), above_ground[use]
    n = np.bincount(lab, minlength=count).astype(np.float64)
    has = n > 0
    safe = np.maximum(n, 1)
    mean = np.stack([np.bincount(lab, p[:, k], count) for k in range(3)], 1) / safe[:, None]
    d = p - mean[lab]
    cov = np.empty((count, 3, 3))
    for i in range(3):
        for j in range(i, 3):
            cov[:, i, j] = cov[:, j, i] = np.bincount(lab, d[:, i] * d[:, j], count) / safe
    cov[~has] = np.eye(3)
    values, vectors = np.linalg.eigh(cov)  # ascending
    l3, l2, l1 = (np.maximum(values[:, k], 1e-12) for k in range(3))
    # footprint along the cluster's own horizontal axes
    xy_values, xy_vectors = np.linalg.eigh(cov[:, :2, :2])
    major = xy_vectors[:, :, 1]
    along = np.einsum("ij,ij->i", d[:, :2], major[lab])
    across = np.einsum("ij,ij->i", d[:, :2], xy_vectors[:, :, 0][lab])
    length = _spread(along, lab, count)
    width = _spread(across, lab, count)
    top = np.full(count, -np.inf)
    bottom = np.full(count, np.inf)
    np.maximum.at(top, lab, h)
    np.minimum.at(bottom, lab, h)
    edges = np.array([*BANDS, np.inf])
    band = np.clip(np.searchsorted(edges, h, side="right") - 1, 0, len(BANDS) - 1)
    bands = np.zeros((count, len(BANDS)))
    np.add.at(bands, (lab, band), 1.0)
    bands /= safe[:, None]
    distance = np.linalg.norm(mean[:, :2], axis=1)
    height = top - bottom
    area = np.maximum(length, 0.1) * np.maximum(height, 0.1)
    columns = [
        np.log(safe), distance, length, width, top, bottom, height, *bands.T,
        (l1 - l2) / l1, (l2 - l3) / l1, l3 / l1, np.abs(vectors[:, 2, 0]),
        np.log(safe * np.maximum(distance, 1.0) ** 2 / area),
    ]  # fmt: skip
    out[has] = np.stack(columns, 1)[has].astype(np.float32)
    local = np.stack([along, across, h], 1)
    points[has] = _drawn(local, lab, n.astype(np.int64), seed)[has]
    return ShapeInputs(out, points)


def _drawn(local: np.ndarray, label: np.ndarray, n: np.ndarray, seed: int) -> np.ndarray:
    """(C, SHAPE_POINTS, 3): per cluster, `SHAPE_POINTS` of its rows drawn uniformly (with
    repeats where it has fewer); zeros for empty clusters."""
    order = np.argsort(label, kind="stable")
    starts = np.concatenate([[0], np.cumsum(n)[:-1]]).astype(np.int64)
    draw = np.random.default_rng(seed).random((len(n), SHAPE_POINTS))
    pick = starts[:, None] + np.minimum((draw * n[:, None]).astype(np.int64), n[:, None] - 1)
    pick = np.clip(pick, 0, max(len(order) - 1, 0))
    return local[order[pick]].astype(np.float32) if len(order) else np.zeros((len(n), 0, 3))


def _spread(values: np.ndarray, label: np.ndarray, count: int) -> np.ndarray:
    lo = np.full(count, np.inf)
    hi = np.full(count, -np.inf)
    np.minimum.at(lo, label, values)
    np.maximum.at(hi, label, values)
    return np.where(np.isfinite(hi - lo), hi - lo, 0.0)


class ShapeNet(nn.Module):
    """A PointNet over the cluster's points (shared MLP, max-pooled) beside an MLP over its
    summary features; one logit, vehicle or not."""

    def __init__(self, features: int):
        super().__init__()
        layers: list[nn.Module] = []
        width = 3
        for out in POINT_WIDTHS:
            layers += [nn.Linear(width, out), nn.ReLU()]
            width = out
        self.point_mlp = nn.Sequential(*layers)
        self.summary = nn.Sequential(nn.Linear(features, HIDDEN), nn.ReLU())
        self.head = nn.Sequential(
            nn.Linear(width + HIDDEN, HIDDEN), nn.ReLU(), nn.Linear(HIDDEN, 1)
        )

    def forward(self, features: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
        pooled = self.point_mlp(points).amax(dim=1)
        return self.head(torch.cat([pooled, self.summary(features)], dim=1))[:, 0]


@dataclass
class VehicleShapes:
    """The classifier: standardisation and the network, with its model card."""

    net: ShapeNet
    mean: np.ndarray
    std: np.ndarray
    card: dict[str, Any]

    def probability(self, inputs: ShapeInputs) -> np.ndarray:
        """(C,) P(vehicle) per cluster, the mean logit of its four mirror images; clusters
        without inputs (NaN rows) or narrower than `MIN_VEHICLE_SPAN` give 0."""
        features, points = inputs.features, inputs.points
        out = np.zeros(len(features), dtype=np.float32)
        ok = np.isfinite(features).all(axis=1) & np.isfinite(points).all(axis=(1, 2))
        span = np.fmax(features[:, FEATURES.index("length")], features[:, FEATURES.index("width")])
        ok &= span >= MIN_VEHICLE_SPAN
        if not ok.any():
            return out
        x = torch.from_numpy(((features[ok] - self.mean) / self.std).astype(np.float32))
        p = torch.from_numpy(points[ok].astype(np.float32))
        logits = []
        with torch.inference_mode():  # in batches: a point's activations are 128 floats
            for xs, ps in zip(x.split(BATCH), p.split(BATCH), strict=True):
                mirrored = [self.net(xs, ps * mirror_of(m)) for m in MIRRORS]
                logits.append(torch.stack(mirrored).mean(0))
        out[ok] = torch.sigmoid(torch.cat(logits)).numpy()
        return out

    def save(self, path: Path) -> None:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        card = {"created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
                "features": list(FEATURES), **self.card}  # fmt: skip
        blob = {"state": self.net.state_dict(), "mean": torch.from_numpy(self.mean),
                "std": torch.from_numpy(self.std), "card": card}  # fmt: skip
        torch.save(blob, path)
        path.with_suffix(".json").write_text(json.dumps(card, indent=1) + "\n")


def mirror_of(signs: tuple[float, float]) -> torch.Tensor:
    """(3,) the factors that mirror points along / across the long axis (heights stay)."""
    return torch.tensor([signs[0], signs[1], 1.0])


def load_vehicle_shapes(path: Path = ROTATING_MODEL) -> VehicleShapes:
    """The classifier at `path` (weights only); InputError naming the file when it is not one."""
    blob = load_checkpoint(path, "vehicle shape")
    try:
        mean = blob["mean"].numpy().astype(np.float32)
        std = blob["std"].numpy().astype(np.float32)
        net = ShapeNet(len(mean))
        net.load_state_dict(blob["state"])
    except (KeyError, RuntimeError, AttributeError) as exc:
        raise InputError(path, f"not a vehicle shape checkpoint ({exc})") from None
    if len(mean) != len(FEATURES):
        raise InputError(path, f"has {len(mean)} features, this version measures {len(FEATURES)}")
    card = card_of(path, ".json", lambda p: dict(blob.get("card") or {}))
    return VehicleShapes(net.eval(), mean, std, card)
