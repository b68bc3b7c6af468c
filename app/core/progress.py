"""How long work reports on itself: one progress callback type and one stopwatch for every
pipeline, so a job, the command line's progress bar and a benchmark read them the same way."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

# (stage name, fraction of the whole run done, 0..1): what pipelines call as they go
Progress = Callable[[str, float], None]


def no_progress(stage: str, fraction: float) -> None:
    """The callback of a run nobody watches."""


class Stopwatch:
    """Seconds per stage, summed over repeats (e.g. per frame): `with clock("stage"): ...`."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}

    @contextmanager
    def __call__(self, stage: str) -> Iterator[None]:
        started = time.perf_counter()
        try:
            yield
        finally:
            elapsed = time.perf_counter() - started
            self.seconds[stage] = self.seconds.get(stage, 0.0) + elapsed

    def rounded(self) -> dict[str, float]:
        """Milliseconds are enough for a report."""
        return {k: round(v, 3) for k, v in self.seconds.items()}
