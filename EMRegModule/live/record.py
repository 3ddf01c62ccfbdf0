"""``emreg record``: a tracker's samples into a tracking CSV or a PLUS sequence metafile, held back while the link
guard's alarm is up, and refused (exit 3) when too few samples of the reference or the probe arrived."""

from __future__ import annotations

import threading
import time
from pathlib import Path

from ..devices.link_quality import HoldBack, guard_for
from ..devices.sources import open_source
from ..errors import NoSafeAnswerError
from ..io.sequence_metafile import is_sequence_file
from ..names import MIN_RECORDED_SHARE
from .loop import LiveOptions, LiveOutcome, StopFlag, framing_text, run_loop
from .writers import RecordingWriter, SequenceRecordingWriter


def record(device: str, out: str, reference: int, probe: int, options: LiveOptions) -> LiveOutcome:
    """Record the samples of ``device`` (a device URL) into ``out`` until a limit of ``options``, the source's end
    or a signal; the reference and probe ports are counted for :func:`refuse_short_recording`."""
    source = open_source(device, reference, probe, fast=options.fast, loop=options.loop)
    writer = (SequenceRecordingWriter(out, reference_port=reference, probe_port=probe)
              if is_sequence_file(out) else RecordingWriter(out))
    rows = {reference: 0, probe: 0}
    count = [0]
    lock = threading.Lock()

    def write(sample) -> None:
        if options.max_samples is not None and count[0] >= options.max_samples:
            return  # the reader may deliver more before the loop below stops it
        if writer.write_sample(sample):
            count[0] += 1
            if sample.sensor in rows:
                rows[sample.sensor] += 1

    guard = guard_for(source)
    held = HoldBack(guard, write) if guard is not None else None  # nothing a clean link delivered is lost
    paused = [False]

    def on_sample(sample) -> None:
        with lock:
            if held is None:
                write(sample)
                return
            state = held.push(sample)
            if guard.monitor.alarm != paused[0]:  # the link went bad or came back
                paused[0] = guard.monitor.alarm
                options.say(f"[emreg] record: {'not recording' if paused[0] else 'recording again'}: "
                            f"{state.message}")

    options.say(f"[emreg] recording {source.description} -> {out}")
    try:
        with StopFlag() as stop:
            started = time.monotonic()
            source.start(on_sample)
            why = run_loop(source, stop, options.duration_s,
                           lambda: options.max_samples is not None and count[0] >= options.max_samples)
            elapsed_s = time.monotonic() - started
    finally:
        source.stop()
        with lock:
            if held is not None:
                held.close()
        writer.close()
    refuse_short_recording(out, writer, source, guard, rows, (reference, probe),
                           None if why == "sample limit reached" else elapsed_s)
    return LiveOutcome(f"{writer.rows} samples recorded -> {out} ({why})", framing_text(source))


def refuse_short_recording(out: str, writer, source, guard, rows: dict[int, int], ports: tuple[int, int],
                           elapsed_s: float | None) -> None:
    """Exit 3 (:class:`NoSafeAnswerError`, one line with the link guard's figures) when the reference or the probe
    has no sample or (``elapsed_s`` given: the recording was not ended by its sample limit) fewer than
    :data:`~EMRegModule.names.MIN_RECORDED_SHARE` of those expected; the file at ``out`` is then removed (no usable
    row) or moved aside to ``out.incomplete``."""
    expected = 0
    if elapsed_s is not None:
        period_s = getattr(source, "period_s", None)
        expected = getattr(source, "frames_sent", None) or (int(elapsed_s / period_s) if period_s else 0)
    fewest = min(rows[port] for port in ports)
    if fewest > 0 and fewest >= MIN_RECORDED_SHARE * expected:
        return
    target = Path(getattr(writer, "target", writer.path))
    kept = ""
    if writer.rows:
        target.replace(target.with_name(target.name + ".incomplete"))
        kept = f"; what was recorded is kept as {target.name}.incomplete"
    else:
        target.unlink(missing_ok=True)
    of = f" of {expected} expected ({100 * MIN_RECORDED_SHARE:g} % needed)" if expected else ""
    cause = guard.summary() if guard is not None else f"as {source.description} delivered them (no link guard)"
    framing = framing_text(source)
    reference, probe = ports
    raise NoSafeAnswerError(f"{out}: not a usable recording: {rows[reference]} reference (port {reference}) and "
                            f"{rows[probe]} probe (port {probe}) samples{of}; {cause}"
                            + (f"; {framing}" if framing else "") + kept)
