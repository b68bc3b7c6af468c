"""The points a client is shown, held in contiguous arrays beside their map indices.

The viewer's map lives in memory-mapped files. Gathering a few hundred thousand shown points
from them at random indices took 60 of a click's 80 ms on a real street (SemanticKITTI 08,
550,000 points shown), and every click, rectangle, polygon, preview and colour update needs
those points. A cloud's positions and pillars are gathered once, when it is drawn, and kept
here."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from app.review.survey_map import SurveyMap


@dataclass(frozen=True)
class ShownPoints:
    index: np.ndarray  # (n,) int64 map point indices
    xyz: np.ndarray  # (n, 3) float32 local coordinates, C-contiguous
    cell: np.ndarray  # (n,) int64 pillar of each point (index into the map's cells)

    @classmethod
    def gather(cls, survey_map: SurveyMap, index: np.ndarray) -> ShownPoints:
        index = np.asarray(index, dtype=np.int64)
        return cls(
            index,
            np.ascontiguousarray(survey_map.xyz[index], dtype=np.float32),
            np.asarray(survey_map.cell[index], dtype=np.int64),
        )

    @classmethod
    def empty(cls) -> ShownPoints:
        return cls(np.zeros(0, np.int64), np.zeros((0, 3), np.float32), np.zeros(0, np.int64))

    @classmethod
    def join(cls, parts: Sequence[ShownPoints]) -> ShownPoints:
        return cls(
            np.concatenate([p.index for p in parts]),
            np.concatenate([p.xyz for p in parts]),
            np.concatenate([p.cell for p in parts]),
        )

    def take(self, which: np.ndarray) -> ShownPoints:
        """The points selected by a boolean mask or an index array."""
        return ShownPoints(self.index[which], self.xyz[which], self.cell[which])

    def __len__(self) -> int:
        return len(self.index)
