"""The Dask cluster that fleets of identifications and `quadsr campaign` run on: a local cluster of worker
processes by default, or an existing scheduler's address (many machines; see README.md, "Campaigns")."""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator
from typing import Any

from bridge.errors import UserError


@contextlib.contextmanager
def dask_client(workers: int | None, scheduler: str | None) -> Iterator[Any]:
    """A Dask client: on `scheduler` (an address) if given, else on a new local cluster of `workers`."""
    try:
        from dask.distributed import Client, LocalCluster
    except ImportError as exc:  # pragma: no cover - dask is a dependency
        raise UserError(f"Dask distributed is not installed ({exc})",
                        hint="pip install 'dask[distributed]'") from None
    logging.getLogger("distributed").setLevel(logging.ERROR)
    if scheduler:
        try:
            client = Client(scheduler, timeout="20s")
        except OSError as exc:
            raise UserError(f"cannot reach the Dask scheduler at {scheduler} ({exc})",
                            hint="start it with `dask scheduler` and workers with `dask worker ADDRESS`, "
                                 "or drop --scheduler for a local cluster") from None
        try:
            yield client
        finally:
            client.close()
        return
    n = workers or 2
    if n < 1:
        raise UserError(f"--workers must be >= 1, got {n}")
    cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None,
                           silence_logs=logging.ERROR)
    client = Client(cluster)
    try:
        yield client
    finally:
        client.close()
        cluster.close()


