"""The ``emreg`` command: a thin face over the controller and the core modules.

Exit codes (spec): 0 success; 2 bad input or usage (one line naming the file and what is
wrong); 3 the data do not allow a safe answer. Every output file is written atomically.
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from . import __version__
from .errors import EXIT_BAD_INPUT, EMRegError, NoSafeAnswerError, StageNotAvailableError
from .progress import Progress

if TYPE_CHECKING:
    from .settings import Settings

#: Output files of each stage in OUT, in workflow order (used to clear stale results).
STAGE_OUTPUTS: dict[str, tuple[str, ...]] = {
    "detect": ("markers.json", "markers.mrk.json"),
    "calibrate": ("frame_calibration.json",),
    "register": ("registration.json", "ReferenceToImage.h5", "tre_map.nrrd"),
    "navigate": ("navigation.csv",),
    "evaluate": ("evaluation.json",),
    "report": ("report.html", "EMReg.mrb"),
}


class _Parser(argparse.ArgumentParser):
    """argparse with the spec's exit code 2 and a one-line message for usage errors."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.print_usage(sys.stderr)
        self.exit(EXIT_BAD_INPUT, f"{self.prog}: error: {message}\n")


def stage_available(module: str) -> bool:
    """True when the core module for a stage exists in this build."""
    return importlib.util.find_spec(f"EMRegModule.{module}") is not None


def _need_stage(module: str, what: str) -> None:
    if not stage_available(module):
        raise StageNotAvailableError(f"{what} is not built yet in this version of EMReg")


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


def _controller(args: argparse.Namespace, settings: Settings):
    from .controller import EMRegController

    controller = EMRegController(settings, _progress(args))
    controller.set_sensors(getattr(args, "reference_sensor", None), getattr(args, "probe_sensor", None))
    return controller


# --- subcommands ----------------------------------------------------------------------------


def cmd_simulate(args: argparse.Namespace) -> int:
    _need_stage("simulation", "the case simulator")
    _out_folder(args.out)
    from .simulation import simulate_case

    options = {"probe_axis": args.probe_axis} if args.probe_axis else {}
    simulate_case(
        Path(args.out), seed=args.seed, difficulty=args.difficulty, spacing_mm=args.spacing,
        progress=_progress(args), **options,
    )
    print(f"simulated case written to {args.out}")
    return 0


def cmd_detect(args: argparse.Namespace) -> int:
    _need_stage("detection", "marker detection")
    from .io.case import find_ct

    _out_folder(args.out)
    source = Path(args.ct)
    case_dir = source if source.is_dir() and find_ct(source) is not None else None
    ct_path = find_ct(source) if case_dir is not None else source
    controller = _controller(args, _with_series(_settings(args, case_dir), args))
    result = controller.load_ct_and_detect(ct_path)  # detects on the slices read while the rest arrives
    from .detection import write_detection

    write_detection(result, Path(args.out))
    print(f"{len(result.markers)} markers detected, {len(result.rejected)} candidates rejected -> {args.out}")
    return 0


def cmd_calibrate(args: argparse.Namespace) -> int:
    _need_stage("calibration", "frame calibration")
    from .calibration import write_frame_calibration

    _out_folder(args.out)
    controller = _controller(args, _settings(args))
    controller.load_calibration_recording(args.recording)
    result = controller.calibrate_frame()
    write_frame_calibration(result, Path(args.out) / "frame_calibration.json")
    _warn("calibrate", result.warnings)
    print(f"{len(result.points)} pinholes calibrated -> {args.out}")
    return 0


def cmd_register(args: argparse.Namespace) -> int:
    _need_stage("registration", "registration")
    from .calibration import read_frame_calibration
    from .detection import read_detection
    from .registration import write_registration

    _out_folder(args.out)
    controller = _controller(args, _settings(args))
    controller.set_detection(read_detection(args.markers))
    controller.set_frame_calibration(read_frame_calibration(args.calibration))
    targets = None
    if args.targets:
        from .io.markups import read_markups

        targets = read_markups(args.targets)[1]
    try:
        result = controller.register(targets)
    except NoSafeAnswerError:
        _remove_outputs(Path(args.out), "register")
        raise
    write_registration(result, Path(args.out))
    _warn("register", result.warnings)
    print(f"registered: FRE {result.fre_mm:.2f} mm, l = {result.sensor_offset_l_mm:.2f} mm, "
          f"{len(result.pairs)} pairs -> {args.out}")
    return 0


def cmd_navigate(args: argparse.Namespace) -> int:
    _out_folder(args.out)
    live = args.igtl_port is not None or not args.source.startswith("replay:")
    if live:
        _need_stage("live", "live navigation (tracker / OpenIGTLink)")
        from .live.commands import run_live_navigate

        return run_live_navigate(args)
    if not args.out:
        raise EMRegError("navigate: --out DIR is needed to write navigation.csv from a replay")
    _need_stage("navigation", "navigation")
    from .navigation import write_navigation_csv
    from .registration import max_fre_from_settings, read_registration

    settings = _settings(args)
    controller = _controller(args, settings)
    controller.set_registration(read_registration(args.registration, max_fre_from_settings(settings)))
    from .io.recording import read_recording

    recording = read_recording(args.source[len("replay:"):], controller.settings, controller.reference_sensor,
                               controller.probe_sensor)
    result = controller.navigate_recording(recording)
    _warn("navigate", recording.warnings)
    write_navigation_csv(result, Path(args.out) / "navigation.csv")
    print(f"{len(result)} probe samples mapped into image space -> {args.out}")
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    _need_stage("evaluation", "evaluation")
    from .evaluation import write_evaluation
    from .io.case import open_case
    from .registration import max_fre_from_settings, read_registration

    case = open_case(args.case)
    _out_folder(args.out)
    if case.navigation is None and case.board is None:
        raise EMRegError(f"{case.folder}: nothing to evaluate: no navigation recording (navigation.csv) and no "
                         "board recording (board.csv) in the case folder")
    if case.navigation is not None and case.targets is None and case.board is None:
        raise EMRegError(f"{case.folder}: nothing to evaluate: a navigation recording but no targets.mrk.json "
                         "(and no board.csv)")
    if args.settings:
        case.settings = _settings(args)
    case.settings = case.settings.with_sensors(args.reference_sensor, args.probe_sensor)  # sequence files' ports
    controller = _controller(args, case.settings)
    controller.set_registration(read_registration(args.registration, max_fre_from_settings(case.settings)))
    result = controller.evaluate(case.read_recording("navigation"), case.read_targets(), case.read_recording("board"))
    write_evaluation(result, Path(args.out) / "evaluation.json")
    _warn("evaluate", result.warnings)
    print(f"evaluation -> {Path(args.out) / 'evaluation.json'}")
    return 0


def cmd_convert(args: argparse.Namespace) -> int:
    from .io.recording import write_recording
    from .io.sequence_metafile import is_sequence_file, read_sequence_frames, recording_from_frames
    from .io.tracking_csv import read_tracking_csv

    sensors = _settings(args).sensors
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
    else:
        recording, others = read_tracking_csv(source), {}
    write_recording(recording, target, {"sensors": names}, reference, probe,
                    orientation="quaternion" if args.quaternion else None)
    _warn("convert", recording.warnings)
    extra = ("; other transforms as sensor ports " + ", ".join(f"{n} = {p}" for n, p in others.items())
             if others else "")
    print(f"{len(recording)} sensor samples converted -> {target}{extra}")
    return 0


def cmd_report(args: argparse.Namespace) -> int:
    _need_stage("report", "the verification report")
    from .report import write_reports_batch
    from .report.writer import write_report_keeping_ct

    if args.batch:
        batch = Path(args.batch)
        if not batch.is_dir():
            raise EMRegError(f"{batch}: folder of run outputs not found")
        folders = sorted(p for p in batch.iterdir() if p.is_dir())
        bundles: list = []  # each job writes its case's bundle with the CT its report read
        pages = write_reports_batch(folders, jobs=args.jobs, progress=_progress(args), bundles=bundles)
        print(f"{len(pages)} reports written under {args.batch}")
        for _, (path, message) in bundles:
            print(_bundle_line(path, message))
        return 0
    if not args.out:
        raise EMRegError("report: give an output folder (emreg report OUT) or --batch DIR")
    _out_folder(args.out, create=False)  # the run's folder: the report is written into it
    case = Path(args.case) if args.case else None
    path, image = write_report_keeping_ct(Path(args.out), case_dir=case, progress=_progress(args))
    print(f"report -> {path}")
    print(slicer_bundle(Path(args.out), case, image, progress=_progress(args)))  # the report's CT, not re-read
    return 0


def slicer_bundle(out: Path, case_dir: Path | None = None, image=None, progress: Progress | None = None) -> str:
    """Write ``OUT/EMReg.mrb`` (3D Slicer scene bundle) from the outputs in OUT; one summary line.

    Optional: without slicer-core, or when the bundle cannot be written (disk full, no
    permission), the rest of the outputs stand, a warning says why and the exit code is unchanged.
    """
    from .io.slicer_scene import write_run_bundle

    with (progress or Progress(enabled=False)).step("writing the 3D Slicer scene bundle"):
        path, message = write_run_bundle(out, case_dir, image)
    return _bundle_line(path, message)


def _bundle_line(path, message: str) -> str:
    """The summary line of a scene bundle; one that could not be written is also a warning."""
    if path is None:
        _warn("bundle", [message])
    return f"bundle: {message}"


def cmd_run(args: argparse.Namespace) -> int:
    _out_folder(args.out)
    summary = run_case(Path(args.case), Path(args.out), _progress(args), reference_sensor=args.reference_sensor,
                       probe_sensor=args.probe_sensor, settings_path=args.settings, series=args.series)
    for line in summary:
        print(line)
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    _need_stage("simulation", "the case simulator")
    from .simulation import simulate_case

    out = _out_folder(args.out)
    case_dir = out / "case"
    progress = _progress(args)
    start = time.perf_counter()
    progress.message(f"[emreg] demo: simulating the sample case into {case_dir}")
    simulate_case(case_dir, seed=args.seed, difficulty="standard", spacing_mm=args.spacing, progress=progress)
    summary = run_case(case_dir, out / "result", progress)
    for line in summary:
        print(line)
    print(f"demo finished in {time.perf_counter() - start:.1f} s; outputs in {out / 'result'}")
    return 0


def cmd_study(args: argparse.Namespace) -> int:
    from .studies import STUDIES, format_table, run_study

    summary = run_study(args.name, Path(args.out), quick=args.quick, scheduler=args.scheduler, workers=args.workers,
                        case_dir=Path(args.case) if args.case else None,
                        work=Path(args.work) if args.work else None, seed=args.seed, progress=_progress(args))
    print(f"{STUDIES[args.name].title}\n")
    print(format_table(summary))
    print(f"\n-> {Path(args.out) / args.name}.json, .csv, .png")
    return 0


def _remove_outputs(out: Path, from_stage: str) -> None:
    """Delete the outputs of ``from_stage`` and every later stage (stale after a refusal)."""
    stages = list(STAGE_OUTPUTS)
    for stage in stages[stages.index(from_stage):]:
        for name in STAGE_OUTPUTS[stage]:
            (out / name).unlink(missing_ok=True)


def run_case(
    case_dir: Path, out: Path, progress: Progress, reference_sensor: int | None = None,
    probe_sensor: int | None = None, settings_path: str | None = None, series: str | None = None,
) -> list[str]:
    """Run every available stage on a case folder through the controller; returns summary lines.

    ``OUT/run.json`` records the case folder, the CT, the sensor ports and the summary (the
    report finds the CT through it).
    A stage that refuses (no safe answer) removes its own and all later outputs from OUT,
    so no stale result of an earlier run can be mistaken for this one's, then re-raises.
    Once the registration stands, an optional recording that cannot be used (navigation, TRE
    targets, board) does not fail the run: the part is "not evaluated" with its reason in
    ``run.json`` (``not_evaluated``), ``evaluation.json`` and the report, and on stderr.
    """
    from .controller import EMRegController
    from .io.atomic import atomic_write_json
    from .io.case import open_case
    from .settings import load_settings, with_series

    case = open_case(case_dir)
    if settings_path:
        case.settings = load_settings(settings_path, required=True)
    case.settings = with_series(case.settings, series)
    if case.ct is None:
        raise EMRegError(f"{case_dir}: no CT found (ct.nrrd, ct.nii.gz, ct.mha or a ct/ DICOM folder)")
    case.settings = case.settings.with_sensors(reference_sensor, probe_sensor)  # a sequence file's ports too
    controller = EMRegController.for_case(case, progress)
    controller.set_sensors(reference_sensor, probe_sensor)
    out.mkdir(parents=True, exist_ok=True)
    summary: list[str] = []
    run_record = {"case": str(case.folder.resolve()), "ct": str(case.ct.resolve()), "emreg_version": __version__,
                  "reference_sensor": controller.reference_sensor, "probe_sensor": controller.probe_sensor,
                  "summary": summary}
    not_made: dict[str, str] = {}
    run_record["not_evaluated"] = not_made
    atomic_write_json(out / "run.json", run_record)
    current = "detect"
    try:
        if stage_available("detection"):
            from .detection import write_detection

            detection = controller.load_ct_and_detect(case.ct)
            if detection.ct_series is not None:
                run_record["ct_series"] = detection.ct_series
            write_detection(detection, out)
            summary.append(f"detect: {len(detection.markers)} markers, {len(detection.rejected)} rejected")
        else:
            summary.append("detect: not built yet, skipped")
        current = "calibrate"
        if case.calibration is not None and stage_available("calibration"):
            from .calibration import write_frame_calibration

            controller.load_calibration_recording(case.calibration)
            calibration = controller.calibrate_frame()
            write_frame_calibration(calibration, out / "frame_calibration.json")
            if controller.detection is None:  # otherwise the registration repeats them
                _warn("run", calibration.warnings)
            summary.append(f"calibrate: {len(calibration.points)} pinholes")
        current = "register"
        if controller.detection is not None and controller.frame_calibration is not None \
                and stage_available("registration"):
            from .registration import write_registration

            targets = None
            if case.targets is not None:
                from .io.markups import read_markups

                targets = read_markups(case.targets)[1]
            registration = controller.register(targets)
            write_registration(registration, out)
            _warn("run", registration.warnings)
            summary.append(f"register: FRE {registration.fre_mm:.2f} mm, l = "
                           f"{registration.sensor_offset_l_mm:.2f} mm, {len(registration.pairs)} pairs")
        current = "navigate"
        if controller.registration is not None and case.navigation is not None \
                and stage_available("navigation"):
            from .navigation import write_navigation_csv

            try:
                navigation_recording = case.read_recording("navigation")
                navigation = controller.navigate_recording(navigation_recording)
            except NoSafeAnswerError:
                raise
            except EMRegError as exc:  # the registration stands; an unusable navigation recording is reported
                not_made["navigation"] = str(exc)
                print(f"emreg run: warning: navigation not made: {exc}", file=sys.stderr)
                summary.append(f"navigate: not made: {exc}")
            else:
                _warn("run", navigation_recording.warnings)
                write_navigation_csv(navigation, out / "navigation.csv")
                summary.append(f"navigate: {len(navigation)} probe samples")
        current = "evaluate"
        evaluation = None
        if controller.registration is not None and stage_available("evaluation") \
                and (case.navigation is not None or case.board is not None):
            from .evaluation import write_evaluation

            unreadable: dict[str, str] = {}
            inputs: dict[str, object] = {}
            for part, read in (("tre", lambda: (case.read_recording("navigation"), case.read_targets())),
                               ("board", lambda: case.read_recording("board"))):
                try:
                    inputs[part] = read()
                except NoSafeAnswerError:
                    raise
                except EMRegError as exc:  # an unreadable optional recording: that part is not evaluated
                    unreadable[part] = str(exc)
            navigation_input, targets_input = inputs.get("tre") or (None, None)
            evaluation = controller.evaluate(navigation_input, targets_input, inputs.get("board"),
                                             tolerant=True, not_evaluated=unreadable)
            for part, reason in evaluation.not_evaluated.items():
                not_made[part] = reason
                print(f"emreg run: warning: {'TRE' if part == 'tre' else part} not evaluated: {reason}",
                      file=sys.stderr)
            write_evaluation(evaluation, out / "evaluation.json")
            summary.extend(evaluation.summary())
        if controller.error_model is not None:
            from .tre_map import write_tre_map

            tracking_rms = evaluation.tre.tracking_rms_mm if evaluation and evaluation.tre else None
            write_tre_map(out / "tre_map.nrrd", controller.error_model, controller.detection.image,
                          None if tracking_rms is None else tracking_rms**2)
        current = "report"
        if stage_available("report"):
            from .report import write_report

            page = write_report(out, case_dir=case.folder, progress=progress, image=controller.image)
            summary.append(f"report: {page}")
    except NoSafeAnswerError as exc:
        _remove_outputs(out, current)
        summary.append(f"{current}: refused: {exc}")
        atomic_write_json(out / "run.json", run_record)
        raise
    summary.append(slicer_bundle(out, case.folder, controller.image, progress))
    atomic_write_json(out / "run.json", run_record)
    return summary


# --- parser -----------------------------------------------------------------------------------


def _add_sensor_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--reference-sensor", type=int, default=None, metavar="PORT",
                        help="port of the reference sensor (default 1 or case.toml [sensors])")
    parser.add_argument("--probe-sensor", type=int, default=None, metavar="PORT",
                        help="port of the probe sensor (default 2 or case.toml [sensors])")


def _add_series_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--series", default=None, metavar="UID|NUMBER",
                        help="the DICOM series to use (Series Instance UID or series number; default: the CT "
                             "volume best for detection)")


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

    p = add("detect", cmd_detect, "find the markers in a CT: OUT/markers.json and markers.mrk.json")
    p.add_argument("ct", metavar="CT_OR_CASE", help="a CT file, a DICOM folder, or a case folder")
    p.add_argument("--out", required=True, metavar="OUT")
    _add_series_option(p)

    p = add("calibrate", cmd_calibrate, "frame calibration from a tracking recording: OUT/frame_calibration.json")
    p.add_argument("recording", metavar="RECORDING")
    p.add_argument("--out", required=True, metavar="OUT")
    _add_sensor_options(p)

    p = add("register", cmd_register, "pair, solve the sensor offset, register: OUT/registration.json")
    p.add_argument("--markers", required=True, metavar="markers.json")
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
    if stage_available("live"):
        from .live.commands import add_live_navigate_arguments

        add_live_navigate_arguments(p)

    p = add("evaluate", cmd_evaluate, "TRE at targets and the board table: OUT/evaluation.json")
    p.add_argument("case", metavar="CASE")
    p.add_argument("--registration", required=True, metavar="registration.json")
    p.add_argument("--out", required=True, metavar="OUT")
    _add_sensor_options(p)

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

    p = add("demo", cmd_demo, "simulate the built-in sample case and run it")
    p.add_argument("--out", default="demo-output", metavar="DIR")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--spacing", type=float, default=None, metavar="MM")

    p = add("study", cmd_study, "an accuracy study on simulated data, run on Dask: OUT/NAME.json, .csv, .png")
    p.add_argument("name", metavar="NAME", help="calibration, board, tre, noise, markers or prediction")
    p.add_argument("--out", required=True, metavar="DIR")
    p.add_argument("--quick", action="store_true", help="a small frame and few sessions (a smoke-sized run)")
    p.add_argument("--scheduler", metavar="tcp://HOST:PORT", help="an existing Dask scheduler (default: a local one)")
    p.add_argument("--workers", type=int, default=None, metavar="N", help="local worker processes (default 2)")
    p.add_argument("--case", metavar="CASE", help="a simulated case folder with truth.json (default: simulate one)")
    p.add_argument("--work", metavar="DIR", help="where the simulated case and its detection are kept (OUT/work)")
    p.add_argument("--seed", type=int, default=1, help="seed of the simulated case")

    if stage_available("live"):
        from .live import commands as live

        for name, add_arguments, run, help_text in live.SUBCOMMANDS:
            p = add(name, run, help_text)
            add_arguments(p)
    else:
        for name in ("record", "sim-tracker", "serve"):
            p = add(name, _not_built(name), f"{name} (not built yet)")
            p.add_argument("rest", nargs=argparse.REMAINDER)
    return parser


def _not_built(name: str) -> Callable[[argparse.Namespace], int]:
    def run(args: argparse.Namespace) -> int:
        raise StageNotAvailableError(f"'emreg {name}' is not built yet in this version of EMReg")

    return run


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``emreg`` console script."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except EMRegError as exc:
        print(f"emreg {args.command}: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print(f"emreg {args.command}: interrupted", file=sys.stderr)
        return 130
    except OSError as exc:  # a file-system failure no specific check foresaw: still one line, exit 2
        where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
        print(f"emreg {args.command}: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return EXIT_BAD_INPUT


if __name__ == "__main__":
    sys.exit(main())
