"""The scheduler's state on disk (``state_dir``): the last schedule and the loss map, so that a restarted scheduler
resumes from its last schedule, and every replan's solve time (``bench/acceptance/demo.py`` reads it). Pure, no ROS."""

from __future__ import annotations

import json
from pathlib import Path

from gsrmr_common.wire import ScheduleMsg
from gsrmr_scheduler.loss_map import LossMap

SCHEDULE_FILE = "schedule.json"
LOSS_MAP_FILE = "loss_map.json"
PLAN_STATS_FILE = "plan_stats.json"


def _replace_atomically(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    tmp.replace(path)


class StateStore:
    """``state_dir``'s files; an empty ``state_dir`` keeps nothing."""

    def __init__(self, state_dir: str) -> None:
        self.folder = Path(state_dir) if state_dir else None

    def loss_map_path(self) -> Path | None:
        """The saved loss map, where there is one."""
        path = self.folder / LOSS_MAP_FILE if self.folder else None
        return path if path is not None and path.exists() else None

    def initial_loss_map(self, loss_map_file: str, prior: float) -> tuple[LossMap, Path | None]:
        """The loss map to start from: the saved one, else ``loss_map_file``, else an empty map of ``prior``.

        Returns:
            The map and the file it was read from (None: the empty map).
        """
        for candidate in (self.loss_map_path(), Path(loss_map_file) if loss_map_file else None):
            if candidate is not None and candidate.exists():
                return LossMap.load(candidate), candidate
        return LossMap(prior=prior), None

    def save(self, schedule: ScheduleMsg, loss_map: LossMap, method: str, solve_times_s: list[float],
             slack_s: list[float]) -> None:
        """Write the schedule, the loss map and the replans' solve times and slacks [s] (each file replaced
        atomically)."""
        if self.folder is None:
            return
        self.folder.mkdir(parents=True, exist_ok=True)
        _replace_atomically(self.folder / SCHEDULE_FILE, json.dumps({"data": schedule.to_data()}))
        loss_map.save(self.folder / LOSS_MAP_FILE)
        _replace_atomically(self.folder / PLAN_STATS_FILE, json.dumps({"method": method, "solve_time_s": solve_times_s,
                                                                       "slack_s": slack_s}))

    def load_schedule(self) -> ScheduleMsg | None:
        """The saved schedule, None when there is none.

        Raises:
            ValueError: the file is there but holds no schedule.
        """
        path = self.folder / SCHEDULE_FILE if self.folder else None
        if path is None or not path.exists():
            return None
        try:
            return ScheduleMsg.from_data(json.loads(path.read_text())["data"])
        except (KeyError, TypeError, json.JSONDecodeError) as err:
            raise ValueError(f"{path}: {type(err).__name__}: {err}") from err
