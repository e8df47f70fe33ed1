"""What the nodes do with input that goes wrong: a malformed message is reported and dropped,
an unexpected error in a callback, timer or service is reported and the node lives on, a
service answers ``success=false`` with the reason. No ROS needed: the nodes pass their
callbacks and a reporting function, or take :class:`GuardedCallbacks` as a mixin."""
from __future__ import annotations

import functools
from typing import Callable

from rfm_core.processes import limit_blas_threads

__all__ = ['guarded', 'decoded', 'GuardedCallbacks']


def guarded(callback: Callable, report: Callable[[str, Exception], None]) -> Callable:
    """``callback`` (a subscription's, a timer's or a service's) made safe: an unexpected
    error goes to ``report(name, exc)``; a service call (request, response) answers
    success=false with the error."""
    name = getattr(callback, '__name__', 'callback').lstrip('_')

    @functools.wraps(callback)             # (its signature: rclpy passes message info by it)
    def run(*args):
        try:
            return callback(*args)
        except Exception as exc:  # noqa: BLE001 - no input may kill a node
            report(name, exc)
            if len(args) == 2 and hasattr(args[1], 'success'):     # a service: (request, response)
                args[1].success, args[1].message = False, f'internal error: {exc!r}'
                return args[1]
            return None
    return run


class GuardedCallbacks:
    """A mixin for a node (``class N(GuardedCallbacks, Node)``): every subscription, timer and
    service it creates runs :func:`guarded`; an unexpected error is counted
    (``unexpected_errors``, for the node's diagnostics or status), logged (throttled) and
    the node goes on. A node that reports elsewhere too overrides :meth:`callback_failed`.
    Its process's math libraries run on one thread (:func:`~rfm_core.processes.limit_blas_threads`)."""

    unexpected_errors = 0

    def __init__(self, *args, **kwargs):
        limit_blas_threads()
        super().__init__(*args, **kwargs)

    def create_subscription(self, msg_type, topic, callback, *args, **kwargs):
        return super().create_subscription(msg_type, topic, guarded(callback, self.callback_failed), *args, **kwargs)

    def create_timer(self, period, callback, *args, **kwargs):
        return super().create_timer(period, guarded(callback, self.callback_failed), *args, **kwargs)

    def create_service(self, srv_type, name, callback, *args, **kwargs):
        return super().create_service(srv_type, name, guarded(callback, self.callback_failed), *args, **kwargs)

    def callback_failed(self, name: str, exc: Exception) -> None:
        self.unexpected_errors += 1
        self.get_logger().error(f'{name}: unexpected error {exc!r} (dropped; the node goes on)',
                                throttle_duration_sec=5.0)


def decoded(decode: Callable, msg, what: str, dropped: Callable[[str, Exception], None]):
    """``decode(msg)``, or None after ``dropped(what, error)`` when the message is malformed
    (the decoders raise ValueError saying what is wrong)."""
    try:
        return decode(msg)
    except ValueError as exc:
        dropped(what, exc)
        return None
