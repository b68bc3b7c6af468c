"""Synchronous review helpers that the API and the viewer share: they answer a reviewer's
question (a preview, a position) at once, from the store and a pipeline's saved artifacts,
without queueing a job. Review helpers may import store, pipelines and io; never api, viewer
or jobs."""
