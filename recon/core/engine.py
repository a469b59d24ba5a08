"""Where the match stage's pair tasks run: a `concurrent.futures.Executor` chosen by name.

* `threads` (default): a ThreadPoolExecutor of `--workers` threads (OpenCV releases the GIL, so
  pairs overlap). Tasks are `match_pair_task(store, matcher, a, b)` over the run's shared store.
* `dask`: a Dask `LocalCluster` of `--workers` single-thread worker processes on this machine;
  `dask:ADDRESS` (e.g. `dask:tcp://HOST:8786`): an existing Dask scheduler and its workers
  (`recon.core.dask_engine`). Tasks are `match_pair_on_worker(PairTaskSpec)`: each worker builds
  its own matcher and opens the feature store over the shared cache folder; only the driver
  writes the pair cache and the database. A task whose worker dies is retried on another.

The stage only submits and waits on `concurrent.futures.Future`s, so both fit the same loop.
"""

from __future__ import annotations

from concurrent.futures import Executor, Future, ThreadPoolExecutor
from typing import Any

from recon.errors import UserError

ENGINES: tuple[str, ...] = ("threads", "dask", "dask:ADDRESS")


def check_engine(engine: str) -> None:
    """UserError (one line) unless `engine` is threads, dask or dask:ADDRESS."""
    if engine == "threads":
        return
    from recon.core.dask_engine import parse_dask_engine

    try:
        parse_dask_engine(engine)
    except ValueError as e:
        raise UserError(f"{e}; choose one of {', '.join(ENGINES)}") from None


class DaskExecutor(Executor):
    """A Dask client's executor whose `shutdown` also closes the client (and its LocalCluster)."""

    distributed = True

    def __init__(self, engine: Any):
        self.engine = engine

    @property
    def dashboard_link(self) -> str | None:
        return self.engine.dashboard_link

    def submit(self, fn: Any, /, *args: Any, **kwargs: Any) -> Future:
        return self.engine.executor.submit(fn, *args, **kwargs)

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        self.engine.close()


def make_executor(engine: str, workers: int) -> Executor:
    """The executor for `engine` with `workers` parallel tasks (at least 1)."""
    check_engine(engine)
    if engine == "threads":
        return ThreadPoolExecutor(max_workers=max(1, int(workers)), thread_name_prefix="recon-pair")
    from recon.core.dask_engine import make_dask_executor, parse_dask_engine

    try:
        return DaskExecutor(make_dask_executor(parse_dask_engine(engine), workers))
    except (OSError, TimeoutError) as e:
        raise UserError(f"--engine {engine}: cannot reach the Dask scheduler ({e})") from None
