"""Tools a user runs between missions, on the workstation: a robot's bag or the server's recording as a
dataset (``gsrmr-dataset``), the deployment survey of a model's loss along a route (``gsrmr-survey``) and the model
update from what the server received, with change confirmation (``gsrmr-update``). No ROS runtime.
"""

from gsrmr_common.interrupts import guard_console_start_up

guard_console_start_up()  # a console script of this package: Ctrl-C while its module loads exits 0
