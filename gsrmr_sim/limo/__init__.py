"""The simulated LIMO base: a byte-exact mock of the serial protocol on a pty (:mod:`mock`, no ROS) and its
node module (:mod:`mock_ros`: ``gsrmr-mock-limo``, publishing the true pose). The real driver is
:mod:`gsrmr_robot.limo`."""
