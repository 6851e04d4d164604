"""Evaluation plans (``liris eval --plan``); the executors are :mod:`lidar_iris_eval.executor`.

``check_scheduler`` and ``use_scheduler`` stay importable from here for
scripts written against the previous layout.
"""

from __future__ import annotations

from lidar_iris_eval.executor import (
    ONE_THREAD_ENV,
    SCHEDULERS,
    DaskExecutor,
    check_scheduler,
)
from lidar_iris_eval.executor import open_executor as use_scheduler

__all__ = ["ONE_THREAD_ENV", "SCHEDULERS", "DaskExecutor", "check_scheduler", "use_scheduler"]
