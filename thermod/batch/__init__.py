"""Batches of recordings for `thermod deblur`: the per-file job and the engines that run it.

- `job`: one recording in, one deblurred recording out (`Job` → `run_job` → `Outcome`); plain data,
  so it runs unchanged in this process or on a cluster worker, and writes the same bytes.
- `local`: the default executor, the files one after another in this process.
- `cluster`: the Dask distributed executor (`--scheduler tcp://HOST:8786`), one task per file,
  outputs written by the workers on a filesystem they share with this machine.
- `progress`: per-file events (started, done with frames and seconds, failed naming the file).

Only `cluster` imports dask, and only when a scheduler is given.
"""
