"""The simulated world: scenes, mock camera and LIMO, simulated radio, route follower, scorer, fault relay, the
process stacks, ``gsrmr-demo``, the paper's experiments and the shared test data (docs/world.md); the tools that read
recorded runs (``analysis/``) and what the benches share (``machine_probe``, ``core_path``, ``demo_runs``).

Nothing else imports this package (import-linter contract in ``pyproject.toml``); it may import everything.
"""

from gsrmr_common.interrupts import guard_console_start_up

guard_console_start_up()  # a console script of this package: Ctrl-C while its module loads exits 0
