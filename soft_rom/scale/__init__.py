"""Fitting at scale: POD, projection and fits streamed from disk, locally or on Dask."""
