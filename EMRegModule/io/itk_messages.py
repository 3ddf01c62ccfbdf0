"""ITK's own messages silenced around EMReg's reads, so that a refusal is EMReg's one line alone.

ITK prints warnings itself (a NIfTI read as Analyze, a deprecated field: ``WARNING: In .../itkNiftiImageIO.cxx``)
through its output window, and MetaIO, GDCM and NIfTI print their complaints straight to the process's
standard error (a truncated MetaImage header: ``DimSize required and not defined.`` and three more lines, for
each of the three times a file is looked at). Either way they land before EMReg's own message and say
nothing EMReg does not say better; worse, ITK's exception then often ends with a stale ``Reason: No such file
or directory`` while the true reason was only printed.

:func:`quiet_itk` turns ITK's warning display off (SimpleITK's ``ProcessObject`` global switch, restored
after the last user leaves) and, with ``capture``, also catches what C code writes to file descriptor 2
meanwhile: the lines are handed back (:attr:`Captured.lines`) so that the caller can name the true reason.
Only short synchronous reads (a header, a small SimpleITK read) capture: lines other threads write to
standard error in that time are caught too, and EMReg's own (``emreg ...``, ``[emreg] ...``) are written out
again afterwards.
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field

_lock = threading.RLock()  # one capture of fd 2 at a time (a second one waits: captures are short)
_users = 0  # readers inside quiet_itk: ITK's warning display is restored when the last one leaves
_users_lock = threading.Lock()
_display_before = True


@dataclass
class Captured:
    """What C code wrote to standard error during a :func:`quiet_itk` block (filled when the block ends)."""

    lines: list[str] = field(default_factory=list)

    def reason(self) -> str | None:
        """The first captured line that says what is wrong (MetaIO's and NIfTI's complaints come first), or None."""
        return next(iter(self.lines), None)


@contextlib.contextmanager
def quiet_itk(capture: bool = False) -> Iterator[Captured]:
    """Silence ITK's warnings (and, with ``capture``, C-level standard error) for the block; see the module."""
    global _users, _display_before
    import SimpleITK as sitk  # what is quieted is SimpleITK's reading: it is loaded by then

    with _users_lock:
        if _users == 0:
            _display_before = bool(sitk.ProcessObject.GetGlobalWarningDisplay())
            sitk.ProcessObject.SetGlobalWarningDisplay(False)
        _users += 1
    captured = Captured()
    try:
        if capture:
            with _lock, _stderr_caught(captured):
                yield captured
        else:
            yield captured
    finally:
        with _users_lock:
            _users -= 1
            if _users == 0:
                sitk.ProcessObject.SetGlobalWarningDisplay(_display_before)


@contextlib.contextmanager
def _stderr_caught(captured: Captured) -> Iterator[None]:
    """File descriptor 2 into a temporary file for the block; its lines into ``captured``."""
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError, AttributeError):  # no usable fd 2 (an embedding host): nothing to catch
        yield
        return
    with tempfile.TemporaryFile() as sink:
        os.dup2(sink.fileno(), 2)
        try:
            yield
        finally:  # also when the read raised: the caller may still name what was printed
            with contextlib.suppress(OSError, ValueError, AttributeError):
                sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
            sink.seek(0)
            lines = [line.strip() for line in sink.read().decode("utf-8", "replace").splitlines() if line.strip()]
            ours = [line for line in lines if line.startswith(("emreg ", "[emreg]"))]
            captured.lines = [line for line in lines if line not in ours]
            if ours:  # another thread's lines, written meanwhile
                with contextlib.suppress(OSError, ValueError, AttributeError):
                    print("\n".join(ours), file=sys.stderr, flush=True)


def read_failure(exc: BaseException, printed: Captured | None = None,
                 path: str | os.PathLike[str] | None = None) -> str:
    """The reason a SimpleITK read failed, in a few words: what the reader printed (``printed``, from
    :func:`quiet_itk`) when it printed something, else ITK's error from its exception (the ``ITK ERROR`` line
    and what follows, without the ``Class(0x...)`` prefix). A ``Reason: <errno text>`` line is dropped when
    ``path`` is a readable file: ITK adds whatever ``errno`` last said (often "No such file or directory")."""
    reason = printed.reason() if printed is not None else None
    if reason:
        return reason.rstrip(".")[:200]
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()] or ["unreadable"]
    start = next((i for i, line in enumerate(lines) if line.startswith("ITK ERROR:")), len(lines) - 1)
    readable = path is not None and os.path.isfile(path) and os.access(path, os.R_OK)
    kept = [line for line in lines[start:] if not (readable and line.startswith("Reason:"))] or lines[start:]
    detail = " ".join(kept)
    if detail.startswith("ITK ERROR:"):
        detail = detail.split("): ", 1)[-1]
    return detail.rstrip(".")[:200]
