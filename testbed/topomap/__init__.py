"""The topological-map paper's system (monocular semantic topological map) run in the testbed's episodes:
cached camera streams, pose-estimation evaluation, detector training and evaluation, navigation,
and the side-by-side comparison with DOPESLAM."""

from stack.errors import DopeSlamError


class InputError(DopeSlamError, ValueError):
    """A user's input (an argument, a file) is not what the command expects; the message names it."""
