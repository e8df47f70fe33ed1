"""Test session set-up: an isolated DDS domain per run, kept on this machine; test helpers."""
import os
import random
import sys
from pathlib import Path

# Helpers shared by the tests (bag playback, bags as users record them) live in tests/tools.
sys.path.insert(0, str(Path(__file__).resolve().parent / 'tools'))

# A random domain per test run, so parallel runs (and other sessions) never cross-talk.
# Set before anything imports rclpy; child processes inherit it.
os.environ['ROS_DOMAIN_ID'] = str(random.SystemRandom().randint(1, 101))
os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
