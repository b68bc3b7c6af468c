"""The FastAPI app: one router per resource; reaches pipelines only through `app.jobs`."""
