"""A one-line progress display for a terminal: episodes done, their returns, steps, and what the
planner is doing (retraining, new models), redrawn in place.

It writes to a stream only when that stream is a terminal (or when forced), so a log file or a
pipe gets the driver's plain lines and nothing else. A thread redraws the line twice a second,
so a long wait (an episode's first action waiting for retraining) shows its elapsed time, and
it reads the run's events there so that the line says what the trainer does.
"""

from __future__ import annotations

import contextlib
import sys
import threading
import time
from typing import Iterator, Optional, TextIO

from .errors import EbmpcError
from .events import ModelsUpdated, RunEvents, TrainingFailed, TrainingStarted

#: Width of the bar in characters.
BAR_WIDTH = 20
#: Seconds between redraws.
REDRAW_SECONDS = 0.5


class Progress:
    """Progress of ``total`` episodes (``None``: no episode budget) and ``total_steps``
    environment steps (``None``: no step budget) on ``stream`` (default stderr); the bar
    follows whichever budget is nearer its end.

    ``enabled``: ``None`` draws when the stream is a terminal. ``events``: the run's events
    (:meth:`ebmpc.Planner.events`), read to show retraining. Use it as a context manager;
    print within :meth:`paused` to print above the bar.
    """

    def __init__(
        self,
        total: Optional[int],
        *,
        total_steps: Optional[int] = None,
        stream: Optional[TextIO] = None,
        enabled: Optional[bool] = None,
        events: Optional[RunEvents] = None,
    ) -> None:
        self.total = total
        self.total_steps = total_steps
        self.stream = stream if stream is not None else sys.stderr
        isatty = getattr(self.stream, "isatty", None)
        self.enabled = enabled if enabled is not None else bool(isatty and isatty())
        self.done = 0
        self.steps = 0
        self.last_return: Optional[float] = None
        self.best_return: Optional[float] = None
        self.trainer = ""
        self._events = events
        self._started = time.monotonic()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: Optional[threading.Thread] = None
        self._drawn = False

    def __enter__(self) -> Progress:
        if self.enabled:
            self._thread = threading.Thread(target=self._redraw, name="ebmpc-progress", daemon=True)
            self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        if self.enabled:
            with self._lock:
                self._draw()
                self.stream.write("\n")
                self.stream.flush()

    def episode(self, episode_return: float) -> None:
        """Counts a finished episode (its steps were counted by :meth:`step`)."""
        with self._lock:
            self.done += 1
            self.last_return = episode_return
            if self.best_return is None or episode_return > self.best_return:
                self.best_return = episode_return

    def step(self, n: int = 1) -> None:
        """Counts ``n`` environment steps."""
        with self._lock:
            self.steps += n

    @contextlib.contextmanager
    def paused(self) -> Iterator[None]:
        """Clears the line for what is printed within (an episode's line), then draws it
        again below that."""
        with self._lock:
            if self.enabled and self._drawn:
                self.stream.write("\r\x1b[2K")
                self.stream.flush()
                self._drawn = False
            try:
                yield
            finally:
                if self.enabled:
                    self._draw()

    def line(self) -> str:
        """The progress line as it is drawn."""
        shares = [self.done / max(1, self.total)] if self.total is not None else []
        if self.total_steps is not None:
            shares.append(self.steps / max(1, self.total_steps))
        filled = min(BAR_WIDTH, int(BAR_WIDTH * max(shares, default=0.0)))
        bar = "#" * filled + "-" * (BAR_WIDTH - filled)
        episodes = f"{self.done}/{self.total}" if self.total is not None else f"{self.done}"
        steps = f"{self.steps}/{self.total_steps}" if self.total_steps is not None else f"{self.steps}"
        parts = [f"[{bar}] {episodes} episodes", f"{steps} steps"]
        if self.last_return is not None and self.best_return is not None:
            parts.append(f"return {self.last_return:.1f} (best {self.best_return:.1f})")
        if self.trainer:
            parts.append(self.trainer)
        parts.append(f"{time.monotonic() - self._started:.0f} s")
        return " | ".join(parts)

    def _read_events(self) -> None:
        if self._events is None:
            return
        while True:
            try:
                event = self._events.next(timeout=0)
            except EbmpcError:
                return  # no event waiting (or an undecodable one: the bar does without)
            if isinstance(event, TrainingStarted):
                self.trainer = f"retraining on {event.transitions} transitions"
            elif isinstance(event, ModelsUpdated):
                self.trainer = f"models v{event.models_version} ({event.seconds:.1f} s to train)"
                ends = event.termination_accuracy
                if ends is not None:
                    self.trainer += (
                        f", ends {100 * ends.accuracy:.0f}% right "
                        f"({100 * ends.recall:.0f}% of {ends.terminations} held out)"
                    )
            elif isinstance(event, TrainingFailed):
                self.trainer = f"retraining failed: {event.message[:60]}"

    def _draw(self) -> None:
        self.stream.write("\r\x1b[2K" + self.line())
        self.stream.flush()
        self._drawn = True

    def _redraw(self) -> None:
        while not self._stop.wait(REDRAW_SECONDS):
            with self._lock:
                self._read_events()
                self._draw()
