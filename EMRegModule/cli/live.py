"""The live commands: ``emreg record``, ``emreg sim-tracker``, ``emreg serve`` and live ``emreg navigate``.

:func:`add_parsers` adds the subcommands of :data:`SUBCOMMANDS` (name, add_arguments, run, help); ``emreg navigate``
(:mod:`.stages`) hands itself to :func:`run_live_navigate` when ``--igtl-port`` is given or the source is not a
``replay:`` file. Every loop here stops by itself with ``--duration`` / ``--max-samples`` (or on
Ctrl-C / SIGTERM), and releases the serial port, the sockets and the pty.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..errors import EMRegError
from ..names import CHECKPOINTS_JSON, DEFAULT_IGTL_PORT, DEFAULT_TRAKSTAR_BAUD, NAVIGATION_CSV, REGISTRATION_JSON
from .args import AddCommand, sensor_ports
from .live_guidance import live_guidance_summary, live_tool_and_guide, tip_device_name, write_live_guidance

# The tracker and OpenIGTLink modules (pyigtl, the trakSTAR protocol, the link guard) are imported by the commands
# that run them: every command builds this module's parsers, ``emreg detect`` among them.

if TYPE_CHECKING:
    from ..core.registration import RegistrationResult

# --- shared helpers ---------------------------------------------------------------------------


def _check_ports_attached(source, reference: int, probe: int, tool=None) -> None:
    """Refuse (exit 2) a reference or probe port without a sensor, when the source can tell; a replay's
    recording is judged whole, as the offline commands judge it (absent, still or swapped ports). ``tool``: the
    tool on the probe port, refused on a 5-DOF sensor unless its tip lies on the sensor's axis
    (:func:`~EMRegModule.live.guide_setup.check_tool_on_port`)."""
    check = getattr(source, "check_ports", None)
    if callable(check):
        try:
            check(reference, probe)
        except EMRegError:
            source.stop()
            raise
    if tool is not None:
        from ..live.guide_setup import check_tool_on_port

        try:
            check_tool_on_port(source, probe, tool)
        except EMRegError:
            source.stop()
            raise
    ports = getattr(source, "attached_ports", None)
    if not callable(ports):
        return
    attached = ports()
    for role, port in (("reference", reference), ("probe", probe)):
        if port not in attached:
            source.stop()
            what = "" if tool is None or role == "reference" else f" for the tool of {tool.source}"
            raise EMRegError(f"{source.description}: no sensor on the {role} port {port}{what} (sensors on ports "
                             f"{', '.join(map(str, attached)) or 'none'}); set --{role}-sensor")


def load_registration(path: str, settings_path: str | None = None) -> RegistrationResult:
    """The registration of ``registration.json`` (``ReferenceToImage``: 4x4, mm, LPS), via the registration module.

    The file is checked as every consumer checks it (finite, rigid, FRE within ``max_fre_mm`` of
    the settings file when given, and belonging to the run recorded beside it: no stale registration).
    """
    from ..core.registration import max_fre_from_settings, read_registration
    from ..io.provenance import check_belongs
    from ..settings import load_settings

    settings = load_settings(settings_path, required=True)
    registration = read_registration(path, max_fre_from_settings(settings))
    check_belongs(Path(path) / REGISTRATION_JSON if Path(path).is_dir() else Path(path))
    return registration


class _StopFlag:
    """Set by SIGTERM / SIGINT so loops end cleanly (the previous handlers come back afterwards)."""

    def __init__(self) -> None:
        self.event = threading.Event()
        self._previous: dict[int, object] = {}

    def __enter__(self) -> _StopFlag:
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGTERM, signal.SIGINT):
                self._previous[sig] = signal.signal(sig, lambda *_: self.event.set())
        return self

    def __exit__(self, *exc: object) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)


def _run_loop(source, stop: _StopFlag, duration_s: float | None, done: Callable[[], bool],
              tick: Callable[[], object] | None = None, interval_s: float = 0.01) -> str:
    """Wait until the source ends, a limit is reached or a signal arrives; returns why."""
    deadline = None if duration_s is None else time.monotonic() + duration_s
    while True:
        if stop.event.wait(interval_s):
            return "interrupted"
        if tick is not None:
            tick()
        if source.error:
            raise EMRegError(source.error)
        if done():
            return "sample limit reached"
        if deadline is not None and time.monotonic() >= deadline:
            return "duration reached"
        if source.finished.is_set():
            return "source finished"


#: ``(option, attribute, what it must be)`` of the live commands' numeric options: zero or a negative value is
#: a usage error (exit 2, one line), never a loop that ends at once or never (``--reconnect 0`` keeps its
#: documented meaning, end at once; ``--max-quality`` -1 means "do not check").
_POSITIVE_OPTIONS = (("--duration", "duration", "a positive number of seconds"),
                     ("--max-samples", "max_samples", "a positive number of samples"),
                     ("--max-records", "max_records", "a positive number of records"),
                     ("--stale-periods", "stale_periods", "a positive number of sample periods"),
                     ("--rate", "rate", "a positive rate in Hz"))


def check_live_options(args: argparse.Namespace) -> None:
    """Refuse (:class:`EMRegError`, exit 2, one line) a live command's option outside its range: ``--duration``,
    ``--max-samples``, ``--max-records``, ``--stale-periods``, ``--rate`` not positive (or not finite), a negative
    ``--reconnect``, an ``--igtl-port`` outside 0..65535 (0: any free port)."""
    for option, name, what in _POSITIVE_OPTIONS:
        value = getattr(args, name, None)
        if value is not None and not (np.isfinite(value) and value > 0):
            raise EMRegError(f"{option} {value:g}: give {what}")
    reconnect = getattr(args, "reconnect", None)
    if reconnect is not None and not (np.isfinite(reconnect) and reconnect >= 0):
        raise EMRegError(f"--reconnect {reconnect:g}: give the seconds to try reconnecting (0: end at once)")
    port = getattr(args, "igtl_port", None)
    if port is not None and not 0 <= port <= 65535:
        raise EMRegError(f"--igtl-port {port}: a TCP port is 1..65535 (0: any free port)")


def _add_limits(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds")
    parser.add_argument("--max-samples", type=int, default=None, metavar="N", help="stop after N samples / frames")


def _add_replay_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--fast", action="store_true", help="replay: as fast as possible, not at the recording's rate")
    parser.add_argument("--loop", action="store_true", help="replay: start again at the end")


def _add_watchdog_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--max-quality", type=float, default=None, metavar="Q",
                        help="worst acceptable tracker quality number, 0 = best (default: 20 for the trakSTAR's "
                             "METAL number, 1 mm for the Aurora's RMS error; -1: do not check)")
    parser.add_argument("--stale-periods", type=float, default=3.0, metavar="K",
                        help="data are stale after K sample periods without a sample (default 3)")


def _max_quality(args: argparse.Namespace) -> float | None:
    if args.max_quality is None:  # not given: the source's own scale, else the trakSTAR's
        from ..live.navigator import DEFAULT_MAX_QUALITY

        return float(getattr(args, "source_max_quality", None) or DEFAULT_MAX_QUALITY)
    return None if args.max_quality < 0 else args.max_quality


def _say(args: argparse.Namespace, text: str) -> None:
    if not getattr(args, "quiet", False):
        print(text, file=sys.stderr, flush=True)


def _framing_text(source) -> str | None:
    """The tracker driver's framing counters in one line (None for a source without a serial link)."""
    if hasattr(source, "framing_summary"):  # the Aurora's own counters
        return source.framing_summary().removeprefix("[emreg] ")
    driver = getattr(source, "driver", None)
    if driver is None:
        return None
    st = driver.stats
    return (f"trakSTAR records: {st.records} accepted, {st.rejected} rejected (phase {st.phase_errors}, address "
            f"{st.address_errors}, follow {st.follow_errors}, gap {st.gap_errors}, values {st.value_errors}), "
            f"{st.stray_bytes} stray bytes")


def _report_framing(args: argparse.Namespace, source) -> None:
    text = _framing_text(source)
    if text is not None:
        _say(args, f"[emreg] {text}")


# --- emreg sim-tracker -------------------------------------------------------------------------


def add_sim_tracker_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", choices=("trakstar", "aurora"), default="trakstar",
                        help="trakstar (Flock-of-Birds binary RS-232) or aurora (NDI serial API: BX/TX, CRC16)")
    parser.add_argument("--tools", default=None, metavar="1:6dof,2:5dof,...",
                        help="aurora: tools on ports 1-4 (6dof, 5dof, 5dof2 = two on a splitter, nosrom, none); "
                             "default: a 6-DOF tool on every port the scene has")
    parser.add_argument("--rate", type=float, default=None, metavar="HZ",
                        help="aurora: measuring rate (default 40 Hz; a replay: its recording's rate)")
    parser.add_argument("--freeze-tag", default=None, metavar="TAG",
                        help="aurora: firmware tag VER reports (default 'AURORA Rev 013'; 'AURORA Rev 008' makes "
                             "scikit-surgerynditracker use TX)")
    parser.add_argument("--replay", metavar="FILE.csv", help="replay this tracking recording (default: built-in scene)")
    parser.add_argument("--fast", action="store_true", help="STREAM as fast as the baud rate allows")
    parser.add_argument("--baud", type=int, default=DEFAULT_TRAKSTAR_BAUD,
                        help=f"line speed to emulate (default {DEFAULT_TRAKSTAR_BAUD})")
    parser.add_argument("--link", metavar="PATH", help="also make PATH a symbolic link to the pty (like socat's link)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the scene and of the faults")
    parser.add_argument("--fault", action="append", default=[], metavar="KIND=VALUE",
                        help="inject faults: drop=P, flip=P, corrupt=P (per byte), stall=EVERY_S:DURATION_S, "
                             "late=P:DELAY_S (a POINT reply DELAY_S late), "
                             "unplug=SENSOR@START-END, out-of-range=SENSOR@START-END (repeatable)")
    parser.add_argument("--attached", default=None, metavar="1,2,3,4", help="ports with a sensor (default all)")
    parser.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds")
    parser.add_argument("--max-records", type=int, default=None, metavar="N", help="stop after N records sent")
    parser.add_argument("--emit-log", metavar="FILE.csv", help="at exit, write every record sent: seq, sensor, "
                        "monotonic ns of its last byte, truth position (for latency measurements)")
    parser.add_argument("--distortion", default=None, metavar="MM[@X,Y,Z,R]",
                        help="field distortion the tracker flags: MM everywhere, or MM at R mm from a metal object at "
                             "X,Y,Z (tracker frame, falling off as 1/r^3); trakstar: the METAL byte (40 per mm), "
                             "aurora: the tools' RMS error (+MM)")
    parser.add_argument("--volume", default=None, metavar="X0,Y0,Z0,X1,Y1,Z1[:MARGIN]",
                        help="aurora: the characterised volume (tracker frame, mm): a tool outside is out of volume, "
                             "within MARGIN (10) mm of a face partly out")


def run_sim_tracker(args: argparse.Namespace) -> int:
    check_live_options(args)
    if args.model == "aurora":
        return _run_aurora_simulator(args)
    from ..devices.simulator.faults import FaultPlan
    from ..devices.simulator.scene import BuiltinScene, ReplayScene
    from ..devices.simulator.trakstar import TrackerSimulator
    from ..devices.trakstar.driver import sensors_from_list

    scene = BuiltinScene(args.seed)
    if args.replay:
        from ..io.recording import read_recording

        scene = ReplayScene(read_recording(args.replay))
    attached = sensors_from_list(args.attached) if args.attached else None
    distortion, _ = _flags(args)
    sim = TrackerSimulator(scene, baud=args.baud, faults=FaultPlan.parse(args.fault), seed=args.seed, link=args.link,
                           fast=args.fast, max_records=args.max_records, duration_s=args.duration, attached=attached,
                           keep_truth=bool(args.emit_log))
    sim.distortion = distortion
    link = f" (link {args.link})" if args.link else ""
    print(f"trakSTAR simulator on {sim.path}{link}: connect with trakstar://{sim.path}?baud={args.baud}", flush=True)
    _run_until_stopped(sim)
    if args.emit_log:
        _write_emit_log(args.emit_log, "seq,sensor,emit_ns,status,corrupted,x_mm,y_mm,z_mm,azimuth_deg,elevation_deg,"
                        "roll_deg", (f"{r.seq},{r.sensor},{r.emit_ns},{r.status},{int(r.corrupted)},"
                                     + ",".join(f"{v:.6f}" for v in (*r.pose.position_mm, *r.pose.angles_deg))
                                     for r in sim.truth if r.emit_ns))
    _say(args, f"simulator stopped after {sim.records_sent} records")
    return 0


def _flags(args: argparse.Namespace) -> tuple:
    """(distortion model, measurement volume) of ``--distortion`` / ``--volume`` (None each when not given),
    checked before the simulator opens its pty (:mod:`EMRegModule.simulation.tracker_flags`)."""
    if args.distortion is None and args.volume is None:
        return None, None
    from ..simulation.tracker_flags import parse_distortion, parse_volume

    if args.volume is not None and args.model != "aurora":
        raise EMRegError("--volume: only the aurora simulator reports a tool out of its volume")
    return (None if args.distortion is None else parse_distortion(args.distortion),
            None if args.volume is None else parse_volume(args.volume))


def _run_until_stopped(sim) -> None:
    """Run a simulator until it ends by itself or SIGINT/SIGTERM asks it to stop; close it either way."""
    with _StopFlag() as stop:
        watcher = threading.Thread(target=lambda: (stop.event.wait(), sim._stop.set()), daemon=True)
        watcher.start()
        try:
            sim.run()
        finally:
            stop.event.set()
            sim.close()


def _write_emit_log(path: str, header: str, lines: Iterable[str]) -> None:
    """The simulator's log of what it emitted (the tests' truth), as CSV, atomically."""
    from ..io.atomic import atomic_write_text

    atomic_write_text(path, "\n".join([header, *lines]) + "\n")


def _run_aurora_simulator(args: argparse.Namespace) -> int:
    from ..devices.aurora import protocol as ndi
    from ..devices.simulator.aurora import AuroraSimulator, parse_tools
    from ..devices.simulator.faults import AuroraFaults
    from ..devices.simulator.scene import BuiltinScene, ReplayScene

    scene = BuiltinScene(args.seed)
    if args.replay:
        from ..io.recording import read_recording

        scene = ReplayScene(read_recording(args.replay))
    distortion, volume = _flags(args)
    sim = AuroraSimulator(scene, tools=parse_tools(args.tools) if args.tools else None, rate_hz=args.rate,
                          faults=AuroraFaults.parse(args.fault), seed=args.seed, link=args.link,
                          duration_s=args.duration, freeze_tag=args.freeze_tag or ndi.DEFAULT_FREEZE_TAG,
                          keep_log=bool(args.emit_log))
    sim.distortion, sim.volume = distortion, volume
    # a device does not pause mid-reply; ndicapi gives up on a reply after 0.1 s of silence while probing,
    # so on a loaded host the simulator asks for a higher priority where it may (choice; root only)
    with contextlib.suppress(OSError):
        os.nice(-5)
    link = f" (link {args.link})" if args.link else ""
    tools = ", ".join(f"port {t.port}{'/' + str(t.channel) if t.channel else ''}: {t.dof}-DOF"
                      + ("" if t.srom else " without SROM") for t in sim.tools)
    print(f"Aurora simulator on {sim.path}{link}: connect with aurora://{sim.path}?baud=115200 "
          f"({sim.rate_hz:g} Hz; {tools})", flush=True)
    _run_until_stopped(sim)
    if args.emit_log:
        _write_emit_log(args.emit_log, "frame,command,emit_ns,corrupted",
                        (f"{f.frame},{f.command},{f.emit_ns},{int(f.corrupted)}" for f in sim.log if f.emit_ns))
    _say(args, f"simulator stopped after {sim.frames_sent} BX/TX replies")
    return 0


# --- emreg record ---------------------------------------------------------------------------


def add_record_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--device", required=True, metavar="URL",
                        help="trakstar:///dev/ttyUSB0?baud=115200, aurora:///dev/ttyUSB0, igtl://HOST:PORT or "
                             "replay:FILE.csv")
    parser.add_argument("--out", required=True, metavar="rec.csv",
                        help="tracking CSV to write (flushed every second), or a PLUS sequence metafile "
                             "rec.seq.mha (written at the end; samples kept meanwhile in rec.seq.mha.partial.csv); "
                             f"a recording whose reference or probe has under {100 * MIN_RECORDED_SHARE:g} %% of "
                             "the expected samples exits 3 and is removed, or moved to OUT.incomplete")
    parser.add_argument("--reference-sensor", type=int, default=None, metavar="PORT")
    parser.add_argument("--probe-sensor", type=int, default=None, metavar="PORT")
    _add_limits(parser)
    _add_replay_options(parser)


def run_record(args: argparse.Namespace) -> int:
    check_live_options(args)
    from ..devices.link_quality import HoldBack, guard_for
    from ..devices.sources import open_source
    from ..io.sequence_metafile import is_sequence_file
    from ..live.writers import RecordingWriter, SequenceRecordingWriter

    reference, probe = sensor_ports(args)
    from .args import out_file

    out_file(args.out)
    source = open_source(args.device, reference, probe, fast=args.fast, loop=args.loop)
    writer = (SequenceRecordingWriter(args.out, reference_port=reference, probe_port=probe)
              if is_sequence_file(args.out) else RecordingWriter(args.out))
    rows = {reference: 0, probe: 0}
    count = [0]
    lock = threading.Lock()

    def write(sample) -> None:
        if args.max_samples is not None and count[0] >= args.max_samples:
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
                _say(args, f"[emreg] record: {'not recording' if paused[0] else 'recording again'}: {state.message}")

    _say(args, f"[emreg] recording {source.description} -> {args.out}")
    try:
        with _StopFlag() as stop:
            started = time.monotonic()
            source.start(on_sample)
            why = _run_loop(source, stop, args.duration,
                            lambda: args.max_samples is not None and count[0] >= args.max_samples)
            elapsed_s = time.monotonic() - started
    finally:
        source.stop()
        with lock:
            if held is not None:
                held.close()
        writer.close()
    _refuse_short_recording(args.out, writer, source, guard, rows, (reference, probe),
                            None if why == "sample limit reached" else elapsed_s)
    print(f"{writer.rows} samples recorded -> {args.out} ({why})")
    _report_framing(args, source)
    return 0


#: Share of the expected samples (the frames a replay sent; else the measurement cycles the tracker's rate gives
#: over the recording's time) that the reference and the probe must each reach for ``emreg record`` to succeed.
#: A clean link delivers all of them (measured: 100 %); under the link alarm nothing is recorded, and a
#: recording missing more than half its samples is more gap than recording (dwells cut short, motion unseen):
#: exit 3, never a success.
MIN_RECORDED_SHARE = 0.5


def _refuse_short_recording(out: str, writer, source, guard, rows: dict[int, int], ports: tuple[int, int],
                            elapsed_s: float | None) -> None:
    """Exit 3 (:class:`NoSafeAnswerError`, one line with the link guard's figures) when the reference or the probe
    has no sample or (``elapsed_s`` given: the recording was not ended by its sample limit) fewer than
    :data:`MIN_RECORDED_SHARE` of those expected; the file at ``out`` is then removed (no usable row) or moved
    aside to ``out.incomplete``."""
    from ..errors import NoSafeAnswerError

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
    framing = _framing_text(source)
    reference, probe = ports
    raise NoSafeAnswerError(f"{out}: not a usable recording: {rows[reference]} reference (port {reference}) and "
                            f"{rows[probe]} probe (port {probe}) samples{of}; {cause}"
                            + (f"; {framing}" if framing else "") + kept)


# --- emreg serve ------------------------------------------------------------------------------


def add_serve_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--device", required=True, metavar="URL",
                        help="trakstar:///dev/ttyUSB0?baud=115200, aurora:///dev/ttyUSB0, igtl://HOST:PORT or "
                             "replay:FILE.csv")
    parser.add_argument("--igtl-port", type=int, default=DEFAULT_IGTL_PORT, metavar="PORT",
                        help=f"OpenIGTLink port (default {DEFAULT_IGTL_PORT})")
    parser.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    parser.add_argument("--reference-sensor", type=int, default=None, metavar="PORT")
    parser.add_argument("--probe-sensor", type=int, default=None, metavar="PORT")
    _add_limits(parser)
    _add_replay_options(parser)
    _add_watchdog_options(parser)


def run_serve(args: argparse.Namespace) -> int:
    check_live_options(args)
    from ..devices.igtl_server import IGTLServer
    from ..devices.link_quality import guard_for
    from ..devices.sources import open_source
    from ..live.navigator import TrackerPublisher

    reference, probe = sensor_ports(args)
    source = open_source(args.device, reference, probe, fast=args.fast, loop=args.loop)
    _check_ports_attached(source, reference, probe)
    args.source_max_quality = getattr(source, "default_max_quality", None)
    try:
        server = IGTLServer(args.host, args.igtl_port, log=None if args.quiet else sys.stderr)
    except BaseException:
        source.stop()
        raise
    publisher = TrackerPublisher(server, reference, probe, source.period_s, args.stale_periods, _max_quality(args),
                                 out=None if args.quiet else sys.stderr, link=guard_for(source))
    publisher.max_samples = args.max_samples
    _say(args, f"[emreg] serving {source.description} on OpenIGTLink {args.host}:{server.port} "
               f"(ReferenceToTracker, ProbeToTracker, STATUS Tracker)")
    try:
        with _StopFlag() as stop:
            source.start(publisher.on_sample)
            try:
                why = _run_loop(source, stop, args.duration,
                                lambda: args.max_samples is not None and publisher.samples >= args.max_samples,
                                publisher.tick)
            except EMRegError as exc:
                publisher.device_lost(f"tracker lost: {exc}")  # the last STATUS a client sees is not OK
                raise
    finally:
        source.stop()
        server.close()
    print(f"{publisher.published} transforms published to {server.connections} client(s) ({why})")
    _report_framing(args, source)
    return 0


# --- emreg navigate (live) -----------------------------------------------------------------------


def add_live_navigate_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of live ``emreg navigate`` beyond those ``cli.py`` defines."""
    parser.add_argument("--host", default="127.0.0.1", help="address the OpenIGTLink server listens on")
    parser.add_argument("--reconnect", type=float, default=DEFAULT_RECONNECT_S, metavar="S",
                        help="when the tracker is lost, try to reopen it once a second for up to S seconds "
                             f"(default {DEFAULT_RECONNECT_S:g}; 0: end at once); STATUS is not OK meanwhile")
    _add_replay_options(parser)
    _add_limits(parser)
    _add_watchdog_options(parser)


def run_live_navigate(args: argparse.Namespace) -> int:
    """Live navigation: samples from ``--source`` -> ``ProbeToImage`` on ``--igtl-port`` and/or
    ``OUT/navigation.csv``."""
    from ..devices.igtl_server import IGTLServer
    from ..devices.link_quality import guard_for
    from ..devices.port_check import SensorPortsError
    from ..devices.sources import open_source
    from ..live.navigator import LiveNavigator
    from ..live.writers import NavigationWriter

    if args.igtl_port is None and not args.out:
        raise EMRegError("navigate: a live source needs --igtl-port PORT (publish) and/or --out DIR (record)")
    registration = load_registration(args.registration, getattr(args, "settings", None))
    reference_to_image = np.asarray(registration.reference_to_image, dtype=float)
    reference, probe = sensor_ports(args, registration)
    tool, guide = live_tool_and_guide(args, registration)  # refused (one line) before the tracker is opened
    source = open_source(args.source, reference, probe, fast=args.fast, loop=args.loop)
    _check_ports_attached(source, reference, probe, tool)
    args.source_max_quality = getattr(source, "default_max_quality", None)
    server = writer = None
    try:
        if args.igtl_port is not None:
            server = IGTLServer(args.host, args.igtl_port, log=None if args.quiet else sys.stderr)
        if args.out:
            writer = NavigationWriter(Path(args.out) / NAVIGATION_CSV, guidance=guide is not None)
    except BaseException:
        source.stop()
        if server is not None:
            server.close()
        raise
    link = guard_for(source)
    trust = _trust_monitor(args, registration, tool is None)
    device = tip_device_name(tool)
    navigator = LiveNavigator(reference_to_image, reference, probe, server, writer, source.period_s,
                              args.stale_periods, _max_quality(args), out=None if args.quiet else sys.stderr,
                              device_name=device, link=link, check_ports=link is not None,  # ports judged live
                              trust=trust, tip_to_probe=None if tool is None else tool.tip_to_probe, guide=guide,
                              prediction_trust=_prediction_trust(registration))
    navigator.max_frames = args.max_samples
    if guide is not None and server is not None:
        guide.keep_plan_published(server)
    where = f"OpenIGTLink {args.host}:{server.port} ({device}, RAS)" if server else ""
    if writer:
        where += (" and " if where else "") + str(writer.path)
    _say(args, f"[emreg] navigating from {source.description} -> {where}")
    deadline = None if args.duration is None else time.monotonic() + args.duration
    reconnects = 0
    try:
        with _StopFlag() as stop:
            while True:
                source.start(navigator.on_sample)
                try:
                    left = None if deadline is None else max(0.0, deadline - time.monotonic())
                    why = _run_loop(source, stop, left,
                                    lambda: args.max_samples is not None and navigator.frames >= args.max_samples,
                                    lambda: _tick_or_refuse(navigator))
                    break
                except SensorPortsError:
                    raise  # the ports are wrong: exit 2 (clients already have the not-OK STATUS)
                except EMRegError as exc:  # the device failed: cable pulled, tracker switched off or killed
                    source.stop()
                    navigator.device_lost(f"tracker lost: {exc}")  # the last STATUS a client sees is not OK
                    back = _reconnect(args, reference, probe, stop, exc)
                    if back is None:
                        why = "interrupted while reconnecting"
                        break
                    source = back
                    reconnects += 1
                    navigator.device_back(guard_for(source))
    finally:
        source.stop()
        navigator.finish_trust()
        if server is not None:
            server.close()
        if writer is not None:
            writer.close()
        if args.out:
            from ..core.checkpoints import write_checkpoints

            write_checkpoints(trust.report, Path(args.out) / CHECKPOINTS_JSON)
            if guide is not None:
                write_live_guidance(Path(args.out), guide, tool, navigator.frames)
    again = f", {reconnects} reconnection(s)" if reconnects else ""
    guided = "" if guide is None else f"; {live_guidance_summary(guide)}"
    print(f"{navigator.published} {'probe' if tool is None else 'tool tip'} poses published, {navigator.withheld} "
          f"withheld by the watchdog ({why}{again}); {trust.report.summary()}{guided}")
    _report_framing(args, source)
    return 0


def _prediction_trust(registration: RegistrationResult) -> dict | None:
    """The registration's ``prediction_trust`` block (None: an older registration that has none)."""
    distortion = None if registration.error is None else registration.error.distortion
    return None if distortion is None else distortion.prediction_trust()


def _trust_monitor(args: argparse.Namespace, registration: RegistrationResult, pinhole_probe: bool = True):
    """The live checkpoints and reference-jump watch (:class:`EMRegModule.core.checkpoints.TrustMonitor`) at the
    pinholes
    of the markers beside ``--registration`` (``[navigation]`` of ``--settings``); without them, jumps only. A tool
    on the probe port (``pinhole_probe`` False) never rests in a pinhole: reference jumps only."""
    from ..core.checkpoints import TrustMonitor, markers_beside, pinholes_from_detection
    from ..settings import load_settings

    markers, note = markers_beside(args.registration)
    if pinhole_probe and (note or markers is None):
        _say(args, f"[emreg] warning: {note or 'no markers.json beside the registration: no checkpoints'}")
    pinholes = (None if markers is None or not pinhole_probe else
                pinholes_from_detection(markers, registration.sensor_offset_l_mm, registration))
    return TrustMonitor(pinholes, load_settings(getattr(args, "settings", None)).navigation)


def _tick_or_refuse(navigator) -> None:
    """The watchdog's tick; raises :class:`SensorPortsError` once the port check found swapped ports."""
    navigator.tick()
    if navigator.fatal:
        from ..devices.port_check import SensorPortsError

        raise SensorPortsError(navigator.fatal)


def _reconnect(args: argparse.Namespace, reference: int, probe: int, stop: _StopFlag, cause: Exception):
    """Reopen ``--source`` once a second for up to ``--reconnect`` seconds (bounded retries).

    Returns the new source, or None when interrupted; raises :class:`EMRegError` (exit 2) when the
    device did not come back in time. Replays are not reopened.
    """
    from ..devices.device_url import parse_device_url
    from ..devices.sources import open_source

    window = float(getattr(args, "reconnect", 0) or 0)
    if window <= 0 or parse_device_url(args.source).kind == "replay":
        raise EMRegError(f"{cause}; not reconnecting (--reconnect 0)") if window <= 0 else cause
    _say(args, f"[emreg] tracker lost ({cause}); trying to reconnect for up to {window:g} s")
    give_up = time.monotonic() + window
    attempts = 0
    while time.monotonic() < give_up:
        if stop.event.wait(RECONNECT_INTERVAL_S):
            return None
        attempts += 1
        try:
            source = open_source(args.source, reference, probe, fast=args.fast, loop=args.loop)
        except Exception:  # noqa: BLE001 - any failure to open or configure it: not back yet
            continue
        _say(args, f"[emreg] tracker back after {attempts} attempt(s): {source.description}")
        return source
    raise EMRegError(f"{cause}; the tracker did not come back within {window:g} s ({attempts} attempts)")


#: Seconds between two attempts to reopen a lost tracker.
RECONNECT_INTERVAL_S = 1.0
#: Default time (s) live navigation keeps trying to reopen a lost tracker before it gives up.
DEFAULT_RECONNECT_S = 30.0


#: ``(name, add_arguments, run, help)`` for ``cli.py``.
SUBCOMMANDS = [
    ("record", add_record_arguments, run_record,
     ("record a tracking CSV from a trakSTAR, an OpenIGTLink server or a replay")),
    ("sim-tracker", add_sim_tracker_arguments, run_sim_tracker,
     ("run a simulated trakSTAR on a pseudo-terminal (RS-232 protocol, fault injection)")),
    ("serve", add_serve_arguments, run_serve,
     ("publish every tracker sensor over OpenIGTLink (ReferenceToTracker, ProbeToTracker, STATUS)")),
]

__all__ = ["SUBCOMMANDS", "add_live_navigate_arguments", "check_live_options", "run_live_navigate",
           "load_registration"]


def add_parsers(add: AddCommand) -> None:
    """The live subcommands of :data:`SUBCOMMANDS` (``add``: :data:`~EMRegModule.cli.args.AddCommand`)."""
    for name, add_arguments, run, help_text in SUBCOMMANDS:
        add_arguments(add(name, run, help_text))
