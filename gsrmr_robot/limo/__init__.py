"""AgileX LIMO base over pyserial: protocol codecs, kinematics, odometry, driver, mock base, ROS node.

Pure (no rclpy): :mod:`protocol`, :mod:`kinematics`, :mod:`odometry`, :mod:`driver`, :mod:`mock`.
ROS: :mod:`node` (``gsrmr-limo-base``) and :mod:`mock_ros` (ground-truth publisher of the mock).
"""
