"""``python -m lidar_iris_eval`` runs the ``liris`` command line."""

from lidar_iris_eval.cli import main

main()
