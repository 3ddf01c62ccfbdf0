"""``emreg sim-tracker``: a simulated trakSTAR (Flock-of-Birds binary RS-232) or Aurora (NDI serial API) on a
pseudo-terminal, with its scene, faults, flagged distortion and measurement volume, run until it ends or a signal
stops it; at exit, the log of what it emitted (the tests' truth)."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

from ..devices.aurora import protocol as ndi
from ..devices.simulator.aurora import AuroraSimulator, parse_tools
from ..devices.simulator.faults import AuroraFaults, FaultPlan
from ..devices.simulator.scene import BuiltinScene, ReplayScene
from ..devices.simulator.tracker_flags import parse_distortion, parse_volume
from ..devices.simulator.trakstar import TrackerSimulator
from ..devices.trakstar.driver import sensors_from_list
from ..errors import EMRegError
from ..io.atomic import atomic_write_text
from ..io.recording import read_recording
from ..names import DEFAULT_TRAKSTAR_BAUD
from .loop import run_until_stopped


@dataclass(frozen=True)
class SimulatorOptions:
    """The simulated tracker, as ``emreg sim-tracker``'s options give it (their names; s, Hz, mm)."""

    model: str = "trakstar"
    seed: int = 0
    replay: str | None = None
    fault: list[str] = field(default_factory=list)
    link: str | None = None
    duration: float | None = None
    emit_log: str | None = None
    distortion: str | None = None
    volume: str | None = None
    # trakstar
    baud: int = DEFAULT_TRAKSTAR_BAUD
    fast: bool = False
    max_records: int | None = None
    attached: str | None = None
    # aurora
    tools: str | None = None
    rate: float | None = None
    freeze_tag: str | None = None


def run_simulator(options: SimulatorOptions, announce: Callable[[str], None]) -> str:
    """Run the simulator until it ends or SIGINT / SIGTERM; ``announce`` gets the line that says where to connect
    once its pty is open. Returns the line that says what it sent."""
    if options.model == "aurora":
        return _run_aurora(options, announce)
    scene = _scene(options)
    attached = sensors_from_list(options.attached) if options.attached else None
    distortion, _ = _flags(options)
    sim = TrackerSimulator(scene, baud=options.baud, faults=FaultPlan.parse(options.fault), seed=options.seed,
                           link=options.link, fast=options.fast, max_records=options.max_records,
                           duration_s=options.duration, attached=attached, keep_truth=bool(options.emit_log))
    sim.distortion = distortion
    link = f" (link {options.link})" if options.link else ""
    announce(f"trakSTAR simulator on {sim.path}{link}: connect with trakstar://{sim.path}?baud={options.baud}")
    run_until_stopped(sim)
    if options.emit_log:
        _write_emit_log(options.emit_log, "seq,sensor,emit_ns,status,corrupted,x_mm,y_mm,z_mm,azimuth_deg,"
                        "elevation_deg,roll_deg",
                        (f"{r.seq},{r.sensor},{r.emit_ns},{r.status},{int(r.corrupted)},"
                         + ",".join(f"{v:.6f}" for v in (*r.pose.position_mm, *r.pose.angles_deg))
                         for r in sim.truth if r.emit_ns))
    return f"simulator stopped after {sim.records_sent} records"


def _scene(options: SimulatorOptions):
    return ReplayScene(read_recording(options.replay)) if options.replay else BuiltinScene(options.seed)


def _flags(options: SimulatorOptions) -> tuple:
    """(distortion model, measurement volume) of ``--distortion`` / ``--volume`` (None each when not given),
    checked before the simulator opens its pty (:mod:`EMRegModule.devices.simulator.tracker_flags`)."""
    if options.distortion is None and options.volume is None:
        return None, None
    if options.volume is not None and options.model != "aurora":
        raise EMRegError("--volume: only the aurora simulator reports a tool out of its volume")
    return (None if options.distortion is None else parse_distortion(options.distortion),
            None if options.volume is None else parse_volume(options.volume))


def _write_emit_log(path: str, header: str, lines: Iterable[str]) -> None:
    """The simulator's log of what it emitted (the tests' truth), as CSV, atomically."""
    atomic_write_text(path, "\n".join([header, *lines]) + "\n")


def _run_aurora(options: SimulatorOptions, announce: Callable[[str], None]) -> str:
    scene = _scene(options)
    distortion, volume = _flags(options)
    sim = AuroraSimulator(scene, tools=parse_tools(options.tools) if options.tools else None, rate_hz=options.rate,
                          faults=AuroraFaults.parse(options.fault), seed=options.seed, link=options.link,
                          duration_s=options.duration, freeze_tag=options.freeze_tag or ndi.DEFAULT_FREEZE_TAG,
                          keep_log=bool(options.emit_log))
    sim.distortion, sim.volume = distortion, volume
    # a device does not pause mid-reply; ndicapi gives up on a reply after 0.1 s of silence while probing,
    # so on a loaded host the simulator asks for a higher priority where it may (choice; root only)
    with contextlib.suppress(OSError):
        os.nice(-5)
    link = f" (link {options.link})" if options.link else ""
    tools = ", ".join(f"port {t.port}{'/' + str(t.channel) if t.channel else ''}: {t.dof}-DOF"
                      + ("" if t.srom else " without SROM") for t in sim.tools)
    announce(f"Aurora simulator on {sim.path}{link}: connect with aurora://{sim.path}?baud=115200 "
             f"({sim.rate_hz:g} Hz; {tools})")
    run_until_stopped(sim)
    if options.emit_log:
        _write_emit_log(options.emit_log, "frame,command,emit_ns,corrupted",
                        (f"{f.frame},{f.command},{f.emit_ns},{int(f.corrupted)}" for f in sim.log if f.emit_ns))
    return f"simulator stopped after {sim.frames_sent} BX/TX replies"
