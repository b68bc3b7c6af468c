"""Review fixtures: the guardrail jobs' simulated street, one survey and its users (a review
helper answers from what a run left in the store and the job folder)."""

from __future__ import annotations

from tests.jobs.guardrail_street import jobs, sim_dir  # noqa: F401  (the fixtures)
