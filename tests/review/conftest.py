"""Review fixtures: the guardrail jobs' simulated street with one survey and its users (a
review helper answers from what a run left in the store and the job folder)."""

from tests.jobs.test_guardrail_tasks import jobs, sim_dir  # noqa: F401
