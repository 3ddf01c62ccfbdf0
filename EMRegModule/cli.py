"""The ``emreg`` command: a thin face over the controller and the core modules.

Exit codes (spec): 0 success; 2 bad input or usage (one line naming the file and what is
wrong); 3 the data do not allow a safe answer. Every output file is written atomically.
"""

from __future__ import annotations

import argparse
import signal
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from . import __version__
from .errors import EXIT_BAD_INPUT, EMRegError, NoSafeAnswerError
from .live import commands as live
from .progress import Progress

if TYPE_CHECKING:  # the commands import what they use: `emreg --help` and `emreg detect` start fast
    from .controller import EMRegController
    from .outputs import OutputFolder
    from .settings import Settings

class _Parser(argparse.ArgumentParser):
    """argparse with the spec's exit code 2 and a one-line message for usage errors."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.print_usage(sys.stderr)
        self.exit(EXIT_BAD_INPUT, f"{self.prog}: error: {message}\n")


def _progress(args: argparse.Namespace) -> Progress:
    return Progress(enabled=not getattr(args, "quiet", False))


def _settings(args: argparse.Namespace, case_dir: Path | None = None) -> Settings:
    """``--settings FILE``, else the case folder's ``case.toml``, else the defaults (typed, checked)."""
    from .settings import load_settings

    if getattr(args, "settings", None):
        return load_settings(args.settings, required=True)
    if case_dir is not None:
        return load_settings(case_dir / "case.toml")
    return load_settings(None)


def _out_folder(out: str | Path | None, create: bool = True) -> Path | None:
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


def _out_file(out: str | Path) -> Path:
    """Check an output file's place before any work: not a folder, its folder writable (one line, exit 2)."""
    path = Path(out)
    if path.is_dir():
        raise EMRegError(f"{path}: is a folder; give a file name for --out")
    _out_folder(path.parent if str(path.parent) else Path("."))
    return path


def _with_series(settings: Settings, args: argparse.Namespace) -> Settings:
    """``--series UID|NUMBER`` overrides ``[ct] series`` of case.toml."""
    from .settings import with_series

    return with_series(settings, getattr(args, "series", None))


def _warn(command: str, warnings: Sequence[str]) -> None:
    """Print a stage's warnings (also kept in its JSON output), one line each, on stderr."""
    for warning in warnings:
        print(f"emreg {command}: warning: {warning}", file=sys.stderr)


def _output_folder(args: argparse.Namespace, stage: str, inputs: Sequence[Path],
                   case_dir: Path | None = None) -> OutputFolder:
    """OUT for a per-stage command: refused when it could overwrite an input; the outputs of ``stage`` and
    of the stages made from it (stale once this stage has a new result) moved to ``OUT/previous/``."""
    from .outputs import OutputFolder, outputs_from, refuse_out_over_inputs

    refuse_out_over_inputs(args.out, inputs, outputs_from(stage), case_dir)
    folder = OutputFolder(args.out, f"emreg {args.command}")
    folder.start_stage(stage)
    return folder


def _ports_given(args: argparse.Namespace, settings: Settings) -> tuple[int | None, int | None]:
    """The ports the user chose (reference, probe): ``--reference-sensor`` / ``--probe-sensor``, else those
    ``case.toml [sensors]`` names; None where neither gives one (a registration's own ports then apply)."""
    from .settings import sensor_ports_given

    in_file = sensor_ports_given(settings)
    flags = (getattr(args, "reference_sensor", None), getattr(args, "probe_sensor", None))
    return tuple(f if f is not None else t for f, t in zip(flags, in_file, strict=True))  # type: ignore[return-value]


def _controller(args: argparse.Namespace, settings: Settings) -> EMRegController:
    from .controller import EMRegController

    controller = EMRegController(settings, _progress(args), f"emreg {args.command}")
    controller.set_sensors(getattr(args, "reference_sensor", None), getattr(args, "probe_sensor", None))
    return controller


# --- subcommands ----------------------------------------------------------------------------


def cmd_simulate(args: argparse.Namespace) -> int:
    _out_folder(args.out)
    from .simulation import simulate_case

    options = {"probe_axis": args.probe_axis} if args.probe_axis else {}
    if args.tool_tip:
        options["tool_tip_mm"] = tuple(args.tool_tip)
    if args.distortion:
        options.update(distortion_mm=args.distortion, distortion_during=args.distortion_during,
                       distortion_onset_s=args.distortion_onset)
    simulate_case(
        Path(args.out), seed=args.seed, difficulty=args.difficulty, spacing_mm=args.spacing,
        progress=_progress(args), **options,
    )
    print(f"simulated case written to {args.out}")
    return 0


def cmd_detect(args: argparse.Namespace) -> int:
    from .io.case import find_ct

    _out_folder(args.out)
    source = Path(args.ct)
    case_dir = source if source.is_dir() and find_ct(source) is not None else None
    ct_path = find_ct(source) if case_dir is not None else source
    controller = _controller(args, _with_series(_settings(args, case_dir), args))
    folder = _output_folder(args, "detect", [ct_path], case_dir)
    controller.recorder.note_inputs(ct=ct_path if ct_path.exists() else None)
    result = controller.load_ct_and_detect(ct_path, keep_image=False)  # detects on the slices read as the rest arrives
    controller.save("detect", folder)
    print(f"{len(result.markers)} markers detected, {len(result.rejected)} candidates rejected -> {args.out}")
    return 0


def _use_tool(args: argparse.Namespace, controller: EMRegController, solves: bool = True) -> None:
    """``--tool FILE`` (else ``[tool] calibration`` of the settings): the tool whose tip is tracked. ``solves``:
    the command has a calibration recording to solve ``--tool auto`` from (else it is refused)."""
    if getattr(args, "tool", None):
        controller.load_tool(args.tool)
    else:
        controller.load_tool_from_settings()
    if controller.tool_auto and not solves:
        raise EMRegError(f"emreg {args.command}: --tool auto solves the tip from a calibration recording; give the "
                         "tool_calibration.json that emreg calibrate or emreg run wrote with it instead")


def cmd_calibrate(args: argparse.Namespace) -> int:
    _out_folder(args.out)
    recording = Path(args.recording)
    controller = _controller(args, _settings(args))
    _use_tool(args, controller)
    controller.load_calibration_recording(recording)
    tool_file = [Path(args.tool)] if args.tool and args.tool != "auto" else []
    folder = _output_folder(args, "calibrate", [recording] + tool_file)
    controller.recorder.note_inputs(calibration=recording)
    result = controller.calibrate_frame()
    controller.save("calibrate", folder)
    controller.recorder.warn(result.warnings)
    if controller.tool is None:
        print(f"{len(result.points)} pinholes calibrated -> {args.out}")
    else:
        motions = [p.motion for p in result.points]
        tool = controller.tool
        solved = "" if result.solved_tool is None else (
            f"; tip solved from {tool.touches} pivoting touches: [{', '.join(f'{v:.2f}' for v in tool.tip_mm)}] mm "
            f"+/- [{', '.join(f'{v:.2f}' for v in tool.tip_std_mm)}], RMS {tool.rms_mm:.2f} mm")
        print(f"{len(result.points)} tip touches ({motions.count('pivot')} pivoting, {motions.count('rest')} "
              f"resting) with the tool of {tool.source}{solved} -> {args.out}")
    return 0


def cmd_pivot(args: argparse.Namespace) -> int:
    import numpy as np

    from .outputs import refuse_out_over_inputs
    from .tool import TIP_TO_PROBE_ITK, TOOL_CALIBRATION_JSON, pivot_calibration, pivot_poses, write_tool_calibration

    _out_folder(args.out)
    recording_path = Path(args.recording)
    controller = _controller(args, _settings(args))
    poses, frame, name, warnings = pivot_poses(recording_path, controller.settings, controller.reference_sensor,
                                               controller.probe_sensor)
    tool = pivot_calibration(poses, str(recording_path), frame, name)
    refuse_out_over_inputs(args.out, [recording_path], (TOOL_CALIBRATION_JSON, TIP_TO_PROBE_ITK))
    write_tool_calibration(tool, args.out)
    _warn("pivot", warnings + tool.warnings)
    tip = ", ".join(f"{v:.2f}" for v in tool.tip_mm)
    print(f"tip at [{tip}] mm in the probe frame ({np.linalg.norm(tool.tip_mm):.1f} mm from the sensor), RMS "
          f"{tool.rms_mm:.2f} mm over {tool.samples} of {tool.samples_total} samples, swing "
          f"{tool.rotation_range_deg:.0f} degrees -> {args.out}")
    return 0


def cmd_register(args: argparse.Namespace) -> int:
    _out_folder(args.out)
    controller = _controller(args, _settings(args))
    inputs = [Path(p) for p in (args.markers, args.fiducials, args.calibration, args.targets) if p]
    if (args.markers is None) == (args.fiducials is None):
        raise EMRegError("register: give the image side once: --markers markers.json (CT markers) or --fiducials FILE "
                         "(.mrk.json, .fcsv, a PLUS device-set XML with landmarks, or markers.json)")
    folder = _output_folder(args, "register", inputs)
    if args.fiducials is not None:
        controller.load_fiducials(args.fiducials)
    else:
        controller.load_detection(args.markers)
    controller.load_frame_calibration(args.calibration)
    targets = None
    if args.targets:
        from .io.case import read_targets

        controller.recorder.note_inputs(targets=args.targets)
        targets = read_targets(args.targets)[1]
    try:
        result = controller.register(targets)
    except NoSafeAnswerError:
        folder.remove_from("register")
        raise
    controller.save("register", folder)
    controller.recorder.warn(result.warnings)
    from .workflow.results import offset_summary

    print(f"registered: FRE {result.fre_mm:.2f} mm, {offset_summary(result)}, {len(result.pairs)} pairs -> {args.out}")
    return 0


def cmd_navigate(args: argparse.Namespace) -> int:
    live.check_live_options(args)  # replay or live: a value out of range is refused before anything is made
    _out_folder(args.out)
    if args.igtl_port is not None or not args.source.startswith("replay:"):
        from .live.commands import run_live_navigate

        if args.tool or _settings(args).tool.calibration:  # the live path streams the sensor's pose, not a tip
            raise EMRegError("navigate: a tool (--tool or [tool] calibration) is used with replay:FILE only; live "
                             "navigation streams the probe sensor's pose (ProbeToImage), not the tip")
        return run_live_navigate(args)
    if not args.out:
        raise EMRegError("navigate: --out DIR is needed to write navigation.csv from a replay")
    from .io.recording import read_recording

    recording_path = Path(args.source[len("replay:"):])
    controller = _controller(args, _settings(args))
    from .checkpoints import markers_beside

    markers, note = markers_beside(args.registration)
    if markers is not None:  # the checkpoints need the markers' pinholes (before the registration: it is dropped)
        controller.set_detection(markers)
    controller.load_registration(args.registration)
    _warn("navigate", [note] if note else [])
    _warn("navigate", controller.use_ports(*_ports_given(args, controller.settings), args.registration))
    _use_tool(args, controller, solves=False)
    recording = (read_recording(recording_path, controller.settings, controller.reference_sensor,
                                controller.probe_sensor) if controller.tool is None
                 else controller.read_recording(recording_path))
    folder = _output_folder(args, "navigate", [recording_path, Path(args.registration)])
    controller.recorder.note_inputs(navigation=recording_path)
    result = controller.navigate_recording(recording)
    controller.recorder.warn(recording.warnings)
    controller.save("navigate", folder)
    checkpoints = controller.results.checkpoints
    print(f"{len(result)} probe samples mapped into image space; {checkpoints.summary()} -> {args.out}")
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    from .io.case import open_case

    case = open_case(args.case, _settings(args) if args.settings else None)
    _out_folder(args.out)
    if case.navigation is None and case.board is None:
        raise EMRegError(f"{case.folder}: nothing to evaluate: no navigation recording (navigation.csv) and no "
                         "board recording (board.csv) in the case folder")
    if case.navigation is not None and case.targets is None and case.board is None:
        raise EMRegError(f"{case.folder}: nothing to evaluate: a navigation recording but no targets.mrk.json "
                         "(and no board.csv)")
    given = _ports_given(args, case.settings)
    case.settings = case.settings.with_sensors(args.reference_sensor, args.probe_sensor)  # sequence files' ports
    controller = _controller(args, case.settings)
    inputs = [p for p in (case.navigation, case.targets, case.board) if p is not None]
    folder = _output_folder(args, "evaluate", [*inputs, Path(args.registration)], case.folder)
    controller.load_registration(args.registration)
    _warn("evaluate", controller.use_ports(*given, args.registration))
    case.settings = case.settings.with_sensors(controller.reference_sensor, controller.probe_sensor)
    controller.recorder.check_case_inputs("registration.json", args.registration, case)
    controller.recorder.note_inputs(navigation=case.navigation, targets=case.targets, board=case.board)
    _use_tool(args, controller, solves=False)
    result = controller.evaluate(controller.case_recording(case, "navigation"), case.read_targets(),
                                 controller.case_recording(case, "board"))
    controller.save("evaluate", folder)
    controller.recorder.warn(result.warnings)
    print(f"evaluation -> {folder.path / 'evaluation.json'}")
    return 0


def cmd_convert(args: argparse.Namespace) -> int:
    from .io.recording import write_recording
    from .io.sequence_metafile import is_sequence_file, read_sequence_frames, recording_from_frames
    from .io.tracking_csv import read_tracking_csv

    settings = _settings(args)
    sensors = settings.sensors
    reference = args.reference_sensor or sensors.reference
    probe = args.probe_sensor or sensors.probe
    names = {"reference_transform": sensors.reference_transform or "ReferenceToTracker",
             "probe_transform": sensors.probe_transform or "ProbeToTracker"}
    source, target = Path(args.input), Path(args.output)
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
        from .io.recording import read_recording

        recording, others = read_recording(source, settings, reference, probe), {}
    else:
        recording, others = read_tracking_csv(source), {}
        if is_sequence_file(target):
            _check_convert_ports(recording, reference, probe, names)
    write_recording(recording, target, settings, reference, probe,
                    orientation="quaternion" if args.quaternion else None)
    _warn("convert", recording.warnings)
    extra = ("; other transforms as sensor ports " + ", ".join(f"{n} = {p}" for n, p in others.items())
             if others else "")
    print(f"{len(recording)} sensor samples converted -> {target}{extra}")
    return 0


def _check_convert_ports(recording, reference: int, probe: int, names: dict[str, str]) -> None:
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


def cmd_report(args: argparse.Namespace) -> int:
    if args.batch and (args.out or args.case):  # one of them would be ignored: never guessed
        raise EMRegError(f"give an output folder (emreg report OUT [--case CASE]) or --batch DIR, not "
                         f"both ({args.out or '--case ' + args.case} and --batch {args.batch})")
    from .workflow.exporters import read_run_record, recorded_case, start_report_bundle, start_report_ct

    out, case = (Path(args.out) if args.out else None), (Path(args.case) if args.case else None)
    run = read_run_record(out) if out is not None and not args.batch else None
    early = start_report_ct(out, case, run) if out is not None else None  # read while the report's libraries load
    bundle = early_bundle = start_report_bundle(out, case, run)  # held: writes nothing into OUT until released below
    folder = kept = None
    try:
        from .outputs import OutputFolder

        if args.batch:
            return _report_batch(args)
        if not args.out:
            raise EMRegError("report: give an output folder (emreg report OUT) or --batch DIR")
        _out_folder(args.out, create=False)  # the run's folder: the report is written into it
        from .report.inputs import require_report_inputs

        require_report_inputs(args.out)  # before run.json is written: a case folder is left as it is
        # the case's settings (those the figures use), so that the report's provenance names them
        controller = _controller(args, _settings(args, case or recorded_case(run)))
        stage = OutputFolder(args.out, "emreg report")
        kept = controller.exporter.kept_bundle(stage, case)  # still the scene this report would write: it stays
        stage.start_stage("report", keep=[kept.path.name] if kept is not None else ())
        folder = stage
        if kept is None:
            bundle = controller.exporter.start_bundle(folder, case, early_bundle)  # goes on while the report renders
        elif early_bundle is not None:
            early_bundle.cancel()
            bundle = None
        path = controller.exporter.save_report(folder, case, controller, early)
    except BaseException:
        if bundle is not None:
            bundle.cancel()
        if early is not None:
            early.cancel()
        if folder is not None:  # the bundle (released by then) or figures this failed report wrote: not left in OUT
            if kept is not None:  # nor the kept bundle: as a report that fails leaves none, it goes to previous/
                folder.start_stage("bundle")
            folder.drop_unrecorded()
        raise
    print(f"report -> {path}")
    print(controller.exporter.save_bundle(folder, case, controller, bundle, kept))
    return 0


def _report_batch(args: argparse.Namespace) -> int:
    """``emreg report --batch DIR``: every run folder under DIR, each with its bundle."""
    from .report import write_reports_batch

    batch = Path(args.batch)
    if not batch.is_dir():
        raise EMRegError(f"{batch}: folder of run outputs not found")
    if args.settings:
        _settings(args)  # a settings file that cannot be read is refused once, before any report
    folders = sorted(p for p in batch.iterdir() if p.is_dir())
    # each job checks that its folder's outputs belong together: one mixed folder fails alone, the others are reported
    bundles: list = []  # each job writes its case's bundle (with the CT its report read, if it needs it)
    try:
        pages = write_reports_batch(folders, jobs=args.jobs, progress=_progress(args), bundles=bundles,
                                    settings_file=getattr(args, "settings", None))
        print(f"{len(pages)} reports written under {args.batch}")
    finally:  # the cases that did get their report and bundle say so even when others failed
        for folder, (path, message, sha) in bundles:
            _record_batch_report(args, Path(folder), sha if path is not None else None)
            print(_bundle_line(path, message))
    return 0


def cmd_run(args: argparse.Namespace) -> int:
    from .io.case import open_case

    _out_folder(args.out)
    from .settings import with_series

    case = open_case(args.case, _settings(args) if args.settings else None)
    case.settings = with_series(case.settings, args.series)
    case.settings = case.settings.with_sensors(args.reference_sensor, args.probe_sensor)  # a sequence file's too
    controller = _controller(args, case.settings)
    if args.tool:
        controller.load_tool(args.tool)
    controller.exporter.keep_ct = False  # nothing uses the CT after the run: freed as soon as nothing needs it
    for line in controller.run(case, Path(args.out)):
        print(line)
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from .io.case import open_case
    from .simulation import simulate_case

    out = _out_folder(args.out)
    case_dir = out / "case"
    progress = _progress(args)
    start = time.perf_counter()
    progress.message(f"[emreg] demo: simulating the sample case into {case_dir}")
    simulate_case(case_dir, seed=args.seed, difficulty="standard", spacing_mm=args.spacing, progress=progress)
    case = open_case(case_dir)
    controller = _controller(args, case.settings)
    for line in controller.run(case, out / "result"):
        print(line)
    print(f"demo finished in {time.perf_counter() - start:.1f} s; outputs in {out / 'result'}")
    return 0


def _record_batch_report(args: argparse.Namespace, folder: Path, bundle_sha256: str | None) -> None:
    """The report (and bundle, whose sha256 its job computed as it wrote it) a batch job wrote into ``folder``,
    listed in its ``run.json``."""
    from .io.atomic import read_json
    from .outputs import OutputFolder

    try:
        case = read_json(folder / "run.json", "run record").get("case")
    except (EMRegError, AttributeError):
        case = None
    case_dir = Path(case) if isinstance(case, str) and Path(case).is_dir() else None
    try:
        controller = _controller(args, _settings(args, case_dir))
        controller.recorder.command = "emreg report --batch"
        controller.exporter.record_report_outputs(OutputFolder(folder, controller.recorder.command), bundle_sha256)
    except EMRegError as exc:
        _warn("report", [f"{folder}: not recorded in run.json ({exc})"])


def _bundle_line(path, message: str) -> str:
    """The summary line of a scene bundle; one that could not be written is also a warning."""
    if path is None:
        _warn("bundle", [message])
    return f"bundle: {message}"


def cmd_study(args: argparse.Namespace) -> int:
    from .studies import STUDIES, format_table, run_study

    summary = run_study(args.name, Path(args.out), quick=args.quick, scheduler=args.scheduler, workers=args.workers,
                        case_dir=Path(args.case) if args.case else None,
                        work=Path(args.work) if args.work else None, seed=args.seed, progress=_progress(args))
    print(f"{STUDIES[args.name].title}\n")
    print(format_table(summary))
    print(f"\n-> {Path(args.out) / args.name}.json, .csv, .png")
    return 0


# --- parser -----------------------------------------------------------------------------------


def _add_sensor_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--reference-sensor", type=int, default=None, metavar="PORT",
                        help="port of the reference sensor (default 1 or case.toml [sensors])")
    parser.add_argument("--probe-sensor", type=int, default=None, metavar="PORT",
                        help="port of the probe sensor (default 2 or case.toml [sensors])")


def _add_tool_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--tool", default=None, metavar="FILE",
                        help="a tracked tool's tip: tool_calibration.json, an ITK/Slicer TipToProbe transform "
                             "(.h5/.tfm/.txt) or a PLUS device-set .xml (default: [tool] calibration, else the "
                             "pinhole probe)")


def _add_series_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--series", default=None, metavar="UID|NUMBER",
                        help="the DICOM series to use (Series Instance UID or series number; default: the CT "
                             "volume best for detection)")


def _add_study_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("name", metavar="NAME", help="calibration, board, tre, noise, markers, prediction, tool or trust")
    p.add_argument("--out", required=True, metavar="DIR")
    p.add_argument("--quick", action="store_true", help="a small frame and few sessions (a smoke-sized run)")
    p.add_argument("--scheduler", metavar="tcp://HOST:PORT", help="an existing Dask scheduler (default: a local one)")
    p.add_argument("--workers", type=int, default=None, metavar="N", help="local worker processes (default 2)")
    p.add_argument("--case", metavar="CASE", help="a simulated case folder with truth.json (default: simulate one)")
    p.add_argument("--work", metavar="DIR", help="where the simulated case and its detection are kept (OUT/work)")
    p.add_argument("--seed", type=int, default=1, help="seed of the simulated case")


def build_parser() -> argparse.ArgumentParser:
    """The ``emreg`` argument parser with every subcommand."""
    parser = _Parser(prog="emreg", description="Automatic patient-to-image registration for EM navigation.")
    parser.add_argument("--version", action="version", version=f"emreg {__version__}")
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--quiet", action="store_true", help="no progress output")
    common.add_argument("--settings", metavar="case.toml", help="settings file (default: the case's case.toml)")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    def add(name: str, func: Callable[[argparse.Namespace], int], help_text: str) -> argparse.ArgumentParser:
        p = sub.add_parser(name, parents=[common], help=help_text, description=help_text)
        p.set_defaults(func=func)
        return p

    p = add("simulate", cmd_simulate, "write a simulated case folder with its ground truth (truth.json)")
    p.add_argument("out", metavar="OUT")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--difficulty", choices=("standard", "hard"), default="standard")
    p.add_argument("--spacing", type=float, default=None, metavar="MM", help="CT voxel size in mm")
    p.add_argument("--probe-axis", choices=("+x_in", "+x_out", "none"), default=None,
                   help="probe convention of the recordings: +X into the hole (default), out of it, or "
                        "position only")
    p.add_argument("--tool-tip", type=float, nargs=3, default=None, metavar=("X", "Y", "Z"),
                   help="touch with a stylus whose tip is at X Y Z mm in its sensor's frame (pivoting at the "
                        "pinholes; writes tool_calibration.json, pivot.csv and [tool] calibration)")
    p.add_argument("--distortion", type=float, default=0.0, metavar="MM",
                   help="a steel rod beside the frame distorts the field: RMS non-rigid error (mm) it leaves at the "
                        "calibrated pinholes after the best rigid fit (truth.json 'distortion')")
    p.add_argument("--distortion-during", choices=("calibration", "navigation", "both"), default="both",
                   help="the recordings the rod is in (default both; the navigation is then recorded where the "
                        "frame was calibrated)")
    p.add_argument("--distortion-onset", type=float, default=None, metavar="S",
                   help="the rod is rolled in S seconds into the first recording it is in (default: there from "
                        "the start)")

    p = add("detect", cmd_detect, "find the markers in a CT: OUT/markers.json and markers.mrk.json")
    p.add_argument("ct", metavar="CT_OR_CASE", help="a CT file, a DICOM folder, or a case folder")
    p.add_argument("--out", required=True, metavar="OUT")
    _add_series_option(p)

    p = add("calibrate", cmd_calibrate, "frame calibration from a tracking recording: OUT/frame_calibration.json")
    p.add_argument("recording", metavar="RECORDING")
    p.add_argument("--out", required=True, metavar="OUT")
    _add_sensor_options(p)
    _add_tool_option(p)

    p = add("pivot", cmd_pivot, "pivot calibration of a tool's tip: OUT/tool_calibration.json and TipToProbe.h5")
    p.add_argument("recording", metavar="RECORDING", help="the tip resting in a divot while the tool swings")
    p.add_argument("--out", required=True, metavar="OUT")
    _add_sensor_options(p)

    p = add("register", cmd_register, "pair, solve the sensor offset, register: OUT/registration.json")
    p.add_argument("--markers", metavar="markers.json", help="the CT markers of emreg detect")
    p.add_argument("--fiducials", metavar="FILE",
                   help="fiducial points instead of CT markers: a Slicer markups file (.mrk.json in LPS or RAS, "
                        ".fcsv), a PLUS device-set XML with <PhantomDefinition> landmarks, or markers.json; "
                        "a rigid point fit of the calibration points (tool tips) onto them, no sensor offset")
    p.add_argument("--calibration", required=True, metavar="frame_calibration.json")
    p.add_argument("--targets", metavar="targets.mrk.json", help="targets for the predicted TRE")
    p.add_argument("--out", required=True, metavar="OUT")

    p = add("navigate", cmd_navigate, "map probe samples into image space (replay or live)")
    p.add_argument("--registration", required=True, metavar="registration.json")
    p.add_argument("--source", required=True, metavar="URL",
                   help="replay:FILE.csv, trakstar:///dev/ttyUSB0?baud=115200 or igtl://HOST:PORT")
    p.add_argument("--out", metavar="OUT")
    p.add_argument("--igtl-port", type=int, default=None, metavar="PORT", help="publish ProbeToImage over OpenIGTLink")
    _add_sensor_options(p)
    _add_tool_option(p)
    live.add_live_navigate_arguments(p)

    p = add("evaluate", cmd_evaluate, "TRE at targets and the board table: OUT/evaluation.json")
    p.add_argument("case", metavar="CASE")
    p.add_argument("--registration", required=True, metavar="registration.json")
    p.add_argument("--out", required=True, metavar="OUT")
    _add_sensor_options(p)
    _add_tool_option(p)

    p = add("convert", cmd_convert, "convert a tracking recording between CSV and a PLUS sequence metafile "
            "(.seq.mha, .mha, .seq.nrrd)")
    p.add_argument("input", metavar="IN")
    p.add_argument("output", metavar="OUT")
    p.add_argument("--quaternion", action="store_true", help="write CSV orientations as qw,qx,qy,qz")
    _add_sensor_options(p)

    p = add("report", cmd_report, "render the verification report: OUT/report.html")
    p.add_argument("out", nargs="?", metavar="OUT")
    p.add_argument("--case", metavar="CASE", help="the case folder (for the CT), when not recorded in OUT")
    p.add_argument("--batch", metavar="DIR", help="render a report in every output folder under DIR")
    p.add_argument("--jobs", type=int, default=1,
                   help="reports rendered at a time with --batch (lowered to what the available memory holds)")

    p = add("run", cmd_run, "run every stage on a case folder")
    p.add_argument("case", metavar="CASE")
    p.add_argument("--out", required=True, metavar="OUT")
    _add_series_option(p)
    _add_sensor_options(p)
    _add_tool_option(p)

    p = add("demo", cmd_demo, "simulate the built-in sample case and run it")
    p.add_argument("--out", default="demo-output", metavar="DIR")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--spacing", type=float, default=None, metavar="MM")

    _add_study_arguments(add("study", cmd_study,
                             "an accuracy study on simulated data, run on Dask: OUT/NAME.json, .csv, .png"))

    for name, add_arguments, run, help_text in live.SUBCOMMANDS:
        p = add(name, run, help_text)
        add_arguments(p)
    return parser


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread like Ctrl-C so that every ``finally`` and atomic write cleans up."""


def _on_sigterm(signum: int, frame: object) -> None:
    from .outputs import note_interrupt

    note_interrupt("SIGTERM")
    raise Terminated("SIGTERM")


def _on_sigint(signum: int, frame: object) -> None:
    from .outputs import note_interrupt

    note_interrupt("SIGINT")
    raise KeyboardInterrupt


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``emreg`` console script.

    SIGINT and SIGTERM end a command with one line on stderr and exit code 130 / 143; temporary
    files are removed on the way out and an interrupted ``emreg run`` says so in ``OUT/run.json``.
    """
    from .outputs import interrupted_by, note_interrupt

    parser = build_parser()
    args = parser.parse_args(argv)
    note_interrupt(None)
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _on_sigterm)
        if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
            signal.signal(signal.SIGINT, _on_sigint)
    try:
        try:
            return int(args.func(args) or 0)
        except (EMRegError, KeyboardInterrupt, OSError):
            raise
        except Exception:  # a signal's exception lost in a VTK callback (the filter then fails): the interrupt
            if interrupted_by() is None:
                raise
            raise (Terminated("SIGTERM") if interrupted_by() == "SIGTERM" else KeyboardInterrupt()) from None
    except EMRegError as exc:
        print(f"emreg {args.command}: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt as exc:
        terminated = isinstance(exc, Terminated)
        # CPython marks a KeyboardInterrupt that ends any string exec() (a dataclass or namedtuple being made
        # while Ctrl-C lands) as unhandled even once caught, and `python -m` then kills itself with SIGINT
        # instead of exiting 130 (bpo-41602's check in Py_RunMain). A string exec that ends normally clears it.
        exec("")
        print(f"emreg {args.command}: interrupted ({'SIGTERM' if terminated else 'SIGINT'}); no partial file "
              "was left in place of a complete one", file=sys.stderr)
        return 143 if terminated else 130
    except OSError as exc:  # a file-system failure no specific check foresaw: still one line, exit 2
        where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
        print(f"emreg {args.command}: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return EXIT_BAD_INPUT


def run() -> int:
    """The ``emreg`` console script (and ``python -m EMRegModule``): :func:`main`, in a process that ends with it.

    Every object the command made is frozen out of the garbage collector before the interpreter exits: its
    final collection would otherwise walk them all (0.12 s after a report with pyvista and VTK loaded, measured)
    only to free memory the process is about to give back. Not in :func:`main`, which callers in a longer-lived
    process (tests, the Slicer module) run too.
    """
    import gc

    code = main()
    gc.freeze()
    return code


if __name__ == "__main__":
    sys.exit(run())
