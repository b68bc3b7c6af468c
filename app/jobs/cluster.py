"""Tiles on Dask distributed: the engine that spreads a survey's tiles over processes or hosts.

Embedded by default: a `LocalCluster` of `settings.workers` processes (one thread each,
`tile_worker_memory_mb` each, bound to loopback). The server's worker pool starts one with its
job workers, for the first queued job, and hands its address to them (`embedded_cluster`), so
the jobs of a server share one set of tile workers; the command line starts one on first use. With
`MMSCLEAN_DASK_SCHEDULER=tcp://host:8786` the tiles go to that cluster instead; its workers must
read the survey's files and write the job folders at the same paths (a shared volume) and run
this package.

A pipeline's tiled runner takes a `map_tiles` (`tile_map`): it connects on the first call (a
survey of one tile runs in the job's own process and never does), submits one task per tile and
yields each tile's result as it finishes; a worker lost mid-tile has its tile rescheduled by
Dask.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Iterator
from typing import Any

from dask.distributed import Client, LocalCluster, as_completed

from app.core.settings import Settings
from app.jobs.registry import JobContext

TILES_PROGRESS = (0.02, 0.85)  # the share of a job's bar its tiles fill
PRELOAD = "app.jobs.tile_preload"  # what a tile worker imports as it starts

_lock = threading.Lock()
_clients: dict[tuple, Client] = {}


def tile_client(settings: Settings) -> Client:
    """The process's client: to the configured scheduler, else to a local cluster."""
    key = (settings.dask_scheduler, settings.workers, settings.tile_worker_memory_mb)
    with _lock:
        client = _clients.get(key)
        if client is not None and client.status == "running":
            return client
        if settings.dask_scheduler:
            client = Client(settings.dask_scheduler, timeout="10s")
        else:
            client = Client(embedded_cluster(settings))
        _clients[key] = client
        return client


def embedded_cluster(settings: Settings) -> LocalCluster:
    """A local cluster of `settings.workers` tile worker processes, each importing the
    pipelines as it starts (`tile_preload`)."""
    return _in_own_thread(
        lambda: LocalCluster(
            n_workers=settings.workers,
            threads_per_worker=1,
            processes=True,
            memory_limit=f"{settings.tile_worker_memory_mb}MiB",
            dashboard_address="127.0.0.1:0",  # loopback only: an admin tunnels to it
            host="127.0.0.1",
            preload=[PRELOAD],
        )
    )


def close_cluster(cluster: LocalCluster) -> None:
    _in_own_thread(cluster.close)


def _in_own_thread(fn: Callable[[], Any]) -> Any:
    """fn() on a thread of its own: the server starts and stops its cluster from inside its
    event loop, where Dask's synchronous calls refuse to run."""
    outcome: list[Any] = []
    failed: list[BaseException] = []

    def call() -> None:
        try:
            outcome.append(fn())
        except BaseException as exc:  # handed to the caller's thread
            failed.append(exc)

    thread = threading.Thread(target=call, name="mmsclean-tile-cluster")
    thread.start()
    thread.join()
    if failed:
        raise failed[0]
    return outcome[0]


def close_clients() -> None:
    """Close every client and the local clusters this process started."""
    with _lock:
        for client in _clients.values():
            cluster = client.cluster
            client.close()
            if cluster is not None:
                cluster.close()
        _clients.clear()


def shared_threads(settings: Settings) -> int:
    """Threads a tile may use when the local tile workers share this machine's cores."""
    return max(1, (os.cpu_count() or 1) // max(settings.workers, 1))


def tile_map(settings: Settings) -> Callable[..., Iterator[Any]]:
    """A `map_tiles` for the tiled runners: `fn(spec, index, tile)` for every tile on the
    settings' cluster (`tile_client`, connected on the first call), results in the order they
    finish. The tile index (a few MB) is sent once, as a task of its own that returns it and
    that every tile task reads: a copy in each of a long survey's thousand tasks had the
    submitting process serialise gigabytes. Not scattered: scattered data is lost with the
    workers holding it, while a task's result is computed again by the scheduler."""

    def map_tiles(fn: Callable[..., Any], spec: Any, index: Any, tiles: list[int]):
        client = tile_client(settings)
        shared = client.submit(_the, index, pure=False)
        client.replicate([shared])  # on every worker: else the tiles queue where it was made
        futures = [client.submit(fn, spec, shared, tile, pure=False) for tile in tiles]
        try:
            for future in as_completed(futures):
                yield future.result()
        finally:
            client.cancel([*futures, shared])

    map_tiles.workers = settings.workers  # type: ignore[attr-defined]  # tiling.tile_workers
    return map_tiles


def _the(index: Any) -> Any:
    """The tile index as a task's result (`tile_map`)."""
    return index


def tile_progress(context: JobContext):
    """The tiled run's `progress(message, fraction of the tiles)` as the job's fraction."""
    start, end = TILES_PROGRESS

    def progress(message: str, fraction: float) -> None:
        context.progress(start + (end - start) * fraction, message)

    return progress


def log_tiles(context: JobContext, tiles: dict) -> None:
    """A tiled job's log line: its tiles (a report's "tiles"), run and kept."""
    context.log.info(
        "%d tiles of %.0f m: %d run, %d kept from an earlier attempt",
        tiles["count"], tiles["length_m"], tiles["run"], tiles["kept_from_earlier_attempt"],
    )  # fmt: skip
