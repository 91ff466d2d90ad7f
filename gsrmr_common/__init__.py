"""Code shared by the robot and the server: camera conventions, metrics, wire formats, ROS helpers.

Pure modules (no rclpy): :mod:`camera`, :mod:`metrics`. ROS helpers live in :mod:`ros_node`.
"""

from gsrmr_common.interrupts import guard_console_start_up

guard_console_start_up()  # a console script of this package: Ctrl-C while its module loads exits 0
