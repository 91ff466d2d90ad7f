"""Run recorder (pure: no rclpy import): one CSV row and a few ROS 2 messages per slot, crash-safe.

A run's directory holds ``slots.csv`` (one row per slot, :data:`CSV_COLUMNS`: the fields of
:class:`gsrmr_server.slot_row.SlotRow`) and ``run.mcap`` (the MR images, ``cmd_vel``, each slot's row, the robot's
calibration, and every image the server received with its pose key). Layout, topics and crash safety:
``docs/nodes.md``, "The server's recording". Modules: :mod:`slots_csv` (the CSV codec), :mod:`msgdefs` (``.msg``
definitions for the MCAP schemas), :mod:`mcap_log` (topics, segments, merge and salvage), :mod:`recorder`
(:class:`RunRecorder`), :mod:`cli`.
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
