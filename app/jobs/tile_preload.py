"""Imported by every tile worker as it starts (Dask's preload: the embedded cluster's
`LocalCluster(preload=...)`; on a team's cluster `dask worker --preload app.jobs.tile_preload`):
the pipelines' code, torch and open3d are loaded before a job's first tile arrives, not while
the job waits on it (2-3 s per worker on this machine, a tenth of a short survey's run)."""

import app.pipelines.clutter.tiled  # noqa: F401
import app.pipelines.guardrail.reconstruction  # noqa: F401
import app.pipelines.guardrail.tiled  # noqa: F401
import app.pipelines.phantom.tiled  # noqa: F401
