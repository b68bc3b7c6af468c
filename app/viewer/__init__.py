"""The browser viewer: viser scenes behind the login (pillar labelling; later clutter review,
guardrail review, model inspection, QA).

`server.ViewerServer` runs viser on the loopback interface and is reached only through the
FastAPI relay (`app.api.routes.viewer`); `session.ViewerSession` is one browser tab with its own
scene and GUI; `modes/` holds one module per annotation mode. The viewer reads surveys through
`app.io` and writes labels through `app.store`, never through a pipeline.
"""
