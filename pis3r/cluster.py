"""The one dask.distributed set-up of pis3r (``pis3r batch``, ``pis3r eval``)."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING

from pis3r.errors import InputError, one_line

if TYPE_CHECKING:
    from distributed import Client

# Seconds to wait for an existing scheduler before saying it cannot be reached.
CONNECT_TIMEOUT_S = 20.0


@contextmanager
def dask_client(workers: int = 1, scheduler: str | None = None,
                connect_timeout_s: float = CONNECT_TIMEOUT_S) -> Iterator[Client]:
    """A dask client for the ``with`` block: connected to ``scheduler`` (e.g.
    ``tcp://10.0.0.5:8786``) when given, else to a fresh local cluster of ``workers``
    processes with one thread each, on 127.0.0.1, without dashboard. Client and local
    cluster are closed on leaving the block. A scheduler not reached within
    ``connect_timeout_s`` is an :class:`InputError` of one line."""
    from distributed import Client, LocalCluster

    cluster = None
    if scheduler:
        try:
            client = Client(scheduler, timeout=f"{connect_timeout_s}s")
        except OSError as exc:
            raise InputError(f"cannot reach the dask scheduler at {scheduler}: {one_line(exc)}") from None
    else:
        cluster = LocalCluster(
            n_workers=workers, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address=None,
            silence_logs=logging.ERROR,  # progress bars say what happens; worker chatter does not
        )
        client = Client(cluster)
    try:
        yield client
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
