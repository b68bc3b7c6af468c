"""Synchronous services that the API and the viewer share: they answer a request at once (a
guardrail correction preview, a slice's position, a survey import) from the store, the readers
and a pipeline's saved artifacts, without queueing a job. They may import store, pipelines and
io; never api, viewer or jobs (jobs may call them)."""
