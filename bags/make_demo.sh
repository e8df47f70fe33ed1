#!/usr/bin/env bash
# Regenerates the demo bag (default: bags/demo; or the directory given): bit-for-bit on this
# machine; on another CPU floats may differ in their last bits (tests/tools/test_demo_bag.py
# compares decoded messages, images exactly, floats to 1e-7 relative):
# a handheld RGB-D + IMU capture (100 frames at 10 Hz, 320x240) of a plain-painted room
# with 32 objects, with ground truth on /ground_truth/*. Colour noise is off to keep the
# bag small; depth has the default sensor noise.
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
out="${1:-$root/bags/demo}"
"$root/ros_ws/env.sh" rfm sim "$out" --seed 11 --style plain --capture handheld \
  --frames 100 --fps 10 --size 320x240 --color-noise 0 --force
