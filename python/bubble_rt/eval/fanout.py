"""Fan-out of picklable tasks over local processes or a Dask cluster."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, TypeVar

T = TypeVar("T")
R = TypeVar("R")


# ---------------------------------------------------------------------------------- fan-out
class FanOut:
    """Maps picklable functions over tasks: inline, on a process pool, or on a Dask cluster.

    ``workers <= 1`` and no scheduler runs inline (no pickling). Given ``scheduler`` (a Dask
    scheduler address, e.g. ``tcp://host:8786`` or a LocalCluster's address) the same tasks run
    on that cluster. The pool / client lives until :meth:`close` (use as a context manager), so
    repeated maps (an optimiser's loss evaluations) reuse warm workers and their caches.
    """

    def __init__(self, workers: int = 1, scheduler: str | None = None) -> None:
        self.workers = max(1, int(workers))
        self.scheduler = scheduler or None
        self._pool: Any = None
        self._client: Any = None
        if self.scheduler:
            from dask.distributed import Client

            self._client = Client(self.scheduler, set_as_default=False)
        elif self.workers > 1:
            import multiprocessing as mp
            from concurrent.futures import ProcessPoolExecutor

            # fork keeps start-up cheap; workers build their own estimators (C++ state is
            # never shared across the fork because nothing heavy is built before it).
            methods = mp.get_all_start_methods()
            ctx = mp.get_context("fork") if "fork" in methods else None
            self._pool = ProcessPoolExecutor(max_workers=self.workers, mp_context=ctx)

    @property
    def parallelism(self) -> int:
        if self._client is not None:
            info = self._client.scheduler_info()
            return max(1, sum(w.get("nthreads", 1) for w in info.get("workers", {}).values()))
        return self.workers

    def map(
        self,
        fn: Callable[[T], R],
        tasks: Sequence[T],
        *,
        progress: bool = False,
        desc: str = "tasks",
    ) -> list[R]:
        """``[fn(t) for t in tasks]`` in order."""
        tasks = list(tasks)
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=len(tasks), desc=desc, unit="task", leave=False)
        try:
            out: dict[int, R] = {}
            if self._client is not None:
                futures = self._client.map(fn, tasks, pure=False)
                # Collected in submission order: the cluster still runs them concurrently.
                for i, fut in enumerate(futures):
                    out[i] = fut.result()
                    if bar is not None:
                        bar.update(1)
            elif self._pool is not None and len(tasks) > 1:
                from concurrent.futures import as_completed as cf_completed

                fmap = {self._pool.submit(fn, t): i for i, t in enumerate(tasks)}
                for fut in cf_completed(fmap):
                    out[fmap[fut]] = fut.result()
                    if bar is not None:
                        bar.update(1)
            else:
                for i, t in enumerate(tasks):
                    out[i] = fn(t)
                    if bar is not None:
                        bar.update(1)
            return [out[i] for i in range(len(tasks))]
        finally:
            if bar is not None:
                bar.close()

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
        if self._client is not None:
            self._client.close()
            self._client = None

    def __enter__(self) -> FanOut:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def run_tasks(
    fn: Callable[[T], R],
    tasks: Sequence[T],
    *,
    workers: int = 1,
    scheduler: str | None = None,
    progress: bool = False,
    desc: str = "tasks",
) -> list[R]:
    """One-shot :class:`FanOut` map: ``[fn(t) for t in tasks]`` in order."""
    with FanOut(workers=min(workers, max(1, len(tasks))), scheduler=scheduler) as fan:
        return fan.map(fn, tasks, progress=progress, desc=desc)
