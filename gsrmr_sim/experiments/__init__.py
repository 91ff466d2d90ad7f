"""Paper Section V experiments on our data (``gsrmr-experiments``); pure, no rclpy. See docs/experiments.md.

Modules: ``data`` (the scene data, cached), ``composite`` (MR images composited under a schedule), ``paper``
(Fig. 4a/4b, Table 1, Fig. 5a/5b), ``tradeoffs``, ``report`` (summary.md/json), ``cli`` (the console script).
"""
