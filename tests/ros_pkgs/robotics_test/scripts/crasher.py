#!/usr/bin/env python3
"""Test node: prints a reason to stderr and exits at once with status 3 (an item that cannot start)."""

import sys

sys.stderr.write("crasher: cannot open /dev/imaginary_lidar: no such device\n")
sys.exit(3)
