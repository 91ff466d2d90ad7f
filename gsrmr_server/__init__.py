"""Server side of gsrmr: scheduling, the Gaussian-splatting engine, the simulated world and the nodes."""

from gsrmr_common.interrupts import guard_console_start_up

guard_console_start_up()  # a console script of this package: Ctrl-C while its module loads exits 0
