"""Test session set-up: an isolated DDS domain per run, kept on this machine."""
import os
import random

# A random domain per test run, so parallel runs (and other sessions) never cross-talk.
# Set before anything imports rclpy; child processes inherit it.
os.environ['ROS_DOMAIN_ID'] = str(random.SystemRandom().randint(1, 101))
os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
