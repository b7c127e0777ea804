"""Files in and out: LAS/LAZ/COPC and PLY read in chunks with their header checks, the scan they make, CRS
and units, the LAS/LAZ, COPC and zarr writers with provenance, and the rules on where an output may go.
Imports only the foundation (pipeline.errors, config, progress), tiling and model."""
