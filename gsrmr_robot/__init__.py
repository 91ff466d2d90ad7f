"""Robot side of gsrmr: the LIMO base driver and the robot node (image or pose key each slot)."""

from gsrmr_common.interrupts import guard_console_start_up

guard_console_start_up()  # a console script of this package: Ctrl-C while its module loads exits 0
