"""Run a node job in a forked child process, so it never holds the node's GIL.

Why: a job in a thread of the node (identification, diagnosis, design) shares the GIL
with the executor. CasADi and NumPy hold it for most of their work, so at 1 kHz joint
states the executor fell behind while a job ran, the subscription queue overflowed and
37 % of the joint states were lost (bench/node_load.py: 11 946 of 32 001 during
automatic re-identification). A child process has its own interpreter: the executor
keeps its core.

Fork, not spawn: the child starts with the job's inputs (robot model, CasADi functions,
measurements) already in memory, copy-on-write, so nothing is pickled on the way in and
nothing is rebuilt. The child only computes and writes result files; it never touches
ROS (the DDS threads of the parent do not exist in it) and leaves with ``os._exit``
so no parent atexit or finaliser runs there; it ends with the node (Linux
``PR_SET_PDEATHSIG``). The value (or the exception) comes back pickled through a pipe.
"""
from __future__ import annotations

import ctypes
import gc
import multiprocessing
import os
import pickle
import signal
import traceback
from multiprocessing.connection import Connection
from typing import Any, Callable

from kpi_calib_ros.core.errors import KpiCalibError


class JobProcessError(KpiCalibError):
    """A job's child process ended without a value (killed, out of memory)."""


def _portable(exc: BaseException) -> BaseException:
    """``exc`` if it survives pickling, else an equivalent that does (ConfigError's
    two-argument constructor does not unpickle)."""
    try:
        pickle.loads(pickle.dumps(exc))
        return exc
    except Exception:
        kind = KpiCalibError if isinstance(exc, KpiCalibError) else RuntimeError
        return kind(str(exc))


def _die_with(parent: int) -> None:
    """Linux: end this child when its parent ends (a killed node leaves no job behind
    to write results later); elsewhere, or if that fails, the child finishes its job."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        return
    if os.getppid() != parent:  # the parent ended before the request took effect
        os._exit(1)


def _child(conn: Connection, fn: Callable[..., Any], args: tuple[Any, ...],
           parent: int) -> None:
    # The child inherits every object of the node, rclpy handles (contexts, nodes,
    # subscriptions) among them. If its garbage collector finalised one of those, the
    # destructor would act on DDS entities whose threads exist only in the parent; it
    # did, and the child died with SIGSEGV now and then. So the child never collects
    # what it inherited: freeze moves those objects out of the collector's reach (the
    # parent froze them just before the fork; this covers what other threads of the
    # parent allocated in between). The job's own objects are collected as usual.
    gc.freeze()
    try:
        _die_with(parent)
        try:
            outcome: tuple[bool, Any] = (True, fn(*args))
        except Exception as exc:  # handed back to the parent, which raises it
            outcome = (False, _portable(exc))
        try:
            conn.send(outcome)
        except Exception as exc:  # the value does not pickle: say so, not hang
            conn.send((False, RuntimeError(f'job result could not be returned: {exc}\n'
                                           f'{traceback.format_exc()}')))
        conn.close()
    finally:
        os._exit(0)


def run_in_child(fn: Callable[..., Any], *args: Any) -> Any:
    """``fn(*args)`` computed in a forked child; returns its value or raises its exception.

    Blocks the calling thread (without holding the GIL) until the child answers; call
    it from a worker thread, never from the executor.
    """
    context = multiprocessing.get_context('fork')
    receive, send = context.Pipe(duplex=False)
    process = context.Process(target=_child, args=(send, fn, args, os.getpid()), daemon=True)
    # Freeze before the fork so that no collection in the child can reach the parent's
    # objects (see _child); unfreeze after it so the parent's collector works as before.
    gc.freeze()
    try:
        process.start()
    finally:
        gc.unfreeze()
    send.close()  # the child holds its end; EOF here once it is gone
    try:
        ok, value = receive.recv()
    except EOFError:
        process.join()
        raise JobProcessError(f'the job process ended without a result (exit code '
                                 f'{process.exitcode})') from None
    finally:
        receive.close()
    process.join()
    if not ok:
        raise value
    return value


__all__ = ['JobProcessError', 'run_in_child']
