"""Errors raised at the rosbag boundary.

Each one names the bag file and says what was expected, and the reader errors
list the topics the bag has, so a user with a real robot's bag sees at once which
``--*-topic`` option to pass.
"""
from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

from stack.errors import DopeSlamError


class BagError(DopeSlamError):
    """Base class of every error about a rosbag file."""

    def __init__(self, path: Path | str, message: str):
        self.path = Path(path)
        self.message = message
        super().__init__(f"{self.path}: {message}")


class BagWriteError(BagError):
    """A bag could not be written (target exists, wrong suffix, bad message)."""


class BagReadError(BagError):
    """A bag could not be opened or decoded."""


class TooManyBadMessagesError(BagReadError):
    """More messages of a topic could not be converted than the reader may skip."""


class CorruptBagError(BagReadError):
    """The file is truncated or damaged and no complete message could be recovered."""


def format_topics(topics: Mapping[str, str]) -> str:
    """``topics`` (name -> message type) as one readable line per topic."""
    if not topics:
        return "  (the bag has no topics)"
    width = max(len(name) for name in topics)
    return "\n".join(f"  {name:<{width}}  {msgtype}" for name, msgtype in sorted(topics.items()))


class MissingTopicError(BagReadError):
    """A topic the stack needs is not in the bag (or has the wrong type)."""

    def __init__(self, path: Path | str, what: str, expected: str, topics: Mapping[str, str],
                 hint: str = ""):
        self.what = what
        self.topics = dict(topics)
        text = f"no {what} topic: expected {expected}"
        if hint:
            text += f"; {hint}"
        super().__init__(path, f"{text}.\nTopics in the bag:\n{format_topics(self.topics)}")


class MissingExtrinsicError(BagReadError):
    """``/tf_static`` has no chain of transforms between two frames."""

    def __init__(self, path: Path | str, parent: str, child: str, frames: list[str],
                 topics: Mapping[str, str], option: str):
        self.parent, self.child = parent, child
        self.frames = list(frames)
        self.topics = dict(topics)
        known = ", ".join(sorted(self.frames)) if self.frames else "(none: no /tf_static messages)"
        super().__init__(
            path,
            f"no transform from {parent!r} to {child!r} in /tf_static (frames there: {known}); "
            f"record /tf_static or pass {option}.\nTopics in the bag:\n{format_topics(self.topics)}")


class UnsupportedEncodingError(BagReadError):
    """A message's encoding or layout cannot be converted (image encoding, point fields)."""

    def __init__(self, path: Path | str, topic: str, found: str, expected: str,
                 topics: Mapping[str, str] | None = None):
        self.topic, self.found, self.expected = topic, found, expected
        text = f"topic {topic!r}: {found}; expected {expected}"
        if topics is not None:
            text += f".\nTopics in the bag:\n{format_topics(topics)}"
        super().__init__(path, text)
