"""Subscriptions no executor wakes up for: their messages queue (the QoS depth) until
:func:`take_all` takes them, in one batch.

rclpy's executors rebuild their wait set in Python on every wake-up (about 1 ms on a 2-core
machine): a 200-400 Hz IMU that woke the detector's executor for every sample cost a quarter
of a core before any detection on a 2-core machine. The detector takes its IMU this
way and ``rfm run``'s recorder its output topics.
"""
from __future__ import annotations

from rclpy.callback_groups import CallbackGroup
from rclpy.exceptions import InvalidHandle

__all__ = ['PolledGroup', 'take_all']


class PolledGroup(CallbackGroup):
    """A callback group that no executor waits on: a subscription created in it is taken
    from with :func:`take_all` only."""

    def can_execute(self, entity) -> bool:
        return False

    def beginning_execution(self, entity) -> bool:
        return False

    def ending_execution(self, entity) -> None:
        pass


def take_all(subscription, callback) -> int:
    """Pass every message waiting on ``subscription`` to ``callback``, oldest first; the
    number taken."""
    taken = 0
    try:
        with subscription.handle:
            while (found := subscription.handle.take_message(subscription.msg_type, subscription.raw)) is not None:
                callback(found[0])
                taken += 1
    except InvalidHandle:                     # destroyed (shutting down)
        pass
    return taken
