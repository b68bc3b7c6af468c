"""Review fixtures: the guardrail jobs' simulated street, one survey and its users (a review
helper answers from what a run left in the store and the job folder)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.jobs.guardrail_street import Jobs, simulate_street


@pytest.fixture(scope="module")
def sim_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return simulate_street(tmp_path_factory.mktemp("guardrail-jobs"))


@pytest.fixture
def jobs(tmp_path: Path, sim_dir: Path) -> Iterator[Jobs]:
    jobs = Jobs(tmp_path, sim_dir)
    yield jobs
    jobs.engine.dispose()
