"""``localization: pose`` on the graph (gsrmr_robot.external_localizer): the robot takes map → odom from another
localizer's ``amcl_pose`` joined with its odometry at the pose's stamp, only from ``correction_writers``; a rogue
writer is refused and named, a pose in another frame refused and counted."""

from __future__ import annotations

import time

from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter

from gsrmr_common.pose2d import Pose2D
from gsrmr_common.tf_ros import tf_message_type
from gsrmr_robot.robot_node import RobotNode

TRUTH = Pose2D(2.0, -1.0, 0.5)  # map → odom of the localizer
ODOM = Pose2D(0.4, 0.1, 0.2)  # the base in odom (parked)




def _pose_msg(pose: Pose2D, stamp, frame: str = "map") -> PoseWithCovarianceStamped:
    msg = PoseWithCovarianceStamped()
    msg.header.stamp, msg.header.frame_id = stamp, frame
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    p.x, p.y = pose.x_m, pose.y_m
    q.x, q.y, q.z, q.w = pose.quaternion()
    msg.pose.covariance[0] = msg.pose.covariance[7] = 0.01
    msg.pose.covariance[35] = 0.001
    return msg


def _odom_msg(stamp) -> Odometry:
    msg = Odometry()
    msg.header.stamp, msg.header.frame_id, msg.child_frame_id = stamp, "odom", "base_link"
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    p.x, p.y = ODOM.x_m, ODOM.y_m
    q.x, q.y, q.z, q.w = ODOM.quaternion()
    return msg


@pytest.mark.ros
def test_the_robot_takes_map_to_odom_from_amcl_pose_and_only_from_its_writers(ros_context):
    robot = RobotNode(context=ros_context, parameter_overrides=[Parameter("localization", value="pose")])
    amcl = rclpy.create_node("amcl", context=ros_context)
    rogue = rclpy.create_node("rogue", context=ros_context)
    executor = SingleThreadedExecutor(context=ros_context)
    try:
        for node in (robot, amcl, rogue):
            executor.add_node(node)
        pub_odom = amcl.create_publisher(Odometry, "odom", 10)
        pub_pose = amcl.create_publisher(PoseWithCovarianceStamped, "amcl_pose", 10)
        pub_rogue = rogue.create_publisher(PoseWithCovarianceStamped, "amcl_pose", 10)

        def feed_until(done, timeout_s: float, frame: str = "map") -> None:
            """Odometry at 20 Hz, the localizer's pose (stamped 100 ms back) and the rogue's at 5 Hz."""
            deadline, n = time.monotonic() + timeout_s, 0
            while not done():
                assert time.monotonic() < deadline, (robot.maps.seq, robot.inputs.gate.refused_by_writer())
                now = amcl.get_clock().now()
                pub_odom.publish(_odom_msg(now.to_msg()))
                if n % 4 == 3:
                    back = rclpy.time.Time(nanoseconds=now.nanoseconds - 100_000_000).to_msg()
                    pub_pose.publish(_pose_msg(TRUTH.compose(ODOM), back, frame))
                    pub_rogue.publish(_pose_msg(Pose2D(9.0, 9.0, 0.0), now.to_msg()))
                n += 1
                end = time.monotonic() + 0.05
                while time.monotonic() < end:
                    executor.spin_once(timeout_sec=0.01)

        feed_until(lambda: robot.maps.seq >= 3 and "/rogue" in robot.inputs.gate.refused_by_writer(), 30)
        assert robot.maps.map_from_odom().distance_m(TRUTH) < 1e-6
        assert abs(robot.maps.map_from_odom().theta_rad - TRUTH.theta_rad) < 1e-6
        assert robot.maps.variance == pytest.approx((0.01, 0.01, 0.001))
        seq = robot.maps.seq
        feed_until(lambda: robot.implausible["correction_malformed"] >= 2, 30, frame="odom")
        assert robot.maps.seq == seq  # a pose in odom is no map → odom
    finally:
        executor.shutdown()
        for node in (robot, amcl, rogue):
            node.destroy_node()


@pytest.mark.ros
def test_localization_tf_without_tf2_msgs_says_what_to_take_instead(ros_context):
    if tf_message_type()[0] is not None:
        pytest.skip("tf2_msgs imports here: localization tf subscribes /tf")
    with pytest.raises(RuntimeError, match=r"tf2_msgs does not import.*localization pose"):
        RobotNode(context=ros_context, parameter_overrides=[Parameter("localization", value="tf")])
