"""The library every gsrmr program uses: wire contract, link model, camera model, TF, metrics, JPEG, ROS helpers.

What it holds and which of its modules import no ROS: docs/architecture.md, "The packages" and "The import rules".
"""

from gsrmr_common.interrupts import guard_console_start_up

guard_console_start_up()  # a console script of this package: Ctrl-C while its module loads exits 0
