"""Held-out map blocks for validation: whole blocks, reproducible, never all, and with class
labels every class on both sides where it spans two blocks."""

from __future__ import annotations

import numpy as np

from app.metrics.splits import held_out_blocks


def grid_positions(blocks: int, per_block: int) -> np.ndarray:
    """`per_block` positions inside each of `blocks` 10 m blocks along x."""
    x = np.repeat(np.arange(blocks) * 10.0 + 5.0, per_block)
    return np.column_stack([x, np.zeros_like(x)])


def test_blocks_stay_whole_reproducible_and_never_all() -> None:
    positions = grid_positions(10, 5)
    held = held_out_blocks(positions, 10.0, 0.2, seed=3)
    per_block = held.reshape(10, 5)
    assert (per_block.all(axis=1) | ~per_block.any(axis=1)).all()  # whole blocks
    assert per_block.any(axis=1).sum() == 2
    assert (held == held_out_blocks(positions, 10.0, 0.2, seed=3)).all()
    assert not held_out_blocks(grid_positions(2, 5), 10.0, 0.99, seed=0).all()


def test_a_rare_class_lands_on_both_sides() -> None:
    """Phantom labels in 2 of 10 blocks: whatever the seed, validation and training each get
    one; a class in one block only stays where the draw put it."""
    positions = grid_positions(10, 5)
    classes = np.zeros(50, dtype=np.int64)
    classes[[7, 8, 31]] = 3  # blocks 1 and 6
    classes[44] = 2  # block 8 alone
    for seed in range(20):
        held = held_out_blocks(positions, 10.0, 0.2, seed, classes)
        phantom = classes == 3
        assert held[phantom].any() and (~held[phantom]).any(), seed
        assert 0 < held.sum() < len(held)
