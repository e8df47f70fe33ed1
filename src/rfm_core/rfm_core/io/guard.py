"""What the nodes do with input that goes wrong: a malformed message is reported and dropped,
an unexpected error in a callback, timer or service is reported and the node lives on, a
service answers ``success=false`` with the reason. No ROS needed: the nodes pass their
callbacks and a reporting function."""
from __future__ import annotations

from typing import Callable

__all__ = ['guarded', 'decoded']


def guarded(callback: Callable, report: Callable[[str, Exception], None]) -> Callable:
    """``callback`` (a subscription's, a timer's or a service's) made safe: an unexpected
    error goes to ``report(name, exc)``; a service call (request, response) answers
    success=false with the error."""
    name = callback.__name__.lstrip('_')

    def run(*args):
        try:
            return callback(*args)
        except Exception as exc:  # noqa: BLE001 - no input may kill a node
            report(name, exc)
            if len(args) == 2 and hasattr(args[1], 'success'):     # a service: (request, response)
                args[1].success, args[1].message = False, f'internal error: {exc!r}'
                return args[1]
            return None
    run.__name__ = callback.__name__
    return run


def decoded(decode: Callable, msg, what: str, dropped: Callable[[str, Exception], None]):
    """``decode(msg)``, or None after ``dropped(what, error)`` when the message is malformed
    (the decoders raise ValueError saying what is wrong)."""
    try:
        return decode(msg)
    except ValueError as exc:
        dropped(what, exc)
        return None
