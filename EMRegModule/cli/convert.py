"""``emreg convert``: a tracking recording between CSV and a PLUS sequence metafile
(:mod:`EMRegModule.pipeline.convert` does the work).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..pipeline.convert import convert_recording
from .args import recording_ports, settings_of, warn


def cmd_convert(args: argparse.Namespace) -> int:
    settings = settings_of(args)
    reference, probe = recording_ports(args, settings)
    target = Path(args.output)
    converted = convert_recording(Path(args.input), target, settings, reference, probe, args.quaternion)
    warn("convert", converted.recording.warnings)
    extra = ("; other transforms as sensor ports " + ", ".join(f"{n} = {p}" for n, p in converted.others.items())
             if converted.others else "")
    print(f"{len(converted.recording)} sensor samples converted -> {target}{extra}")
    return 0
