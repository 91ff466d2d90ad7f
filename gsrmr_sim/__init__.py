"""The simulated world: the "real" scene and camera, the mock LIMO, the route follower, the fault relay, the
process stacks, the demo, the survey, the paper's experiments and the shared test data.

Nothing else imports this package (import-linter contract in ``pyproject.toml``); it may import everything.
"""

from gsrmr_common.interrupts import guard_console_start_up

guard_console_start_up()  # a console script of this package: Ctrl-C while its module loads exits 0
