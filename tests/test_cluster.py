"""pis3r.cluster: one dask client helper for batch and eval."""

import pytest

from pis3r.cluster import dask_client
from pis3r.errors import InputError


def test_an_unreachable_scheduler_is_one_input_error_line():
    with pytest.raises(InputError, match="cannot reach the dask scheduler at tcp://127.0.0.1:1") as raised:
        with dask_client(scheduler="tcp://127.0.0.1:1", connect_timeout_s=1):
            pass
    assert "\n" not in str(raised.value)


@pytest.mark.slow
def test_local_cluster_runs_tasks_in_worker_processes_and_is_closed_after():
    import os

    with dask_client(workers=1) as client:
        cluster = client.cluster
        assert client.submit(os.getpid).result() != os.getpid()
        assert all(w["nthreads"] == 1 for w in client.scheduler_info()["workers"].values())
        assert all(w["host"] == "127.0.0.1" for w in client.scheduler_info()["workers"].values())
    assert client.status == "closed" and cluster.status.name == "closed"
