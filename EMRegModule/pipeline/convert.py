"""A tracking recording converted between EMReg's CSV, a PLUS sequence metafile and 3D Slicer's recording folder
(``emreg convert``): the reference and probe keep their roles' transform names (``[sensors] reference_transform`` /
``probe_transform``), every other transform of a sequence file becomes a sensor port of its own.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ..core.tracking import TrackingRecording
from ..errors import EMRegError
from ..io.recording import read_recording, write_recording
from ..io.sequence_metafile import is_sequence_file, read_sequence_frames, recording_from_frames
from ..io.tracking_csv import read_tracking_csv
from ..settings import Settings


@dataclass(frozen=True)
class Converted:
    """The recording written, and the port each other transform of a sequence file was given (name -> port)."""

    recording: TrackingRecording
    others: dict[str, int]


def convert_recording(source: Path, target: Path, settings: Settings, reference: int, probe: int,
                      quaternion: bool = False) -> Converted:
    """Read ``source`` (a sequence file, a Slicer recording folder or a tracking CSV) and write it to ``target``
    with the reference and probe on ``reference`` / ``probe`` (CSV orientations as quaternions when asked).
    Refused (one line, exit 2): ``target`` is ``source``, a role's transform is missing from a sequence file, or a
    CSV would write another sensor under a role's name."""
    sensors = settings.sensors
    names = {"reference_transform": sensors.reference_transform or "ReferenceToTracker",
             "probe_transform": sensors.probe_transform or "ProbeToTracker"}
    if source.resolve() == target.resolve():
        raise EMRegError(f"convert: {target} is the input file; give another output name")
    if is_sequence_file(source):
        frames = read_sequence_frames(source)
        ports = {names["reference_transform"]: reference, names["probe_transform"]: probe}
        missing = [n for n in ports if n not in frames.matrices]
        if missing:
            raise EMRegError(f"{source}: no {' or '.join(n + 'Transform' for n in missing)} in the file; it holds "
                             f"{', '.join(n + 'Transform' for n in frames.names)}; name them with [sensors] "
                             "reference_transform / probe_transform (--settings case.toml)")
        free = (p for p in range(1, 100) if p not in ports.values())
        for name in frames.names:  # every other transform of the file keeps its own port
            if name not in ports:
                port = name[len("Sensor"):-len("ToTracker")] if name.startswith("Sensor") else ""
                ports[name] = int(port) if port.isdigit() and int(port) not in ports.values() else next(free)
        recording = recording_from_frames(frames, ports)
        others = {n: p for n, p in ports.items() if n not in names.values()}
    elif source.is_dir():  # 3D Slicer's recording: one sequence file per transform, matched by timestamp
        recording, others = read_recording(source, settings, reference, probe), {}
    else:
        recording, others = read_tracking_csv(source), {}
        if is_sequence_file(target):
            _check_convert_ports(recording, reference, probe, names)
    write_recording(recording, target, settings, reference, probe, orientation="quaternion" if quaternion else None)
    return Converted(recording, others)


def _check_convert_ports(recording: TrackingRecording, reference: int, probe: int, names: dict[str, str]) -> None:
    """A sequence file names each sensor by its role: refuse (exit 2) a recording in which a role's port is
    absent while other ports are present, which would write another sensor under a role's name (a probe
    on port 1 as ``ReferenceToTracker``) and leave the role's transform INVALID in every frame."""
    present = recording.sensors
    roles = {"reference": (reference, names["reference_transform"]), "probe": (probe, names["probe_transform"])}
    missing = [(role, port, name) for role, (port, name) in roles.items() if port not in present]
    strangers = [p for p in present if p not in (reference, probe)]
    if missing and strangers:
        role, port, name = missing[0]
        raise EMRegError(f"{recording.source}: no samples on port {port}, the {role} sensor written as "
                         f"{name}Transform (ports present: {present}); name the ports with --reference-sensor / "
                         "--probe-sensor (or --settings case.toml)")
