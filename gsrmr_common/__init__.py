"""Code shared by the robot and the server: camera conventions, metrics, wire formats, ROS helpers.

Pure modules (no rclpy): :mod:`camera`, :mod:`metrics`. ROS helpers live in :mod:`ros_node`.
"""
