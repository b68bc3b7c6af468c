"""Scores of a point-removal decision: the clutter paper's error matrix and the DynamicMap scores.

Both compare a reference (True = the point belongs to an object that should go) with a decision
(True = removed), point by point, and report percentages.

- **Error matrix** (Lee et al. 2020, Tables 2 and 3): rows are the classified data, columns the
  reference; overall accuracy = correct / all; error of omission for clutter = clutter points
  kept / reference clutter; error of commission for clutter = map points removed / removed;
  error of omission for the map = map points removed / reference map; error of commission for
  the map = clutter points kept / kept (the clutter left in the cleaned map).
- **SA / DA / AA** (the DynamicMap benchmark): SA = static points kept / static points,
  DA = dynamic points removed / dynamic points, AA = sqrt(SA x DA).

Undefined ratios (an empty denominator) are NaN here, not 0: a sequence without any moving
point has no DA, and a table must show that instead of a perfect or a zero score.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np


def _percent(numerator: int, denominator: int) -> float:
    return 100.0 * numerator / denominator if denominator else float("nan")


@dataclass(frozen=True)
class ErrorMatrix:
    """Counts of the paper's Table 2 (classified x reference) and the Table 3 ratios (%)."""

    clutter_removed: int  # reference clutter, classified clutter (true positives)
    map_removed: int  # reference map, classified clutter
    clutter_kept: int  # reference clutter, classified map
    map_kept: int  # reference map, classified map (true negatives)

    @property
    def total(self) -> int:
        return self.clutter_removed + self.map_removed + self.clutter_kept + self.map_kept

    @property
    def overall_accuracy(self) -> float:
        return _percent(self.clutter_removed + self.map_kept, self.total)

    @property
    def clutter_omission(self) -> float:
        return _percent(self.clutter_kept, self.clutter_removed + self.clutter_kept)

    @property
    def clutter_commission(self) -> float:
        return _percent(self.map_removed, self.clutter_removed + self.map_removed)

    @property
    def map_omission(self) -> float:
        return _percent(self.map_removed, self.map_removed + self.map_kept)

    @property
    def map_commission(self) -> float:
        return _percent(self.clutter_kept, self.clutter_kept + self.map_kept)

    def as_dict(self) -> dict[str, float | int]:
        return {
            **asdict(self),
            "points": self.total,
            "overall_accuracy": self.overall_accuracy,
            "clutter_omission": self.clutter_omission,
            "clutter_commission": self.clutter_commission,
            "map_omission": self.map_omission,
            "map_commission": self.map_commission,
        }


def error_matrix(reference: np.ndarray, removed: np.ndarray) -> ErrorMatrix:
    """The paper's error matrix of `removed` against `reference` (both boolean per point)."""
    reference, removed = _pair(reference, removed)
    both = int(np.count_nonzero(reference & removed))
    n_reference = int(np.count_nonzero(reference))
    n_removed = int(np.count_nonzero(removed))
    return ErrorMatrix(
        clutter_removed=both,
        map_removed=n_removed - both,
        clutter_kept=n_reference - both,
        map_kept=len(reference) - n_reference - n_removed + both,
    )


@dataclass(frozen=True)
class DynamicScores:
    """SA, DA, AA in percent, with the point counts behind them."""

    static_points: int
    static_kept: int
    dynamic_points: int
    dynamic_removed: int

    @property
    def sa(self) -> float:
        return _percent(self.static_kept, self.static_points)

    @property
    def da(self) -> float:
        return _percent(self.dynamic_removed, self.dynamic_points)

    @property
    def aa(self) -> float:
        return float(np.sqrt(self.sa * self.da))

    def as_dict(self) -> dict[str, float | int]:
        return {**asdict(self), "SA": self.sa, "DA": self.da, "AA": self.aa}


def dynamic_scores(
    dynamic: np.ndarray, removed: np.ndarray, static: np.ndarray | None = None
) -> DynamicScores:
    """SA / DA / AA of `removed`. `static` defaults to not `dynamic`; pass it to leave points
    without a reference class (unlabelled, outliers) out of both scores."""
    dynamic, removed = _pair(dynamic, removed)
    static = ~dynamic if static is None else _pair(static, removed)[0] & ~dynamic
    return DynamicScores(
        static_points=int(np.count_nonzero(static)),
        static_kept=int(np.count_nonzero(static & ~removed)),
        dynamic_points=int(np.count_nonzero(dynamic)),
        dynamic_removed=int(np.count_nonzero(dynamic & removed)),
    )


def _pair(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.asarray(a, dtype=bool).reshape(-1)
    b = np.asarray(b, dtype=bool).reshape(-1)
    if a.shape != b.shape:
        raise ValueError(f"reference has {a.size} points, the decision {b.size}")
    return a, b
