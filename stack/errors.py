"""The base of every error a user can fix: a bad file, option or value.

Each one's message already names what is wrong (the file, the field, what was expected), so a
command line prints it as one line and exits with status 2; anything else is a bug and keeps its
traceback.
"""
from __future__ import annotations


class DopeSlamError(Exception):
    """An error in what a user gave (file, option, value); its message is one readable line."""


class OutputError(DopeSlamError, OSError):
    """An output cannot be written where it was asked for (it would destroy something)."""


class InputDataError(DopeSlamError, ValueError):
    """Recorded data that cannot be used (too many bad messages, no usable data left)."""


class UsageError(DopeSlamError, ValueError):
    """A command-line option whose value cannot be used (names the option and what was expected)."""


class ComponentError(DopeSlamError, ValueError):
    """A plugged-in component (detector, odometry, policy) gave what its Protocol does not allow: a
    detection that is not one, a pose that is not a transform. Names the component, the input it
    was given and what was expected."""
