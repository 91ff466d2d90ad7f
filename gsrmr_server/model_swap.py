"""A new GS model loaded off the slot path and handed over at a slot boundary (pure, no ROS): :class:`ModelSwap`.

How to swap a model: ``docs/model_update.md``, "4. Swap, without stopping the server".
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
import threading
import time
from typing import Any, Generic, TypeVar

M = TypeVar("M")


@dataclass(frozen=True)
class Loaded(Generic[M]):
    """A model ready to be swapped in: what was loaded, from where, and how long the load took [s]."""

    model: M
    path: str
    load_s: float


class ModelSwap(Generic[M]):
    """One loader thread at a time; the newest request wins.

    :meth:`request` starts a loader thread (``load(path)``: read the .ply and, in the server, render it once so that
    the first slot with it pays no first-touch cost); the composing thread calls :meth:`take` before each slot and
    gets the new model once it is ready — the slot being composed keeps the model it started with, no slot waits for
    a load. A newer request supersedes one still loading (its model is dropped when it arrives). A load that fails
    leaves the model in use and is reported (:attr:`error`).
    """

    def __init__(self, load: Callable[[str], M]) -> None:
        self._load = load
        self._lock = threading.Lock()
        self._ready: Loaded[M] | None = None
        self._wanted: int = 0  # the newest request's number
        self.in_use: str = ""  # the path of the model in use (set by the owner at start, then by take)
        self.swaps = 0
        self.error: str = ""  # the last failed load, '' when the last request loaded
        self.loading: str = ""  # the path being loaded, '' when idle

    def diagnostic_values(self) -> dict[str, Any]:
        """``model`` (the path in use), ``model_swaps`` and ``model_loading`` (the path being loaded, '' when idle)."""
        return {"model": self.in_use, "model_swaps": self.swaps, "model_loading": self.loading}

    def problems(self) -> list[str]:
        """What ``/diagnostics`` warns about: the last load failed (the model in use stays)."""
        return [f"model swap failed, the model in use stays: {self.error}"] if self.error else []

    def request(self, path: str) -> threading.Thread:
        """Load ``path`` in a daemon thread (returned, for tests to join)."""
        with self._lock:
            self._wanted += 1
            ticket = self._wanted
            self.loading = path
        thread = threading.Thread(target=self._run, args=(path, ticket), name="gsrmr-model-load", daemon=True)
        thread.start()
        return thread

    def _run(self, path: str, ticket: int) -> None:
        t0 = time.perf_counter()
        try:
            model = self._load(path)
        except Exception as err:
            with self._lock:
                if ticket == self._wanted:
                    self.error, self.loading = f"{path}: {type(err).__name__}: {err}", ""
            return
        with self._lock:
            if ticket == self._wanted:  # not superseded meanwhile
                self._ready = Loaded(model, path, time.perf_counter() - t0)
                self.error, self.loading = "", ""

    def take(self) -> Loaded[M] | None:
        """The newly loaded model, once (None while nothing new is ready)."""
        with self._lock:
            ready, self._ready = self._ready, None
            if ready is not None:
                self.in_use = ready.path
                self.swaps += 1
            return ready
