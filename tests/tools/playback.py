"""Run `rfm play` in a subprocess while spinning a test node until it finishes."""
import shutil
import subprocess
import time

import rclpy


def play_bag(node, bag, *args, timeout=60.0, drain=2.0, on_spin=None) -> float:
    """Play ``bag`` (with extra ``args``) to its end while spinning ``node``, then keep
    spinning ``drain`` seconds for the last messages. Asserts a clean exit; returns the
    seconds from starting the player to its exit."""
    rfm = shutil.which('rfm')
    assert rfm, 'rfm is not on PATH: run through ros_ws/env.sh'
    start = time.monotonic()
    player = subprocess.Popen([rfm, 'play', str(bag), '--delay', '3', '--quiet', *args],
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    while player.poll() is None and time.monotonic() - start < timeout:
        rclpy.spin_once(node, timeout_sec=0.02)
        if on_spin is not None:
            on_spin()
    elapsed = time.monotonic() - start
    end = time.monotonic() + drain
    while time.monotonic() < end:
        rclpy.spin_once(node, timeout_sec=0.02)
    if player.poll() is None:
        player.kill()
    out = player.communicate()[0]
    assert player.returncode == 0, out
    return elapsed
