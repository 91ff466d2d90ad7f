"""Paper Section V experiments on our data (``gsrmr-experiments``); pure, no rclpy.

Modules: ``data`` (round 1 → GS model, round 2 → per-slot L_t and channel gains, cached),
``composite`` (MR images actually composited under a schedule), ``paper`` (Fig. 4a/4b, Table 1,
Fig. 5a/5b), ``tradeoffs`` (scheduler, renderer, JPEG, training), ``report`` (summary.md/json),
``cli`` (the console script). See docs/experiments.md.
"""
