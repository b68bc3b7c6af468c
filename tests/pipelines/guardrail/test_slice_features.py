"""A tiled run's slice features stay in its tiles' files: the index keys them, a read takes the
rows asked from the parts that hold them (retraining reads a few reviewed slices, not the run)."""

from pathlib import Path

import numpy as np

from app.pipelines.guardrail.segmentation import (
    index_slice_features,
    read_slice_features,
    slice_feature_keys,
)

NAMES = np.array(["height", "width"])


def _part(path: Path, slice_index: np.ndarray, rng: np.random.Generator) -> dict:
    columns = {
        "component": np.zeros(len(slice_index), np.int64),  # the tile's own numbers
        "slice_index": slice_index,
        "embedding": rng.normal(size=(len(slice_index), 8)).astype(np.float16),
        "geometry": rng.normal(size=(len(slice_index), 2)).astype(np.float32),
        "has_crop": rng.random(len(slice_index)) < 0.5,
    }
    np.savez(path, geometry_names=NAMES, **columns)
    return columns


def test_an_index_reads_the_rows_asked_from_their_parts(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    (tmp_path / "tiles").mkdir()
    parts = [tmp_path / "tiles" / f"{k:05d}.features.npz" for k in range(3)]
    columns = [
        _part(p, np.arange(n) + 10 * k, rng)
        for k, (p, n) in enumerate(zip(parts, (4, 0, 5), strict=True))
    ]
    numbers = [np.full(4, 7), np.zeros(0, np.int64), np.array([7, 7, 8, 8, 9])]
    index = index_slice_features(tmp_path / "features.npz", parts, numbers)
    component, slice_index = slice_feature_keys(index)
    assert component.tolist() == [7, 7, 7, 7, 7, 7, 8, 8, 9]
    assert slice_index.tolist() == [0, 1, 2, 3, 20, 21, 22, 23, 24]
    whole = {
        c: np.concatenate([part[c] for part in columns])
        for c in ("embedding", "geometry", "has_crop")
    }
    rows = np.array([8, 0, 5, 3])  # across the parts, in no order
    got = read_slice_features(index, rows)
    assert got["geometry_names"].tolist() == NAMES.tolist()
    for c, values in whole.items():
        assert got[c].dtype == values.dtype and np.array_equal(got[c], values[rows])
    empty = read_slice_features(index, np.zeros(0, np.int64))
    assert empty["embedding"].shape == (0, 8) and empty["has_crop"].dtype == bool


def test_a_file_of_its_own_is_read_as_before(tmp_path: Path) -> None:
    columns = _part(tmp_path / "features.npz", np.arange(6), np.random.default_rng(4))
    assert slice_feature_keys(tmp_path / "features.npz")[1].tolist() == list(range(6))
    got = read_slice_features(tmp_path / "features.npz", np.array([5, 1]))
    assert np.array_equal(got["geometry"], columns["geometry"][[5, 1]])
