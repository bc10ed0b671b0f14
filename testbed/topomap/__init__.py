"""The topological-map paper's system (monocular semantic topological map) run in the testbed's episodes:
cached camera streams, pose-estimation evaluation, detector training and evaluation, navigation,
and the side-by-side comparison with DOPESLAM."""

from stack.errors import DopeSlamError


class InputError(DopeSlamError, ValueError):
    """A user's input (an argument, a file) is not what the command expects; the message names it."""


def print_saved_report(path, where: str, expected: str, printer) -> None:
    """``printer(report)`` on the JSON report saved at ``path``, its text printed only when it
    succeeds; a file that cannot be read or is not such a report is one InputError line
    (``{where}: expected {expected}: ...``), and nothing of the tables is printed."""
    import contextlib
    import io
    import json

    from stack.io import read_user_text

    text = read_user_text(path, InputError, expected)  # missing, a folder, not UTF-8: one line naming the file
    try:
        report = json.loads(text)
        with contextlib.redirect_stdout(io.StringIO()) as tables:
            printer(report)
    except KeyError as exc:
        raise InputError(f"{where}: expected {expected}: no field {exc}") from None
    except (ValueError, TypeError, AttributeError, IndexError) as exc:
        raise InputError(f"{where}: expected {expected}: {exc}") from None
    print(tables.getvalue(), end="")
