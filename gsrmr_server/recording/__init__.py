"""Run recorder: one CSV row and a few ROS 2 messages per slot, crash-safe (pure: no rclpy import).

Modules: :mod:`slots_csv` (the CSV codec), :mod:`msgdefs` (``.msg`` definitions for the MCAP schemas),
:mod:`mcap_log` (topics, segments, merge and salvage), :mod:`recorder` (:class:`RunRecorder`), :mod:`cli`.

Output directory layout
-----------------------
``slots.csv``
    One row per slot with the columns :data:`CSV_COLUMNS` (units in the names; ``stamp_s`` is the slot
    start in seconds of ROS time, ``x`` 1 = image / 0 = pose key, ``source`` ∈ {image, render,
    fallback}, pose in ``map`` per REP-103, ``loss`` = MR loss of m̂_t against the true m_t (simulation
    only: empty in the server's file, filled in the demo's report from the scorer's ``scores.csv``),
    ``gs_loss`` = the GS loss L_t measured in an image slot, ``energy_upload_all_j`` = what the
    upload-all reference (RoboMR) would have spent on this slot's frame, ``channel_gain`` = the gain
    g = |h|² the robot's ledger booked the slot at; empty cell = not available).
    The file is flushed after every row, so a killed process (``kill -9``) loses no row that
    :meth:`RunRecorder.write_slot`
    returned from. ``fsync=True`` makes rows survive power loss as well (costs a disk sync per slot).
``run.mcap``
    After :meth:`RunRecorder.close`: ROS 2 (``ros2msg`` schemas, ``cdr`` messages, zstd chunks) with
    the topics :data:`TOPIC_MR_IMAGE` (``sensor_msgs/msg/CompressedImage``: the MR image m̂_t as JPEG,
    ``format = wire.JPEG_FORMAT``), :data:`TOPIC_CMD_VEL` (``geometry_msgs/msg/TwistStamped``: u_t in
    ``base_link``, m/s and rad/s) and :data:`TOPIC_SLOT_LOG` (``std_msgs/msg/String``: the CSV row as
    JSON). Every message's ``log_time``/``publish_time`` and header stamp is the slot start. Other
    topics come through :meth:`RunRecorder.write_message`, e.g. :data:`TOPIC_CAMERA_INFO`
    (``sensor_msgs/msg/CameraInfo``, the robot's calibration, logged when it arrives) and, in every slot composed
    with the robot's image, what arrived for it: :data:`TOPIC_RECEIVED_IMAGE` (``sensor_msgs/msg/CompressedImage``,
    the robot's JPEG byte for byte, frame ``camera_optical_frame``) and :data:`TOPIC_RECEIVED_POSE`
    (``geometry_msgs/msg/PoseStamped``, frame ``map``: the slot's pose key, ``base_link`` at (a_m, b_m, 0) with yaw
    θ), both stamped at the slot start — a model update's training data (``gsrmr-dataset run.mcap --image-topic
    /gsrmr/received/image/compressed --camera-info-topic /gsrmr/camera_info --pose-topic /gsrmr/received/pose``).
    Opens in Foxglove and ``ros2 bag info/play`` (MCAP storage plugin); channels carry
    ``offered_qos_profiles = "[]"`` (the player then uses its default QoS).

Crash safety of the MCAP
------------------------
While running, messages go to segments: ``run-0000.mcap``, ``run-0001.mcap`` … of ``segment_slots``
slots each. The segment being written is named ``run-NNNN.mcap.part`` and renamed when it is finished,
so every ``run-NNNN.mcap`` is a complete, indexed MCAP file. A crash therefore loses at most the slots
of the open ``.part`` segment (default 50 slots = 5 s at τ = 0.1 s), and :func:`recover_run` salvages
its complete chunks too. :meth:`RunRecorder.close` merges the segments into ``run.mcap`` (via
``run.mcap.part`` + rename) and deletes them. After a crash run :func:`recover_run` (same merge).

Message definitions are generated from the installed ``.msg`` files (:func:`message_definition`):
the top-level definition, then each nested type after a line of 80 ``=`` and ``MSG: pkg/msg/Type``,
the rosbag2 ``ros2msg`` encoding.
"""

from gsrmr_server.recording.cli import main
from gsrmr_server.recording.mcap_log import (
    MCAP_NAME,
    TOPIC_CAMERA_INFO,
    TOPIC_CMD_VEL,
    TOPIC_MR_IMAGE,
    TOPIC_RECEIVED_IMAGE,
    TOPIC_RECEIVED_POSE,
    TOPIC_SLOT_LOG,
    TOPIC_TYPES,
    merge_segments,
    read_mcap,
    recover_run,
)
from gsrmr_server.recording.msgdefs import message_definition
from gsrmr_server.recording.recorder import RunRecorder
from gsrmr_server.recording.slots_csv import CSV_COLUMNS, CSV_NAME, SOURCES, read_slots_csv, write_slots_csv

__all__ = ["CSV_COLUMNS", "CSV_NAME", "MCAP_NAME", "SOURCES", "TOPIC_CAMERA_INFO", "TOPIC_CMD_VEL", "TOPIC_MR_IMAGE",
           "TOPIC_RECEIVED_IMAGE", "TOPIC_RECEIVED_POSE", "TOPIC_SLOT_LOG", "TOPIC_TYPES", "RunRecorder", "main",
           "merge_segments", "message_definition", "read_mcap", "read_slots_csv", "recover_run", "write_slots_csv"]
