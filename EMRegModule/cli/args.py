"""Turns the command line into what a command works with: the settings, the sensor ports, the output folder
and the controller. Every command takes these from here (one rule each: where the settings come from, which
ports a user gave, how OUT is checked before any work).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path

from ..errors import EMRegError
from ..io.output_folder import OutputFolder, outputs_from, refuse_out_over_inputs
from ..pipeline.controller import EMRegController
from ..pipeline.inputs import refuse_tool_auto
from ..progress import Progress
from ..settings import Settings, load_settings, sensor_ports_given, with_series


def progress_of(args: argparse.Namespace) -> Progress:
    return Progress(enabled=not getattr(args, "quiet", False))


def settings_of(args: argparse.Namespace, case_dir: Path | None = None) -> Settings:
    """``--settings FILE``, else the case folder's ``case.toml``, else the defaults (typed, checked)."""
    if getattr(args, "settings", None):
        return load_settings(args.settings, required=True)
    if case_dir is not None:
        return load_settings(case_dir / "case.toml")
    return load_settings(None)


def out_folder(out: str | Path | None, create: bool = True) -> Path | None:
    """Check an output folder before any work: a folder (made if missing) that EMReg can write into.

    Refused with one line (exit 2): OUT is a file, a broken symbolic link or a loop, cannot be
    made, or cannot be written (permissions, read-only file system).
    """
    if out is None:
        return None
    path = Path(out)
    try:
        if path.is_symlink() and not path.exists():
            raise EMRegError(f"{path}: output folder is a broken symbolic link (or a symbolic-link loop)")
        if path.exists() and not path.is_dir():
            raise EMRegError(f"{path}: output folder is a file; give a folder for --out")
        if not create and not path.is_dir():
            return path
        path.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=path):
            pass
    except EMRegError:
        raise
    except OSError as exc:
        raise EMRegError(f"{path}: cannot write to the output folder ({exc.strerror or exc})") from None
    return path


def out_file(out: str | Path) -> Path:
    """Check an output file's place before any work: not a folder, its folder writable (one line, exit 2)."""
    path = Path(out)
    if path.is_dir():
        raise EMRegError(f"{path}: is a folder; give a file name for --out")
    out_folder(path.parent if str(path.parent) else Path("."))
    return path


def with_series_of(settings: Settings, args: argparse.Namespace) -> Settings:
    """``--series UID|NUMBER`` overrides ``[ct] series`` of case.toml."""
    return with_series(settings, getattr(args, "series", None))


def warn(command: str, warnings: Sequence[str]) -> None:
    """Print a stage's warnings (also kept in its JSON output), one line each, on stderr."""
    for warning in warnings:
        print(f"emreg {command}: warning: {warning}", file=sys.stderr)


def output_folder(args: argparse.Namespace, stage: str, inputs: Sequence[Path],
                   case_dir: Path | None = None) -> OutputFolder:
    """OUT for a per-stage command: refused when it could overwrite an input; the outputs of ``stage`` and
    of the stages made from it (stale once this stage has a new result) moved to ``OUT/previous/``."""
    refuse_out_over_inputs(args.out, inputs, outputs_from(stage), case_dir)
    folder = OutputFolder(args.out, f"emreg {args.command}")
    folder.start_stage(stage)
    return folder


def ports_given(args: argparse.Namespace, settings: Settings) -> tuple[int | None, int | None]:
    """The ports the user chose (reference, probe): ``--reference-sensor`` / ``--probe-sensor``, else those
    ``case.toml [sensors]`` names; None where neither gives one (a registration's own ports then apply)."""
    in_file = sensor_ports_given(settings)
    flags = (getattr(args, "reference_sensor", None), getattr(args, "probe_sensor", None))
    return tuple(f if f is not None else t for f, t in zip(flags, in_file, strict=True))  # type: ignore[return-value]


def controller_of(args: argparse.Namespace, settings: Settings) -> EMRegController:
    controller = EMRegController(settings, progress_of(args), f"emreg {args.command}")
    controller.give(sensors=(getattr(args, "reference_sensor", None), getattr(args, "probe_sensor", None)))
    return controller


def use_tool(args: argparse.Namespace, controller: EMRegController, solves: bool = True) -> None:
    """``--tool FILE`` (else ``[tool] calibration`` of the settings): the tool whose tip is tracked. ``solves``:
    the command has a calibration recording to solve ``--tool auto`` from (else it is refused)."""
    tool = getattr(args, "tool", None) or controller.settings.file_path(controller.settings.tool.calibration)
    if tool:
        controller.give(tool=tool)
    if controller.inputs.tool_auto and not solves:
        refuse_tool_auto(f"emreg {args.command}")


def use_plan(args: argparse.Namespace, controller: EMRegController) -> None:
    """``--plan FILE`` (else ``[navigation] plan`` of the settings): the planned target (and entry) the guidance
    numbers are computed against; refused (one line) before the controller has a registration."""
    if not getattr(args, "plan", None) and not controller.settings.navigation.plan:
        return
    if controller.results.registration is None:
        raise EMRegError(f"emreg {args.command}: a plan (--plan or [navigation] plan) needs a registration; give "
                         "--registration registration.json")
    settings = controller.settings
    controller.give(plan=getattr(args, "plan", None) or settings.file_path(settings.navigation.plan))


def recording_ports(args: argparse.Namespace, settings: Settings) -> tuple[int, int]:
    """The (reference, probe) ports a recording is written or read with (``emreg convert``): the flags, else
    ``[sensors]`` (any port a sequence file names, not only the tracker's 1..4)."""
    return (args.reference_sensor or settings.sensors.reference, args.probe_sensor or settings.sensors.probe)


def sensor_ports(args: argparse.Namespace) -> tuple[int, int]:
    """The (reference, probe) ports of a live command without a registration (``emreg record``, ``serve``): the
    flags, else the settings file's ``[sensors]``, else the defaults (names.DEFAULT_*_PORT)."""
    settings = load_settings(getattr(args, "settings", None), required=True)
    sensors = settings.with_sensors(args.reference_sensor, args.probe_sensor).sensors
    return sensors.reference, sensors.probe
