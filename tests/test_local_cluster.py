"""The local cluster's workers: settings that cost CPU for what a run never uses are off."""
from pipeline.engine.dask_cluster import local_cluster


def periodic_callbacks(dask_worker) -> list[str]:
    return sorted(dask_worker.periodic_callbacks)


def test_local_workers_run_without_the_statistical_profiler():
    with local_cluster(1, "1GB") as client:
        callbacks = client.run(periodic_callbacks)
    assert callbacks and all("heartbeat" in names and "profile" not in names for names in callbacks.values())


def test_dask_logs_below_an_error_stay_quiet_in_every_named_logger():
    """Dask's config sets some loggers' levels by name (distributed.client at WARNING): the parent's level does
    not reach them, and a "Couldn't gather 1 keys, rescheduling" warning, from a worker dying while the client
    fetched its result, once broke the one-line error of a run whose workers died of memory; a scheduler
    killed mid-run made the client log its failed reconnect at ERROR, with a traceback."""
    import importlib
    import logging
    from pipeline.engine.dask_cluster import quiet_dask_logs
    importlib.import_module("distributed")  # applies Dask's logging config, as a run does
    quiet_dask_logs()
    named = [name for name in logging.root.manager.loggerDict if name.split(".")[0] == "distributed"]
    assert "distributed.client" in named
    loud = {name: logging.getLogger(name).getEffectiveLevel() for name in named}
    assert all(level >= logging.ERROR for level in loud.values()), loud
    assert loud["distributed.client"] > logging.ERROR  # a lost scheduler's reconnect is logged with a traceback
