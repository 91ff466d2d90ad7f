"""The simulated world (wing three): the "real" scene and camera, the mock LIMO, the route follower, the
fault relay, the process stacks, the demo, the survey and the paper's experiments.

Deployment code (``gsrmr_robot``, ``gsrmr_server``) never imports this package (import-linter contract in
``pyproject.toml``); this package may import everything else.
"""

from gsrmr_common.interrupts import guard_console_start_up

guard_console_start_up()  # a console script of this package: Ctrl-C while its module loads exits 0
