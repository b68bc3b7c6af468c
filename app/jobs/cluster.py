"""Tiles on Dask distributed: the engine that spreads a survey's tiles over processes or hosts.

By default a `LocalCluster` of `settings.workers` processes (one thread each, a memory limit
each) is started on first use and kept for the process's life: nothing to install or start.
With `MMSCLEAN_DASK_SCHEDULER=tcp://host:8786` the tiles go to that cluster instead; its workers
must read the survey's files at the same paths (a shared volume) and run this package.

A pipeline's tiled runner takes a `map_tiles` (`tile_map`): it submits one task per tile and
yields each tile's result as it finishes; a worker lost mid-tile has its tile rescheduled by
Dask.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from typing import Any

from dask.distributed import Client, LocalCluster, as_completed

from app.core.settings import Settings

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
            cluster = LocalCluster(
                n_workers=settings.workers,
                threads_per_worker=1,
                processes=True,
                memory_limit=f"{settings.tile_worker_memory_mb}MiB",
                dashboard_address=None,
                host="127.0.0.1",
            )
            client = Client(cluster)
        _clients[key] = client
        return client


def close_clients() -> None:
    """Close every client and the local clusters this process started."""
    with _lock:
        for client in _clients.values():
            cluster = client.cluster
            client.close()
            if cluster is not None:
                cluster.close()
        _clients.clear()


def tile_map(client: Client) -> Callable[..., Iterator[Any]]:
    """A `map_tiles` for the tiled runners: `fn(spec, index, tile)` for every tile on the
    cluster, results in the order they finish. The tile index travels once per worker."""

    def map_tiles(fn: Callable[..., Any], spec: Any, index: Any, tiles: list[int]):
        shared = client.scatter(index, broadcast=True)
        futures = [client.submit(fn, spec, shared, tile, pure=False) for tile in tiles]
        try:
            for future in as_completed(futures):
                yield future.result()
        finally:
            client.cancel(futures)

    return map_tiles
