"""What users call: the command line and batch runs, `info`, `eval`, `compare` and `report`, the in-memory
API, and mesh mode (which runs no cluster and imports no Dask). Built on pipeline.engine and pipeline.io."""
