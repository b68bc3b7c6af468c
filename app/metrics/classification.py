"""Confusion matrices and precision / recall / F-measure per class, in percent.

Conventions (used by every pipeline's report):

- A confusion matrix has one row per *reference* class and one column per *predicted* class;
  entry [i, j] counts the samples of reference class i predicted as class j.
- Precision, recall and F are percentages (0..100). Undefined ratios are 0, never NaN: a class
  that is never predicted has precision 0, a class absent from the reference has recall 0 and
  support 0 (support = number of reference samples of the class).
- F is the harmonic mean 2PR / (P + R) of the class's own precision and recall.
- ``macro`` ("overall") is the unweighted mean of the per-class precision, recall and F over the
  classes with support > 0 (classes absent from the reference would only pull it towards 0).

How the phantom paper's Table I "Overall" row is read: its per-class rows are short object
86.5 / 92.6 / 89.5, high object 98.1 / 93.2 / 95.6, phantom 90.0 / 88.5 / 89.3 and ground
99.7 / 98.6 / 99.2 (P / R / F). The mean over all four classes (93.6 / 93.2 / 93.4) does not give
the printed 91.5 / 91.4 / 91.5; the mean over the three non-ground classes
(91.53 / 91.43 / 91.47) does, to the printed digit. So "Overall" is a macro mean, and the paper
left ground out of it. We report the macro mean over every class with support by default and
offer ``macro_exclude=("ground",)`` to reproduce the paper's reading.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

TABLE_HEADER = ["class", "precision [%]", "recall [%]", "F [%]", "support"]


@dataclass(frozen=True)
class ClassScores:
    """Scores of one class (or their macro mean), percent; support = reference samples."""

    precision: float
    recall: float
    f1: float
    support: int

    def as_dict(self) -> dict[str, float | int]:
        return {
            "precision": float(self.precision),
            "recall": float(self.recall),
            "f1": float(self.f1),
            "support": int(self.support),
        }

    def row(self, name: str) -> list[str]:
        """[name, P, R, F, support] as strings, one decimal for the percentages."""
        return [
            name,
            f"{self.precision:.1f}",
            f"{self.recall:.1f}",
            f"{self.f1:.1f}",
            str(int(self.support)),
        ]


@dataclass
class Scores:
    """Per-class scores, their macro mean ("overall"), micro accuracy and the confusion matrix."""

    classes: dict[str, ClassScores]
    macro: ClassScores
    accuracy: float  # micro: trace / total, percent
    confusion: np.ndarray  # (C, C) int64, rows = reference, columns = predicted
    names: list[str]
    macro_classes: list[str] = field(default_factory=list)  # the classes averaged in `macro`

    def as_dict(self) -> dict:
        """JSON-ready: plain floats, ints, strings and lists only."""
        return {
            "names": list(self.names),
            "classes": {name: self.classes[name].as_dict() for name in self.names},
            "macro": self.macro.as_dict(),
            "macro_classes": list(self.macro_classes),
            "accuracy": float(self.accuracy),
            "confusion": [[int(v) for v in row] for row in np.asarray(self.confusion)],
        }

    def table_rows(self) -> list[list[str]]:
        """One [name, P, R, F, support] row per class, then an "overall" row (the macro mean)."""
        rows = [self.classes[name].row(name) for name in self.names]
        rows.append(self.macro.row("overall"))
        return rows

    def markdown(self) -> str:
        """The rows of `table_rows` as a Markdown table under `TABLE_HEADER`."""
        lines = [
            "| " + " | ".join(TABLE_HEADER) + " |",
            "|" + "|".join(["---"] + ["---:"] * (len(TABLE_HEADER) - 1)) + "|",
        ]
        lines += ["| " + " | ".join(row) + " |" for row in self.table_rows()]
        return "\n".join(lines)


def confusion_matrix(
    reference: np.ndarray,
    predicted: np.ndarray,
    n_classes: int,
    mask: np.ndarray | None = None,
) -> np.ndarray:
    """(C, C) int64 counts, rows = reference class, columns = predicted class.

    `reference` and `predicted` are (N,) integer labels in [0, n_classes); `mask`, an optional
    (N,) bool array, keeps only the samples where it is True (use it to drop unlabelled points).
    """
    reference = np.asarray(reference)
    predicted = np.asarray(predicted)
    n_classes = int(n_classes)
    if n_classes < 1:
        raise ValueError(f"n_classes must be at least 1, got {n_classes}")
    if reference.ndim != 1 or predicted.shape != reference.shape:
        raise ValueError(
            f"reference and predicted must be (N,) arrays of one length, "
            f"got {reference.shape} and {predicted.shape}"
        )
    for name, labels in (("reference", reference), ("predicted", predicted)):
        if labels.size and not np.issubdtype(labels.dtype, np.integer):
            raise ValueError(f"{name} labels must be integers, got dtype {labels.dtype}")
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != reference.shape:
            raise ValueError(f"mask must have shape {reference.shape}, got {mask.shape}")
        reference = reference[mask]
        predicted = predicted[mask]
    for name, labels in (("reference", reference), ("predicted", predicted)):
        if labels.size and (labels.min() < 0 or labels.max() >= n_classes):
            raise ValueError(
                f"{name} labels must lie in [0, {n_classes}), "
                f"got values from {labels.min()} to {labels.max()}"
            )
    index = reference.astype(np.int64) * n_classes + predicted.astype(np.int64)
    counts = np.bincount(index, minlength=n_classes * n_classes)
    return counts.reshape(n_classes, n_classes).astype(np.int64)


def _ratio(numerator: np.ndarray, denominator: np.ndarray) -> np.ndarray:
    """100 * numerator / denominator, 0 where the denominator is 0."""
    numerator = np.asarray(numerator, dtype=np.float64)
    denominator = np.asarray(denominator, dtype=np.float64)
    out = np.zeros(np.broadcast(numerator, denominator).shape)
    np.divide(100.0 * numerator, denominator, out=out, where=denominator > 0)
    return out


def _f1(precision: np.ndarray, recall: np.ndarray) -> np.ndarray:
    """Harmonic mean of percentages, 0 where both are 0."""
    total = precision + recall
    out = np.zeros(np.shape(total))
    np.divide(2.0 * precision * recall, total, out=out, where=total > 0)
    return out


def scores_from_confusion(
    confusion: np.ndarray,
    names: Iterable[str],
    macro_exclude: Iterable[str] = (),
) -> Scores:
    """Per-class precision / recall / F, their macro mean and the micro accuracy.

    `macro` averages the classes with support > 0 that are not named in `macro_exclude`;
    `macro_exclude=("ground",)` gives the phantom paper's Table I "Overall" (see module doc).
    """
    confusion = np.asarray(confusion)
    names = [str(name) for name in names]
    if confusion.ndim != 2 or confusion.shape[0] != confusion.shape[1]:
        raise ValueError(f"confusion must be a square (C, C) matrix, got shape {confusion.shape}")
    if len(names) != confusion.shape[0]:
        raise ValueError(f"{len(names)} names for a {confusion.shape[0]}-class confusion matrix")
    if len(set(names)) != len(names):
        raise ValueError(f"class names must be unique, got {names}")
    excluded = set(macro_exclude)
    unknown = excluded - set(names)
    if unknown:
        raise ValueError(f"macro_exclude names unknown classes {sorted(unknown)}")
    confusion = confusion.astype(np.int64)

    tp = np.diag(confusion)
    support = confusion.sum(axis=1)
    predicted = confusion.sum(axis=0)
    precision = _ratio(tp, predicted)
    recall = _ratio(tp, support)
    f1 = _f1(precision, recall)
    classes = {
        name: ClassScores(float(precision[i]), float(recall[i]), float(f1[i]), int(support[i]))
        for i, name in enumerate(names)
    }

    keep = (support > 0) & np.array([name not in excluded for name in names], dtype=bool)
    if keep.any():
        macro = ClassScores(
            float(precision[keep].mean()),
            float(recall[keep].mean()),
            float(f1[keep].mean()),
            int(support[keep].sum()),
        )
    else:
        macro = ClassScores(0.0, 0.0, 0.0, 0)
    accuracy = float(_ratio(tp.sum(), confusion.sum()))
    return Scores(
        classes=classes,
        macro=macro,
        accuracy=accuracy,
        confusion=confusion,
        names=names,
        macro_classes=[name for name, k in zip(names, keep, strict=True) if k],
    )


def binary_scores(reference_positive: np.ndarray, predicted_positive: np.ndarray) -> ClassScores:
    """Precision / recall / F of one class against everything else (e.g. phantom, Table II).

    Both inputs are (N,) bool: True where the sample belongs to (is predicted as) the class.
    """
    reference_positive = np.asarray(reference_positive, dtype=bool)
    predicted_positive = np.asarray(predicted_positive, dtype=bool)
    if reference_positive.ndim != 1 or predicted_positive.shape != reference_positive.shape:
        raise ValueError(
            f"reference_positive and predicted_positive must be (N,) arrays of one length, "
            f"got {reference_positive.shape} and {predicted_positive.shape}"
        )
    return binary_from_counts(*binary_counts(reference_positive, predicted_positive))


def binary_counts(reference_positive: np.ndarray, predicted_positive: np.ndarray) -> list[int]:
    """[true positives, reference positives, predicted positives]: additive over parts of a
    sample (tiles of a survey), unlike the scores."""
    return [
        int(np.count_nonzero(reference_positive & predicted_positive)),
        int(np.count_nonzero(reference_positive)),
        int(np.count_nonzero(predicted_positive)),
    ]


def binary_from_counts(tp: int, support: int, n_predicted: int) -> ClassScores:
    """`binary_scores` from counts summed over parts (`binary_counts`)."""
    precision = float(_ratio(tp, n_predicted))
    recall = float(_ratio(tp, support))
    return ClassScores(precision, recall, float(_f1(precision, recall)), int(support))
