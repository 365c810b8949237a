"""Ray, the optional distributed engine (`pip install .[cluster]`): a session on a new local Ray or an existing
cluster, and a map function that runs independent calls as Ray tasks."""

from __future__ import annotations

import importlib.util
import logging
import os
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import numpy as np

INSTALL_RAY = "more than one worker needs Ray: pip install '.[cluster]' (or pip install ray)"
THREAD_VARIABLES = ("OMP_NUM_THREADS", "NUMBA_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")
SMALL_TYPES = (int, float, str, bool, type(None))  # arguments sent with each task; others go to the object store
CHUNKS_PER_CPU = 4  # tasks per CPU of a ray_map: few enough to amortise a task, enough to balance the load


def ray_available() -> bool:
    """Whether Ray is installed."""
    return importlib.util.find_spec("ray") is not None


@contextmanager
def ray_session(
    workers: int | None, address: str | None = None, threads: int = 0, warm_up: bool = False
) -> Iterator[None]:
    """Ray while the block runs: the cluster at `address` ('auto' as Ray defines it), else a new local Ray with
    `workers` CPUs; an already initialised Ray is used as it is. `threads` > 0: the worker processes start with
    the usual thread-count variables at that value (OpenMP, numba, BLAS read them once). `warm_up`: a task per
    CPU starts at once that loads the solver and Open3D (seconds per worker process), while the caller goes on.

    Raises:
        ValueError: Ray is not installed.
    """
    try:
        import ray
    except ImportError:
        raise ValueError(INSTALL_RAY) from None
    if ray.is_initialized():
        yield
        return
    env = dict.fromkeys(THREAD_VARIABLES, str(threads)) if threads > 0 else {}
    options = {"log_to_driver": False, "logging_level": logging.WARNING, "runtime_env": {"env_vars": env}}
    if address is None:
        ray.init(num_cpus=workers, include_dashboard=False, **options)
    else:
        ray.init(address=address, **options)
    if warm_up:
        task = ray.remote(num_cpus=1)(_load_solver)
        for _ in range(int(ray.cluster_resources().get("CPU", 1))):
            task.remote()
    try:
        yield
    finally:
        ray.shutdown()


def ray_map(function: Callable, arguments: list[tuple], threads: int = 0) -> list:
    """`function(*args)` for every tuple of `arguments` on Ray (inside `ray_session`), the results in order, each
    task limited to `threads` (`threads_limited`; 0: all). The calls go in `CHUNKS_PER_CPU` contiguous chunks per
    CPU of the cluster, one task each: a call is often shorter than what a task costs. Each distinct argument
    object other than a scalar goes to the object store once, and into a task once, however many calls share it."""
    import ray

    shared: dict[int, object] = {}

    def reference(value: object) -> object:
        if isinstance(value, SMALL_TYPES):
            return value
        if id(value) not in shared:
            shared[id(value)] = ray.put(value)
        return shared[id(value)]

    if not arguments:
        return []
    chunks = min(len(arguments), CHUNKS_PER_CPU * max(1, int(ray.cluster_resources().get("CPU", 1))))
    bounds = np.linspace(0, len(arguments), chunks + 1).astype(int)
    task = ray.remote(num_cpus=1, max_retries=0)(_chunk_call)
    refs = [
        task.remote(function, threads, [[reference(value) for value in args] for args in arguments[a:b]])
        for a, b in zip(bounds[:-1], bounds[1:])
    ]
    try:
        return [result for chunk in ray.get(refs) for result in chunk]
    except KeyboardInterrupt:
        for ref in refs:
            ray.cancel(ref, force=True)
        raise


def _load_solver() -> None:
    """Import the solver and Open3D and load the solver's compiled kernels, as a first registration would."""
    from sandro_core import register

    points = np.random.default_rng(0).uniform(size=(100, 3))
    register(points, points + 1.0)


def _chunk_call(function: Callable, threads: int, chunk: list[list[object]]) -> list:
    """`function(*args)` for every argument list of `chunk`, limited to `threads`. Object references among the
    arguments are fetched once each; arrays are copied, since Ray hands them over read-only and some libraries
    (Open3D) take only writable arrays."""
    import ray

    refs = list({id(value): value for args in chunk for value in args if isinstance(value, ray.ObjectRef)}.values())
    fetched = dict(zip(map(id, refs), ray.get(refs))) if refs else {}

    def resolved(value: object) -> object:
        value = fetched.get(id(value), value)
        return np.array(value) if isinstance(value, np.ndarray) else value

    with threads_limited(threads):
        return [function(*[resolved(value) for value in args]) for args in chunk]


@contextmanager
def threads_limited(threads: int) -> Iterator[None]:
    """Open3D, numba and the libraries that read the usual thread-count variables (as do the processes started
    meanwhile, such as the loop-closure worker) limited to `threads` while the block runs; 0: unchanged."""
    if threads <= 0:
        yield
        return
    import numba
    import open3d as o3d

    saved_env = {variable: os.environ.get(variable) for variable in THREAD_VARIABLES}
    saved_numba, saved_open3d = numba.get_num_threads(), o3d.utility.get_max_threads()
    os.environ.update(dict.fromkeys(THREAD_VARIABLES, str(threads)))
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    o3d.utility.set_max_threads(threads)
    try:
        yield
    finally:
        for variable, value in saved_env.items():
            if value is None:
                os.environ.pop(variable, None)
            else:
                os.environ[variable] = value
        numba.set_num_threads(saved_numba)
        o3d.utility.set_max_threads(saved_open3d)
