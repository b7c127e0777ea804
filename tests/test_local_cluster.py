"""The local cluster's workers: settings that cost CPU for what a run never uses are off."""
from pipeline.engine.dask_cluster import local_cluster


def periodic_callbacks(dask_worker) -> list[str]:
    return sorted(dask_worker.periodic_callbacks)


def test_local_workers_run_without_the_statistical_profiler():
    with local_cluster(1, "1GB") as client:
        callbacks = client.run(periodic_callbacks)
    assert callbacks and all("heartbeat" in names and "profile" not in names for names in callbacks.values())
