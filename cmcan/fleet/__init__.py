"""Fleet scale: many machines' logs replayed on Dask into a Parquet data set, queried and reported."""
