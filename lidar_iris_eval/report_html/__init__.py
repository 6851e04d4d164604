"""``liris report``: one offline HTML page per run (see :func:`build_report`)."""

from lidar_iris_eval.report_html.page import INSTALL_HINT, PLOTLY_JS, build_report

__all__ = ["INSTALL_HINT", "PLOTLY_JS", "build_report"]
