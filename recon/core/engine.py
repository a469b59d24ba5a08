"""Where the match stage's pair tasks run: a `concurrent.futures.Executor` chosen by name.

The match stage only submits pure tasks `match_pair_task(store, matcher, name0, name1) ->
PairResult` and waits on their futures (`concurrent.futures.wait`), so any Executor whose
futures are `concurrent.futures.Future`s fits: `threads` is a ThreadPoolExecutor (OpenCV
releases the GIL, so pairs overlap); a Dask cluster plugs in here later as another engine
(`distributed.Client(...).get_executor()`) without touching the stage.
"""

from __future__ import annotations

from concurrent.futures import Executor, ThreadPoolExecutor

from recon.errors import UserError

ENGINES: tuple[str, ...] = ("threads",)


def make_executor(engine: str, workers: int) -> Executor:
    """The executor for `engine` with `workers` parallel tasks (at least 1)."""
    if engine == "threads":
        return ThreadPoolExecutor(max_workers=max(1, int(workers)), thread_name_prefix="recon-pair")
    raise UserError(f"--engine {engine!r}: choose one of {', '.join(ENGINES)}")
