"""AgileX LIMO base over pyserial: protocol codecs, kinematics, odometry, driver, ROS node.

Pure (no rclpy): :mod:`protocol`, :mod:`kinematics`, :mod:`odometry`, :mod:`driver`. ROS: :mod:`node`
(``gsrmr-limo-base``). The byte-exact mock base is simulation: :mod:`gsrmr_sim.limo`.
"""
