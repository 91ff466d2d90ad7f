"""The simulated LIMO base: a byte-exact mock of the serial protocol on a pty (:mod:`mock`) and its
ground-truth pose publisher (:mod:`mock_ros`). The real driver is :mod:`gsrmr_robot.limo`."""
