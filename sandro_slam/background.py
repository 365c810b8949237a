"""Loop closure beside the odometry: a LoopClosureModule in a worker process at the lowest CPU priority.

Python runs one thread at a time, and KISS-ICP, Open3D and MapClosures hold that lock while they work: loop
closure in a thread adds its whole time to the odometry's. A process does not share the lock. At the lowest
priority (Linux SCHED_IDLE) it runs only on the cycles the odometry leaves idle between and within its frames
(docs/back-end.md has the measurements).

The worker runs the module's own code on the same keyframes in the same order, so what `finish` returns is what
the module would hold after the same `add_keyframe` and `optimize` calls in this process.
"""

from __future__ import annotations

import os
import pickle
import queue
import subprocess
import sys
import threading
import time
from typing import BinaryIO

import numpy as np

from sandro_slam.module import LoopClosureModule

_WORKER = [sys.executable, "-c", "from sandro_slam.background import worker_main; worker_main()"]


class BackgroundLoopClosure:
    """Queues `add_keyframe` calls for a LoopClosureModule that lives in a worker process.

    Keyframes go to the worker from a sender thread, so `add_keyframe` returns at once; `finish` waits for
    the worker to work through them and to optimise, and returns the module. Use it as a context manager, or
    call `close` when something fails before `finish`, so that the worker does not outlive the caller.
    """

    def __init__(self, module: LoopClosureModule):
        # Its own session: a Ctrl-C at the terminal reaches only the caller, who decides what stops.
        self._process = subprocess.Popen(
            _WORKER, stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=worker_environment(), start_new_session=True
        )
        self._outbox: queue.SimpleQueue = queue.SimpleQueue()
        self._send_error: OSError | None = None
        self._sender = threading.Thread(target=self._send, name="loop-closure sender", daemon=True)
        self._sender.start()
        self._outbox.put(module)

    def add_keyframe(self, key: int, T_world_keyframe: np.ndarray, points: np.ndarray) -> None:
        """Queue `LoopClosureModule.add_keyframe(key, T_world_keyframe, points)`; returns at once."""
        self._outbox.put((key, T_world_keyframe, points))

    def finish(self) -> tuple[LoopClosureModule, dict[int, np.ndarray], float]:
        """Wait until the worker has added every queued keyframe and run `optimize()`. Returns the module, the
        optimised T_world_keyframe per key and the worker's CPU time [s]. Re-raises the worker's exception."""
        self._outbox.put(None)
        try:
            reply = pickle.load(self._process.stdout)
        except EOFError:
            reply = None
        self._sender.join()
        code = self._process.wait()
        self.close()
        if reply is None:
            detail = f" ({self._send_error})" if self._send_error else ""
            raise RuntimeError(f"the loop-closure worker process ended with exit code {code}{detail}")
        if isinstance(reply, BaseException):
            raise reply
        return reply

    def close(self) -> None:
        """Stop the worker if it still runs, and close the pipes."""
        self._outbox.put(None)  # lets the sender thread end
        if self._process.poll() is None:
            self._process.kill()
            self._process.wait()
        for stream in (self._process.stdin, self._process.stdout):
            try:
                stream.close()
            except OSError:  # the sender may be writing into the pipe of the worker just killed
                pass

    def __enter__(self) -> BackgroundLoopClosure:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def _send(self) -> None:
        stream = self._process.stdin
        try:
            while True:
                item = self._outbox.get()
                pickle.dump(item, stream, protocol=pickle.HIGHEST_PROTOCOL)
                stream.flush()
                if item is None:
                    return
        except (OSError, ValueError) as error:  # the worker ended (its exception comes as the reply) or was closed
            self._send_error = error


def worker_main() -> None:
    """The worker process: `serve` on stdin and on the stdout it started with, at the lowest CPU priority. What
    else writes to stdout goes to stderr, so that only replies reach the pipe."""
    replies = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    _lowest_priority()
    serve(sys.stdin.buffer, replies)
    # The reply is out: the interpreter's teardown of Open3D, gtsam and numba would keep `finish` waiting 0.3 s.
    os._exit(0)


def serve(commands: BinaryIO, replies: BinaryIO) -> None:
    """Unpickle a LoopClosureModule from `commands`, then keyframes for its `add_keyframe` until None; optimise
    and pickle (module, poses, CPU seconds) to `replies`, or the exception that stopped it."""
    start = time.process_time()
    try:
        module = pickle.load(commands)
        while (keyframe := pickle.load(commands)) is not None:
            module.add_keyframe(*keyframe)
        poses = module.optimize()
        reply = (module, poses, time.process_time() - start)
    except Exception as error:  # noqa: BLE001 - every failure goes back to the caller, who raises it
        reply = error if _pickles(error) else RuntimeError(f"{type(error).__name__}: {error}")
    try:
        pickle.dump(reply, replies, protocol=pickle.HIGHEST_PROTOCOL)
        replies.flush()
    except BrokenPipeError:  # the caller is gone
        pass


def _lowest_priority() -> None:
    """Every thread of this process to SCHED_IDLE (Linux; threads started later inherit it): it runs only on
    cores that would otherwise idle. Elsewhere nice 19."""
    try:
        for thread in os.listdir("/proc/self/task"):
            os.sched_setscheduler(int(thread), os.SCHED_IDLE, os.sched_param(0))
        return
    except (AttributeError, OSError):
        pass
    if hasattr(os, "nice"):
        os.nice(19)


def worker_environment() -> dict[str, str]:
    """This process's environment, with PYTHONPATH set to its import path: the worker imports sandro_slam from
    where the caller did, also when the caller added that place to sys.path at run time."""
    return {**os.environ, "PYTHONPATH": os.pathsep.join(path for path in sys.path if path)}


def usable_cores() -> int:
    """Cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def _pickles(error: BaseException) -> bool:
    try:
        pickle.loads(pickle.dumps(error))
    except Exception:  # noqa: BLE001
        return False
    return True
