#!/usr/bin/env python
"""KITTI-scale speed and memory of every descriptor: the same as ``liris bench``.

Usage::

    .venv/bin/python scripts/bench.py                       # 4541 simulated frames, all four
    .venv/bin/python scripts/bench.py --frames 1000 -d lidar-iris --json -
    .venv/bin/python scripts/bench.py --sequence /data/kitti/sequences/00 --json out.json

Every option is the command's (``--help`` lists them); the measurements are
made by :mod:`lidar_iris_eval.bench`. This wrapper only exists for people who
prefer running scripts to installed commands.
"""

from __future__ import annotations

import sys

from lidar_iris_eval.cli import main

if __name__ == "__main__":
    main(["bench", *sys.argv[1:]])
