"""A node with one job slot: services that run one long job at a time.

A job is a coroutine on the executor; it hands plain inputs to a worker thread (or a
forked child process) with :meth:`JobNode._offload` and resumes on the executor with
the value, so the node's state is only ever touched on the executor thread. A call
while another job runs answers ``success=False, message='busy: ...'`` at once.
"""
from __future__ import annotations

import threading
from typing import Any, Awaitable, Callable

from rclpy.node import Node
from rclpy.task import Future
from std_srvs.srv import Trigger

from kpi_calib_ros.ros.child_process import run_in_child


class JobNode(Node):
    """A :class:`rclpy.node.Node` whose long work runs as jobs, one at a time."""

    def __init__(self, node_name: str, **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self._job_name = ''  # the running job ('' when idle): one long job at a time

    def _service(self, name: str, doing: str, work: Callable[[], Awaitable[tuple[bool, str]]]
                 ) -> Callable[[Trigger.Request, Trigger.Response], Awaitable[Trigger.Response]]:
        """A Trigger callback that runs job ``work`` and answers when it is done, or
        answers 'busy' at once while another job runs. The executor keeps serving
        meanwhile (the callback awaits, it does not block)."""
        async def callback(request: Trigger.Request,
                           response: Trigger.Response) -> Trigger.Response:
            if not self._claim_job(doing):
                response.success, response.message = False, f'busy: {self._job_name}'
            else:
                response.success, response.message = await self._run_job(name, work)
            return response
        return callback

    def _claim_job(self, doing: str) -> bool:
        """Take the one job slot if it is free. The check and the claim run on the
        executor with no await between them, so no other callback interleaves."""
        if self._job_name:
            return False
        self._job_name = doing
        return True

    async def _run_job(self, name: str,
                       work: Callable[[], Awaitable[tuple[bool, str]]]) -> tuple[bool, str]:
        """Run the claimed job ``work`` to its (success, message); free the slot after."""
        try:
            outcome = await work()
        except Exception as exc:  # job boundary: answer, log, keep the node up
            self.get_logger().error(f'{name} failed: {exc}')
            outcome = (False, f'{name} failed: {exc}')
        else:
            self.get_logger().info(f'{name}: {outcome[1]}')
        finally:
            self._job_name = ''
        return outcome

    def _create_task(self, name: str, work: Callable[[], Awaitable[tuple[bool, str]]]) -> None:
        executor = self.executor
        if executor is None:  # timers fire only under an executor
            raise RuntimeError('kpi_calib_node ticked without an executor')
        executor.create_task(self._run_job, name, work)

    def _offload(self, fn: Callable[..., Any], *args: Any, child: bool = False) -> Future:
        """Run ``fn(*args)`` in a worker thread (``child``: in a forked child process that
        the thread waits for, for pure computations that must not hold the GIL); awaiting
        the returned future resumes the job on the executor with ``fn``'s value (or
        raises its exception)."""
        done = Future(executor=self.executor)
        done.add_done_callback(lambda _: None)  # its scheduling wakes the executor

        def run() -> None:
            try:
                value = run_in_child(fn, *args) if child else fn(*args)
            except Exception as exc:  # handed to the awaiting job, which reports it
                done.set_exception(exc)
            else:
                done.set_result(value)
        threading.Thread(target=run, daemon=True).start()
        return done


__all__ = ['JobNode']
