"""The robot's Fast DDS profile: reliable writers send a heartbeat every 50 ms (Fast DDS's default: 3 s).

The uplink hold-back (:mod:`gsrmr_robot.uplink_backlog`) waits for DDS acknowledgements, which come only when a
heartbeat asks. :func:`use_uplink_profile` sets the profile before rclpy starts unless a profile file is set already;
other RMW implementations ignore it. Why 50 ms: ``docs/nodes.md``, "The robot's DDS profile"; where the file is
written: ``docs/security.md``, "Services, parameters, readers".
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
import stat
import tempfile

HEARTBEAT_PERIOD_NS = 50_000_000  # why 50 ms: docs/nodes.md, "The robot's DDS profile"

UPLINK_PROFILE_XML = f"""<?xml version="1.0" encoding="UTF-8"?>
<!-- gsrmr robot: reliable writers ask for acknowledgements every 50 ms (gsrmr_robot/dds_profile.py) -->
<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <data_writer profile_name="gsrmr_robot_uplink" is_default_profile="true">
    <times>
      <heartbeat_period><sec>0</sec><nanosec>{HEARTBEAT_PERIOD_NS}</nanosec></heartbeat_period>
    </times>
  </data_writer>
</profiles>
"""

PROFILE_VARIABLES = ("FASTDDS_DEFAULT_PROFILES_FILE", "FASTRTPS_DEFAULT_PROFILES_FILE")


def _private(path: Path) -> bool:
    """``path`` is a directory (not a link) of this user that no one else may enter or write (mode & 0o077 == 0)."""
    try:
        st = os.lstat(path)
    except OSError:
        return False
    return stat.S_ISDIR(st.st_mode) and st.st_uid == os.getuid() and not st.st_mode & 0o077


def private_dir(environ: dict[str, str] | None = None) -> Path:
    """A directory only this user can enter: ``$XDG_RUNTIME_DIR/gsrmr`` or ``<tmp>/gsrmr-<uid>`` (made 0700 if
    missing, used only if it is this user's and private), else a fresh ``mkdtemp`` directory."""
    env = os.environ if environ is None else environ
    candidates = [Path(env["XDG_RUNTIME_DIR"]) / "gsrmr"] if env.get("XDG_RUNTIME_DIR") else []
    candidates.append(Path(tempfile.gettempdir()) / f"gsrmr-{os.getuid()}")
    for folder in candidates:
        try:
            folder.mkdir(mode=0o700)
        except FileExistsError:
            pass
        except OSError:
            continue
        if _private(folder):
            return folder
    return Path(tempfile.mkdtemp(prefix="gsrmr-"))


def uplink_profile_path(environ: dict[str, str] | None = None) -> Path:
    """The profile as a file in :func:`private_dir`: written to an exclusively created temporary file (0600) and
    renamed over ``gsrmr_robot_fastdds_<content hash>.xml``."""
    digest = hashlib.sha256(UPLINK_PROFILE_XML.encode()).hexdigest()[:12]
    folder = private_dir(environ)
    path = folder / f"gsrmr_robot_fastdds_{digest}.xml"
    fd, tmp = tempfile.mkstemp(prefix=".profile-", suffix=".tmp", dir=folder)  # O_EXCL, mode 0600
    try:
        with os.fdopen(fd, "w") as f:
            f.write(UPLINK_PROFILE_XML)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def use_uplink_profile(environ: dict[str, str] | None = None) -> str:
    """Set ``FASTDDS_DEFAULT_PROFILES_FILE`` to the uplink profile unless a profile file is set already;
    returns the file in effect ('' when none). Call before ``rclpy.init``."""
    env = os.environ if environ is None else environ
    for name in PROFILE_VARIABLES:
        if env.get(name):
            return env[name]
    env["FASTDDS_DEFAULT_PROFILES_FILE"] = str(uplink_profile_path(env))
    return env["FASTDDS_DEFAULT_PROFILES_FILE"]
