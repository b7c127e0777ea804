"""Running one scan: preflight checks, the work folder, the phases (bucket, plan, survey, budgets,
simplify, stitch) as tasks on Dask workers or threads of this process, and the runner that calls them in
order. Imports pipeline.io below it, never pipeline.apps above it."""
