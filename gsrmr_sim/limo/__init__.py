"""The simulated LIMO base: the pty mock (:mod:`~gsrmr_sim.limo.mock`, no ROS) and its node module
(:mod:`~gsrmr_sim.limo.mock_ros`, ``gsrmr-mock-limo``). The real driver is :mod:`gsrmr_robot.limo`.
"""
