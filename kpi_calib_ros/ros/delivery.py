"""How messages reach the node: QoS profiles, subscription depths, and the count of
messages lost before the node read them."""
from __future__ import annotations

import time
from typing import Any

from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy


def latched(depth: int = 1) -> QoSProfile:
    return QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)


def stream_qos(depth: int) -> QoSProfile:
    return QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE)


# Subscription queues sized in seconds at the highest expected rates: a stall of the
# executor this long (a slow disk, a busy machine) loses nothing. Jobs run in a child
# process (ros/child_process.py), so no job holds the executor back.
JOINT_STATES_MAX_HZ = 1000.0
POINTS_MAX_HZ = 50.0
STREAM_BUFFER_S = 10.0


class MessageSequence:
    """Messages lost before the node read them, from the publication sequence numbers
    DDS gives each message (one publisher per topic; a number that goes back is a new
    publisher, or the same one restarted)."""

    def __init__(self) -> None:
        self.last: int | None = None
        self.lost = 0
        self.max_lag_ns = 0  # publication to callback: how far the executor fell behind

    def see(self, info: dict[str, Any]) -> None:
        sent = info.get('source_timestamp')
        if sent:
            self.max_lag_ns = max(self.max_lag_ns, time.time_ns() - sent)
        number = info.get('publication_sequence_number')
        if not number:  # the middleware does not report them
            return
        if self.last is not None and number > self.last + 1:
            self.lost += number - self.last - 1
        self.last = number


__all__ = ['JOINT_STATES_MAX_HZ', 'POINTS_MAX_HZ', 'STREAM_BUFFER_S', 'MessageSequence',
           'latched', 'stream_qos']
