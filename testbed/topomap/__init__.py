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
    from pathlib import Path

    try:
        report = json.loads(Path(path).read_bytes().decode("utf-8"))
        with contextlib.redirect_stdout(io.StringIO()) as text:
            printer(report)
    except OSError as exc:
        raise InputError(f"{where}: expected {expected}: {exc.strerror}") from None
    except KeyError as exc:
        raise InputError(f"{where}: expected {expected}: no field {exc}") from None
    except (ValueError, TypeError, AttributeError, IndexError) as exc:
        raise InputError(f"{where}: expected {expected}: {exc}") from None
    print(text.getvalue(), end="")
