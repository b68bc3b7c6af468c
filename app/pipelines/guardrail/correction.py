"""Label correction by adjacency (paper 3.3, last paragraph).

The paper: "When a sliced segment with the guardrail label is isolated, it is regarded as
'other object'. On the other hand, [when] most consecutive sliced segments have guardrail
labels, sliced segments with 'other object' are regarded as guardrails." It gives no run
lengths; the exact rule here:

- **Neighbours.** Two slices are adjacent when they belong to the same component, lie on the
  same side of the trajectory and their station indices differ by 1 (consecutive 0.5 m cuts).
  A *chain* is a maximal sequence of adjacent slices; a missing station breaks it.
- **Fill first.** Inside a chain, a run of at most `max_gap` consecutive "other" slices with
  guardrail runs on both sides becomes guardrail (the guardrails around it are the majority:
  with the default 2, at least one guardrail slice on each side of at most two others).
- **Then drop isolated ones.** A run of at most `max_isolated` consecutive guardrail slices
  (default 1: a guardrail slice with no guardrail neighbour) becomes other.

Filling first keeps G O G (a misclassified slice inside a guardrail) as a guardrail; a lone G
with no guardrail neighbour in its chain goes.

**Confident slices stay (beyond the paper, `keep`).** A profile scanner sees a guardrail as one
connected surface, so its slices chain up. A rotating scanner sees it as a few rings crossing
it at grazing angles: the rail falls apart into many small components with stations between
the rings holding no slice, and a true guardrail slice is often alone in its chain (held-out
32-beam highway: 26 of the 34 true slices the paper's rule dropped had no neighbour in their
component). Slices in `keep` (the caller's: a classifier probability of at least
`keep_confident`, `pipeline.confident`) are never dropped as isolated.
"""

from __future__ import annotations

import numpy as np

from app.pipelines.guardrail.slices import SliceSet


def _runs(chain: np.ndarray, label: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Run id per position (sorted order) and the start of every run; a run = same chain and
    same label."""
    new = np.concatenate([[True], (chain[1:] != chain[:-1]) | (label[1:] != label[:-1])])
    return np.cumsum(new) - 1, np.flatnonzero(new)


def correct_labels(
    slice_set: SliceSet,
    labels: np.ndarray,
    *,
    max_gap: int = 2,  # paper: "most consecutive ... are guardrails" (no number given)
    max_isolated: int = 1,  # paper: an "isolated" guardrail slice
    keep: np.ndarray | None = None,  # (K,) bool: guardrail slices never dropped as isolated
) -> np.ndarray:
    """Corrected per-slice labels (same dtype as `labels`; nonzero / True = guardrail)."""
    labels = np.asarray(labels)
    k = len(slice_set)
    if len(labels) != k:
        raise ValueError(f"{len(labels)} labels for {k} slices")
    if k == 0:
        return labels.copy()
    g = labels.astype(bool)
    order = np.lexsort((slice_set.station_index, slice_set.side, slice_set.component))
    comp = slice_set.component[order]
    side = slice_set.side[order]
    st = slice_set.station_index[order]
    brk = np.concatenate(
        [[True], (comp[1:] != comp[:-1]) | (side[1:] != side[:-1]) | (st[1:] - st[:-1] != 1)]
    )
    chain = np.cumsum(brk) - 1
    lab = g[order]

    # 1) fill short runs of "other" flanked by guardrail runs in the same chain
    run, start = _runs(chain, lab)
    length = np.diff(np.append(start, len(lab)))
    run_label = lab[start]
    run_chain = chain[start]
    prev_ok = np.zeros(len(start), dtype=bool)
    next_ok = np.zeros(len(start), dtype=bool)
    prev_ok[1:] = (run_chain[1:] == run_chain[:-1]) & run_label[:-1]
    next_ok[:-1] = (run_chain[:-1] == run_chain[1:]) & run_label[1:]
    fill = ~run_label & (length <= max_gap) & prev_ok & next_ok
    lab = lab | fill[run]

    # 2) drop short runs of guardrail (isolated slices)
    run, start = _runs(chain, lab)
    length = np.diff(np.append(start, len(lab)))
    drop = lab[start] & (length <= max_isolated)
    kept = np.zeros(k, dtype=bool) if keep is None else np.asarray(keep, dtype=bool)[order]
    lab = lab & (~drop[run] | kept)

    out = np.empty_like(g)
    out[order] = lab
    if labels.dtype == bool:
        return out
    return out.astype(labels.dtype)
