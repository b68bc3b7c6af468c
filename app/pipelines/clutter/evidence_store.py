"""Each frame's evidence (`fusion.FrameEvidence`: 14 bytes per point) kept on disk instead of in
memory, for the frames of a tile: a rotating scanner's tile reads tens of millions of points,
and the pipeline needs a frame's evidence three times (free space, fusion, review), one frame at
a time. A list of `FrameEvidence` and a `SpilledEvidence` are used alike: `append`, `[i]`,
`[i] = evidence` after a change, `len`."""

from __future__ import annotations

import shutil
from collections.abc import Sequence
from dataclasses import fields
from pathlib import Path

import numpy as np

from app.pipelines.clutter.fusion import FrameEvidence

_FIELDS = tuple(f.name for f in fields(FrameEvidence))


class SpilledEvidence(Sequence[FrameEvidence]):
    """Frame evidence in `folder` (one uncompressed .npz per frame: written and read whole
    at disk speed); `close` removes the folder."""

    def __init__(self, folder: Path):
        self.folder = Path(folder)
        shutil.rmtree(self.folder, ignore_errors=True)
        self.folder.mkdir(parents=True)
        self._count = 0

    def _path(self, i: int) -> Path:
        return self.folder / f"{i:06d}.npz"

    def append(self, evidence: FrameEvidence) -> None:
        self._count += 1
        self[self._count - 1] = evidence

    def __setitem__(self, i: int, evidence: FrameEvidence) -> None:
        if not 0 <= i < self._count:
            raise IndexError(f"frame {i} of {self._count}")
        arrays = {k: getattr(evidence, k) for k in _FIELDS if getattr(evidence, k) is not None}
        np.savez(self._path(i), **arrays)

    def __getitem__(self, i: int) -> FrameEvidence:  # type: ignore[override] (no slices)
        if not 0 <= i < self._count:
            raise IndexError(f"frame {i} of {self._count}")
        with np.load(self._path(i)) as data:
            return FrameEvidence(**{k: data[k] for k in data.files})

    def __len__(self) -> int:
        return self._count

    def close(self) -> None:
        shutil.rmtree(self.folder, ignore_errors=True)
