"""Run `rfm play` in a subprocess while a test node spins until it finishes."""
import shutil
import subprocess
import threading
import time

from rclpy.executors import SingleThreadedExecutor


def play_bag(node, bag, *args, timeout=60.0, drain=2.0, on_spin=None, delay=3.0) -> float:
    """Play ``bag`` (with extra ``args``) to its end while ``node`` spins in its own thread
    (so its callbacks keep up with best-effort topics), then keep spinning ``drain`` seconds
    for the last messages. The player waits ``delay`` seconds after advertising its topics
    (for subscribers in other processes to discover them). Asserts a clean exit; returns the
    seconds from starting the player to its exit."""
    rfm = shutil.which('rfm')
    assert rfm, 'rfm is not on PATH: run through ros_ws/env.sh'
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    try:
        start = time.monotonic()
        player = subprocess.Popen([rfm, 'play', str(bag), '--delay', str(delay), '--quiet', *args],
                                  stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        while player.poll() is None and time.monotonic() - start < timeout:
            time.sleep(0.02)
            if on_spin is not None:
                on_spin()
        elapsed = time.monotonic() - start
        time.sleep(drain)
    finally:
        executor.shutdown()
        spinner.join(timeout=5)
    if player.poll() is None:
        player.kill()
    out = player.communicate()[0]
    assert player.returncode == 0, out
    return elapsed
