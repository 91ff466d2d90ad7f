"""The simulation server: the server node, its slot core (GS render at the pose key or the received image,
composited with the MR content), the MR content itself and the recording of what it received and published."""

from gsrmr_common.interrupts import guard_console_start_up

guard_console_start_up()  # a console script of this package: Ctrl-C while its module loads exits 0
