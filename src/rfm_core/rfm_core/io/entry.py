"""A node process's main: start, spin, stop on Ctrl-C or SIGTERM, whenever it comes.

rclpy's own signal handling is left out (``SignalHandlerOptions.NO``): its handler shuts the
context down from a thread of its own and raises KeyboardInterrupt wherever the main thread
is, so a signal that lands while the node is being built fails the build on a shut-down
context (exit 1), and one that lands as the node starts to spin, on a loaded machine,
could leave the process hung. Here the signal only sets a flag, which the spin loop reads
between callbacks (every ``poll_s`` at most); a second one interrupts at once. No ROS
import: the caller passes its ``rclpy`` (with ``rclpy.executors`` imported).

A node that seems hung tells where: ``kill -USR1 PID`` writes every thread's Python stack to
its standard error (the node's log under ``rfm run``), also while a thread is blocked in C."""
from __future__ import annotations

import faulthandler
import signal
import sys
import threading
from typing import Callable

__all__ = ['run_node']


def run_node(rclpy, make_node: Callable, name: str, args=None, close: Callable | None = None,
             poll_s: float = 0.25) -> None:
    """Build ``make_node()`` and spin it until Ctrl-C or SIGTERM (or the context ends), then
    ``close(node)`` (when given) and destroy it; the signal handlers it found are put back. A
    ValueError from the build (a bad parameter) exits non-zero, saying which."""
    stop = threading.Event()

    def on_signal(signum, frame):
        stop.set()
        signal.signal(signum, signal.default_int_handler)          # a second one interrupts at once

    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    if hasattr(signal, 'SIGUSR1'):
        faulthandler.register(signal.SIGUSR1, file=sys.stderr, all_threads=True)
    rclpy.init(args=args, signal_handler_options=rclpy.signals.SignalHandlerOptions.NO)
    node = None
    try:
        node = make_node()
        executor = rclpy.executors.SingleThreadedExecutor()
        executor.add_node(node)
        while not stop.is_set() and rclpy.ok():
            executor.spin_once(timeout_sec=poll_s)
    except (KeyboardInterrupt, rclpy.executors.ExternalShutdownException):
        pass
    except ValueError as exc:                 # a bad parameter: say which, exit non-zero
        raise SystemExit(f'{name}: {exc}') from None
    finally:
        if node is not None:
            if close is not None:
                close(node)
            node.destroy_node()
        rclpy.try_shutdown()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        if hasattr(signal, 'SIGUSR1'):
            faulthandler.unregister(signal.SIGUSR1)
