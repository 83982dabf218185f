"""SIGINT and SIGTERM stop a node between two callbacks, never inside rclpy.

The Jazzy idiom (``rclpy.init()`` with rclpy's signal handlers, ``rclpy.spin`` and
``except KeyboardInterrupt``) lets Python's SIGINT handler raise KeyboardInterrupt at
whatever bytecode the main thread runs next. While rclpy takes a message, that is the
message class's constructor or a field setter, which rclpy's C code calls to build the
Python message: the exception makes the conversion fail, pybind11 replaces it with
``RuntimeError: Unable to convert call argument '0' to Python object`` and the node
ended with exit code 1 and a traceback instead of stopping: 8 of 12 stops while
another process flooded ``~/tcp_query`` with 35 000-name queries
(``test_ros_node_stop.py``), and rarely in ROS tests that stop the node right after a
query.

Here a signal only records the request; the spin loop polls it every
:data:`POLL_S` and ends with the context still valid. A second signal ends the process
at once (its default action), as a user pressing Ctrl-C twice or a launch file
escalating to SIGTERM expects.
"""
from __future__ import annotations

import signal
from types import FrameType

POLL_S = 0.1  # the longest a stop request waits for an idle executor to notice it
SIGNALS = (signal.SIGINT, signal.SIGTERM)


class StopRequest:
    """Handlers for :data:`SIGNALS` that record a stop request (main thread only).

    Install before ``rclpy.init(signal_handler_options=SignalHandlerOptions.NO)``: a
    signal during start-up is then a request too, and rclpy installs no handler of its
    own.
    """

    def __init__(self) -> None:
        self.signal: int | None = None
        for signum in SIGNALS:
            signal.signal(signum, self._record)

    @property
    def requested(self) -> bool:
        return self.signal is not None

    def _record(self, signum: int, frame: FrameType | None) -> None:
        if self.signal is None:
            self.signal = signum
            return
        # Asked again: the signal's default action, now. Only this signal's handler is
        # changed, here: a handler changed while its signal is pending makes Python raise
        # "OSError: Signal ... ignored due to race condition" wherever it runs next.
        signal.signal(signum, signal.SIG_DFL)
        signal.raise_signal(signum)


__all__ = ['POLL_S', 'StopRequest']
