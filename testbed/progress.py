"""Progress bars with an ETA for the long commands (``run``, ``replay``, ``record``, ``experiment``; the
DOPE data commands ``datagen``, ``dope-eval`` and ``calibrate-fpr`` ask :func:`enabled` for theirs).

They go to stderr, and only when stderr is a terminal; ``dopeslam --quiet`` (or ``-q`` after any
command) turns them off. Code that runs without the command line gets no bars unless it calls
:func:`configure`. ``DOPESLAM_PROGRESS=1`` shows them even when stderr is not a terminal.
"""
from __future__ import annotations

import os
import sys

_quiet = True  # until the command line (or a user) says otherwise
_outer = 0  # outer bars open (runs())


def configure(quiet: bool = False) -> None:
    """Turn bars on (where stderr is a terminal) or off."""
    global _quiet
    _quiet = bool(quiet)


def enabled() -> bool:
    if _quiet:
        return False
    if os.environ.get("DOPESLAM_PROGRESS") == "1":
        return True
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):
        return False


def bar(total=None, desc: str = "", unit: str = "it", **kwargs):
    """A tqdm bar on stderr (disabled, and free, when bars are off)."""
    from tqdm import tqdm

    kwargs.setdefault("dynamic_ncols", True)
    kwargs.setdefault("leave", True)
    return tqdm(total=total, desc=desc, unit=unit, file=sys.stderr, disable=not enabled(), **kwargs)


SIM_FORMAT = "{desc}: {percentage:3.0f}%|{bar}| {n:.1f}/{total:.1f} s [{elapsed}<{remaining}{postfix}]"


class SecondsBar:
    """Seconds of data (simulated, or a bag's) done out of a known span, with an ETA.
    ``update_to(t)`` with the latest message's time; ``postfix`` with counts."""

    def __init__(self, total_s: float, desc: str, t0: float = 0.0, unit: str = "s"):
        self.t0 = float(t0)
        fmt = SIM_FORMAT if unit == "s" else SIM_FORMAT.replace("{n:.1f}/{total:.1f} s", "{n:.0f}/{total:.0f} " + unit)
        self._bar = bar(total=max(float(total_s), 1e-9), desc=desc, unit=unit, bar_format=fmt, leave=_outer == 0)
        self._last = 0.0

    def update_to(self, t: float, **postfix) -> None:
        if self._bar.disable:
            return
        done = min(max(float(t) - self.t0, 0.0), self._bar.total)
        if done > self._last:
            self._bar.update(done - self._last)
            self._last = done
        if postfix:
            self._bar.set_postfix(postfix, refresh=False)

    def close(self) -> None:
        self._bar.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def runs(iterable, desc: str, total: int | None = None, unit: str = "run"):
    """An outer bar over an experiment's runs; the episode bars inside it do not stay."""
    global _outer
    if total is None and hasattr(iterable, "__len__"):
        total = len(iterable)
    b = bar(total=total, desc=desc, unit=unit)
    _outer += 1
    try:
        for item in iterable:
            yield item
            b.update(1)
    finally:
        _outer -= 1
        b.close()


_views: list = []  # live views a job reports to (testbed.view.RerunView), see watching()


def views_active() -> bool:
    """Whether a job started now reports to live views (:class:`watching`)."""
    return bool(_views)


class watching:
    """``with watching(view): run_episode(...)``: the jobs started inside report to ``view``."""

    def __init__(self, *views):
        self.views = [v for v in views if v is not None]

    def __enter__(self):
        _views.extend(self.views)
        return self

    def __exit__(self, *exc):
        for v in self.views:
            _views.remove(v)
            v.close()


class EpisodeWatch:
    """What a job's message loop tells its watchers: the progress bar (data seconds with an ETA)
    and the live views of :func:`watching`. ``truth``: the source's ground truth or None;
    ``pipe``: the stack's pipeline."""

    def __init__(self, desc: str, duration_s: float, t0: float = 0.0, truth=None, pipe=None, unit: str = "s"):
        self.bar = SecondsBar(duration_s, desc, t0, unit)
        self.unit = unit
        self.shown = not self.bar._bar.disable
        self.views = list(_views)
        self.pipe = pipe
        for v in self.views:
            v.start(truth, pipe, desc)

    def scan(self, scan, T_map_base) -> None:
        if self.views:
            points = getattr(getattr(self.pipe, "odometry", None), "last_points_base", None)
            for v in self.views:
                v.scan(scan, T_map_base, points)

    def image(self, frame, detections, correct=None) -> None:
        for v in self.views:
            v.image(frame, detections, correct)

    def tick(self, t: float, **counts) -> None:
        self.bar.update_to(t, **counts)
        if self.unit == "s":  # t is data time (else a count: the views keep time from the scans)
            for v in self.views:
                v.tick(t)

    def finish(self, store, T_world_map=None, map_labels=None) -> None:
        self.bar.close()
        for v in self.views:
            v.finish(store, T_world_map, map_labels)
