"""One progress display for a whole build: stage, share done and time left, on one line.

``prt-train`` runs stages of very different kinds of work: rays traced (precompute, the vertex
estimate), bounce rays traced and searched (bounces), Adam steps (fits) and files written
(export).  :class:`BuildProgress` puts them on one scale: each unit of work is weighted by a
cost per unit (:data:`RAY`, :data:`BOUNCE_RAY`, :func:`step_cost`, :data:`EXPORT_SEGMENT`, in
"ray equivalents"), so each stage's share of the build follows from its work counts (rays to
trace, steps to take), and the line shows the whole build's share done, not one bar per stage
that restarts.  Time left comes from measured rates only: the current stage's remainder at the
rate it has run at, later stages at the build's measured rate so far (weighted units per second
of work actually done: cached chunks count as done but not into the rate).

Work reaches it through handles shaped like ``tqdm``'s (``update``, ``total``, ``n``,
``set_postfix``, ``close``; :meth:`BuildProgress.bar`), so the stages' code passes a display or
``True`` / ``False`` (a ``tqdm`` bar of its own, as the standalone ``prt-precompute`` shows;
:func:`progress_bar`).  The line is drawn on a terminal only: with ``enabled=False``
(``--no-progress``) or a stream that is not a terminal (a pipe, a file, CI) nothing is written.
"""

from __future__ import annotations

import sys
import threading
import time

__all__ = ["BuildProgress", "progress_bar", "step_cost", "STEP_OVERHEAD", "RAY", "BOUNCE_RAY", "EXPORT_SEGMENT", "STAGES", "format_seconds"]

STAGES = ("precompute", "bounces", "vertices", "fits", "export")

# Costs per unit of work, in direct-ray equivalents: they set each stage's share of the build, not
# the time left (that is measured).  From the 15k-vertex scan of issue 35 on this project's 2-core
# machine: 537M direct rays in 82 s, 34M bounce rays (with their nearest-sample searches and the
# bounce products) in 166 s, fits at about 34 GFLOP/s of forward and backward passes.
RAY = 1.0
BOUNCE_RAY = 30.0
FLOPS_PER_RAY = 5000.0  # training FLOPs as costly as one direct ray
EXPORT_SEGMENT = 2.0e6  # ONNX + GLSL + manifest share of one segment


STEP_OVERHEAD = 13_000.0
"""Ray equivalents of an Adam step's fixed cost, whatever its batch (the optimiser and torch's dispatch): about
2 ms a step with two one-thread fits at once (a k16 network on batches of 256: 9.4 s for 4000 steps, of which
the FLOPs are about 0.6 s; AMD EPYC, 2 cores)."""


def step_cost(flops_per_fragment: float, batch: int) -> float:
    """Ray equivalents of one Adam step: a forward and a backward pass (about 3x the forward FLOPs) over a
    batch, plus :data:`STEP_OVERHEAD`."""
    return 3.0 * float(flops_per_fragment) * int(batch) / FLOPS_PER_RAY + STEP_OVERHEAD


def format_seconds(seconds: float) -> str:
    """``4s``, ``3m20s``, ``1h02m``."""
    seconds = max(0.0, float(seconds))
    if seconds < 60:
        return f"{seconds:.0f}s"
    if seconds < 3600:
        return f"{int(seconds // 60)}m{int(seconds % 60):02d}s"
    return f"{int(seconds // 3600)}h{int(seconds % 3600 // 60):02d}m"


def _is_terminal(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # no isatty, or a closed stream
        return False


class _Stage:
    __slots__ = ("planned", "done", "measured", "seconds", "started")

    def __init__(self):
        self.planned = 0.0  # weighted work of the stage (what is left to do included)
        self.done = 0.0  # weighted work done, cached work included
        self.measured = 0.0  # weighted work done in measured time (cached work excluded)
        self.seconds = 0.0  # time the stage has been the current one
        self.started = None  # clock when it became current


class BuildProgress:
    """The build's one line: ``[####......] 41% | bounces: bounce rays (train) 62% | 3m20s left``.

    Parameters
    ----------
    enabled : bool
        False: nothing is drawn (``--no-progress``).
    stream : file, default ``sys.stderr``
        Where the line goes; nothing is drawn unless it is a terminal.
    clock : callable
        Seconds (monotonic); the tests pass their own.
    interval : float
        Least seconds between redraws.
    """

    def __init__(self, enabled: bool = True, stream=None, *, clock=time.monotonic, interval: float = 0.25, width: int = 24):
        self.stream = sys.stderr if stream is None else stream
        self.enabled = bool(enabled) and _is_terminal(self.stream)
        self.clock, self.interval, self.width = clock, float(interval), int(width)
        self.stages = {name: _Stage() for name in STAGES}
        self.current: str | None = None
        self.detail = ""
        self._drawn = 0.0
        self._shown = False
        self._lock = threading.RLock()
        self._segments: dict[int, float] = {}  # fits: each unfinished segment's planned work
        self._last = 0.0  # the share last shown
        self.batch = 8192

    # ---------------------------------------------------------------- plan and record

    def expect(self, stage: str, work: float) -> None:
        """The weighted work ``stage`` will take (replacing an earlier plan; never below what it did)."""
        with self._lock:
            s = self.stages[stage]
            s.planned = max(float(work), s.done)

    def begin(self, stage: str, detail: str = "") -> None:
        """``stage`` is now the current one (the previous one is finished)."""
        with self._lock:
            now = self.clock()
            if self.current is not None and self.current != stage:
                self._finish(self.current, now)
            if self.current != stage:
                self.stages[stage].started = now
            self.current, self.detail = stage, detail
            self._draw(force=True)

    def finish(self, stage: str) -> None:
        """``stage`` is over: its plan becomes what it did (cached or skipped work leaves the estimate)."""
        with self._lock:
            self._finish(stage, self.clock())
            if self.current == stage:
                self.current = None
            self._draw(force=True)

    def _finish(self, stage: str, now: float) -> None:
        s = self.stages[stage]
        if s.started is not None:
            s.seconds += now - s.started
            s.started = None
        s.planned = s.done

    def add(self, stage: str, work: float, *, cached: bool = False) -> None:
        """``work`` (weighted) of ``stage`` done; ``cached``: done before, so no part of the measured rate."""
        with self._lock:
            s = self.stages[stage]
            work = float(work)
            if cached:  # a chunk store read twice (bounces auto, then the bounce stage) counts once
                work = min(work, max(s.planned - s.done, 0.0))
            s.done += work
            if s.planned < s.done:
                s.planned = s.done
            if not cached:
                s.measured += work
            self._draw()

    # ---------------------------------------------------------------- fits

    def plan_fits(self, segments: dict[int, float], batch: int) -> None:
        """The fit stage's plan: ``{segment: weighted work expected}`` for the segments still to fit."""
        with self._lock:
            self.batch = int(batch)
            self._segments = {int(k): float(v) for k, v in segments.items()}
            self.expect("fits", self.stages["fits"].done + sum(self._segments.values()))

    def segment_done(self, segment: int) -> None:
        """A segment is fitted: its part of the plan becomes what it took."""
        with self._lock:
            self._segments.pop(int(segment), None)
            s = self.stages["fits"]
            s.planned = s.done + sum(self._segments.values())
            self._draw()

    def fit_bar(self, segment: int, arch) -> "_Handle":
        """A handle counting one network fit's steps (weighted by its size, :func:`step_cost`)."""
        cost = step_cost(arch.flops_per_fragment(), self.batch)
        return self.bar("fits", f"segment {segment} {arch.label()}", unit_cost=cost)

    # ---------------------------------------------------------------- handles

    def bar(self, stage: str, label: str, total: float | None = None, *, unit_cost: float = 1.0, initial: float = 0.0) -> "_Handle":
        """A ``tqdm``-shaped handle for ``total`` units of ``stage``'s work (``initial`` of them done before)."""
        with self._lock:
            if self.current != stage:
                self.begin(stage)
            handle = _Handle(self, stage, label, total, unit_cost)
            if initial:
                handle.n = initial
                self.add(stage, initial * unit_cost, cached=True)
            self.detail = handle._detail()
            self._draw(force=True)  # a new piece of work shows at once, however short
            return handle

    # ---------------------------------------------------------------- the line

    def fraction(self) -> float:
        """Share of the whole build done (weighted work)."""
        planned = sum(s.planned for s in self.stages.values())
        return sum(s.done for s in self.stages.values()) / planned if planned > 0 else 0.0

    def seconds_left(self) -> float | None:
        """Time left from measured rates; None until a rate has been measured."""
        now = self.clock()
        rates, total_measured, total_seconds = {}, 0.0, 0.0
        for name, s in self.stages.items():
            seconds = s.seconds + (now - s.started if s.started is not None else 0.0)
            if s.measured > 0 and seconds > 0:
                rates[name] = s.measured / seconds
                total_measured += s.measured
                total_seconds += seconds
        if total_measured <= 0 or total_seconds < 1.0:
            return None
        overall = total_measured / total_seconds
        left = 0.0
        for name, s in self.stages.items():
            rest = max(s.planned - s.done, 0.0)
            if rest:
                left += rest / (rates[name] if name == self.current and name in rates else overall)
        return left

    def line(self) -> str:
        """The text of the display (without the terminal's control characters)."""
        # Shown never backwards: a plan revised upwards (the fits' real sample counts) holds the bar
        # until the work catches up; the time left is the revised estimate's.
        f = self._last = max(min(max(self.fraction(), 0.0), 1.0), self._last)
        filled = int(round(f * self.width))
        left = self.seconds_left()
        parts = [f"[{'#' * filled}{'.' * (self.width - filled)}] {100 * f:3.0f}%"]
        if self.current:
            parts.append(f"{self.current}: {self.detail}" if self.detail else self.current)
        parts.append(f"{format_seconds(left)} left" if left is not None else "measuring rates")
        return " | ".join(parts)

    def _draw(self, force: bool = False) -> None:
        if not self.enabled:
            return
        now = self.clock()
        if not force and now - self._drawn < self.interval:
            return
        self._drawn = now
        try:
            self.stream.write("\r" + self.line() + "\x1b[K")
            self.stream.flush()
            self._shown = True
        except (OSError, ValueError):  # the terminal went away: stop drawing, keep building
            self.enabled = False

    def _clear(self) -> None:
        if self.enabled and self._shown:
            try:
                self.stream.write("\r\x1b[K")
                self.stream.flush()
            except (OSError, ValueError):
                self.enabled = False
            self._shown = False

    def log(self, line: str) -> None:
        """Print a log line (stdout) above the display: clear it, print, draw it again."""
        with self._lock:
            self._clear()
            print(line, flush=True)
            self._draw(force=True)

    def close(self) -> None:
        """Clear the line (the build's report follows)."""
        with self._lock:
            self._clear()
            self.enabled = False


class _Handle:
    """What a stage updates: ``tqdm``'s ``update`` / ``total`` / ``n`` / ``set_postfix`` / ``close``."""

    def __init__(self, display: BuildProgress, stage: str, label: str, total, unit_cost: float):
        self.display, self.stage, self.label, self.total, self.unit_cost = display, stage, label, total, float(unit_cost)
        self.n = 0

    def update(self, n: float = 1) -> None:
        self.n += n
        with self.display._lock:
            self.display.detail = self._detail()
            self.display.add(self.stage, n * self.unit_cost)

    def _detail(self) -> str:
        if self.total:
            return f"{self.label} {100 * min(self.n / self.total, 1.0):.0f}%"
        return self.label

    def set_postfix(self, *args, **kwargs) -> None:
        pass  # the one line has no room for a stage's extras

    def set_postfix_str(self, *args, **kwargs) -> None:
        pass

    def close(self) -> None:
        pass


def progress_bar(progress, stage: str, label: str, total: float, *, unit: str, unit_cost: float = 1.0, initial: float = 0.0, **tqdm_args):
    """A handle for ``total`` units of work: from the build's display when ``progress`` is a
    :class:`BuildProgress`, a ``tqdm`` bar of its own when it is True, None when False."""
    if isinstance(progress, BuildProgress):
        return progress.bar(stage, label, total, unit_cost=unit_cost, initial=initial)
    if progress:
        from tqdm import tqdm

        return tqdm(total=total, initial=initial, unit=unit, desc=label, **tqdm_args)
    return None
