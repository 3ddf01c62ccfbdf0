"""Live ``emreg navigate``: the session set up from its files before the tracker is opened, then run.

:func:`prepare_live_navigation` reads each input once: the registration (checked as every consumer checks it), the
markers beside it (for the checkpoints at the pinholes and to check the plan against their CT), the tool
(``--tool``, else ``[tool] calibration``) and the plan's guide (``--plan``, else ``[navigation] plan``; files the
settings name are relative to the settings file's folder, :meth:`EMRegModule.settings.Settings.file_path`).
:func:`navigate_live` maps every sample to image space, publishes it over OpenIGTLink and/or writes
``OUT/navigation.csv``, reopens a lost tracker for up to ``--reconnect`` seconds, and writes ``OUT/checkpoints.json``
(and ``OUT/navigation.json`` with a plan) at the end.

Frames and units: image space (the CT's LPS, mm; RAS on the wire), ``ReferenceToImage`` and ``TipToProbe`` (4x4, mm).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..core.checkpoints import TrustMonitor, pinholes_from_detection
from ..core.detection.result import DetectionResult
from ..core.guidance import GuidanceReport, predicted_at, shaft_in_tip
from ..core.registration import RegistrationResult
from ..core.tool import ToolCalibration
from ..devices.device_url import parse_device_url
from ..devices.igtl_server import IGTLServer
from ..devices.link_quality import guard_for
from ..devices.port_check import SensorPortsError
from ..devices.sources import open_source
from ..errors import EMRegError
from ..io.atomic import atomic_write_json
from ..io.checkpoints_json import write_checkpoints
from ..io.markers_json import markers_beside
from ..io.plan_markups import read_plan
from ..io.provenance import check_belongs
from ..io.registration_files import read_registration
from ..io.tool_files import read_tool
from ..live.guide import LiveGuide, closest_numbers
from ..live.loop import (
    LiveOptions,
    LiveOutcome,
    StopFlag,
    check_ports_attached,
    framing_text,
    max_quality_limit,
    run_loop,
)
from ..live.navigator import LiveNavigator
from ..live.writers import NavigationWriter
from ..names import CHECKPOINTS_JSON, NAVIGATION_CSV, NAVIGATION_JSON, REGISTRATION_JSON
from ..settings import Settings, choose_ports
from .inputs import check_plan_in_ct, refuse_tool_auto
from .navigating import error_model, tool_summary

#: Seconds between two attempts to reopen a lost tracker.
RECONNECT_INTERVAL_S = 1.0


@dataclass
class LiveNavigation:
    """What live navigation works with, read before the tracker is opened: the registration, the ports (reference,
    probe), the tool on the probe port (None: the pinhole probe), the guide to the plan (None: no plan), and the
    markers beside the registration (None: none usable; ``markers_note`` says why when they cannot be used)."""

    registration: RegistrationResult
    settings: Settings
    reference: int
    probe: int
    tool: ToolCalibration | None
    guide: LiveGuide | None
    markers: DetectionResult | None
    markers_note: str | None

    @property
    def device_name(self) -> str:
        """The TRANSFORM's device name: ``ProbeToImage`` without a tool, ``<Name>TipToImage`` for a tool its file
        names (``StylusTipToImage``), else ``TipToImage``."""
        if self.tool is None:
            return "ProbeToImage"
        return f"{self.tool.name}TipToImage" if self.tool.name else "TipToImage"

    def trust_monitor(self, say: Callable[[str], None]) -> TrustMonitor:
        """The live checkpoints and reference-jump watch at the pinholes of the markers beside the registration
        (``[navigation]``); without them, jumps only (said on ``say``). A tool on the probe port never rests in a
        pinhole: reference jumps only."""
        pinhole_probe = self.tool is None
        if pinhole_probe and (self.markers_note or self.markers is None):
            say(f"[emreg] warning: {self.markers_note or 'no markers.json beside the registration: no checkpoints'}")
        pinholes = (None if self.markers is None or not pinhole_probe else
                    pinholes_from_detection(self.markers, self.registration.sensor_offset_l_mm, self.registration))
        return TrustMonitor(pinholes, self.settings.navigation)


def prepare_live_navigation(registration_path: str, settings: Settings, ports_given: tuple[int | None, int | None],
                            warn: Callable[[Sequence[str]], None], tool_file: str | None = None,
                            plan_file: str | None = None) -> LiveNavigation:
    """The session of live navigation with ``registration.json`` at ``registration_path``, the ports the user gave
    (None: not given; a port that differs from the registration's is used, with a warning passed to ``warn``), the
    tool and the plan given on the command line (None: those of the settings, if any).

    Refused (one line): a registration that is not finite and rigid, over ``[registration] max_fre_mm`` or stale in
    its folder; ``--tool auto`` (nothing to solve it from live); an unreadable tool or plan file; a plan outside the
    CT of the markers beside the registration."""
    registration = read_registration(registration_path, settings.registration.max_fre_mm)
    check_belongs(Path(registration_path) / REGISTRATION_JSON if Path(registration_path).is_dir()
                  else Path(registration_path))
    chosen, warnings = choose_ports(ports_given, (registration.reference_sensor, registration.probe_sensor))
    warn(warnings)
    sensors = settings.with_sensors(*chosen).sensors
    tool = _live_tool(tool_file, settings)
    markers, note = markers_beside(registration_path)
    guide = _live_guide(plan_file, settings, registration, markers, tool)
    return LiveNavigation(registration, settings, sensors.reference, sensors.probe, tool, guide, markers, note)


def _live_tool(tool_file: str | None, settings: Settings) -> ToolCalibration | None:
    name = tool_file or settings.tool.calibration
    if name == "auto":
        refuse_tool_auto("navigate")
    if not name:
        return None
    return read_tool(tool_file or settings.file_path(name), settings.tool.name)


def _live_guide(plan_file: str | None, settings: Settings, registration: RegistrationResult,
                markers: DetectionResult | None, tool: ToolCalibration | None) -> LiveGuide | None:
    name = plan_file or settings.navigation.plan
    if not name:
        return None
    plan = read_plan(plan_file or settings.file_path(name))
    check_plan_in_ct(plan, markers)
    model = error_model(registration, settings)
    prediction = None if model is None else predicted_at(model, plan.target_mm, tool)
    return LiveGuide(plan, None if tool is None else shaft_in_tip(tool.tip_to_probe), prediction)


def navigate_live(session: LiveNavigation, source_url: str, options: LiveOptions, igtl_port: int | None,
                  host: str, out: str | os.PathLike[str] | None, reconnect_s: float) -> LiveOutcome:
    """Navigate from ``source_url`` (a device URL) until a limit of ``options``, the source's end or a signal:
    ``ProbeToImage`` (or the tool tip's) on ``host:igtl_port`` and/or ``out/navigation.csv``."""
    reference, probe, tool, guide = session.reference, session.probe, session.tool, session.guide
    source = open_source(source_url, reference, probe, fast=options.fast, loop=options.loop)
    check_ports_attached(source, reference, probe, tool)
    max_quality = max_quality_limit(options.max_quality, getattr(source, "default_max_quality", None))
    server = writer = None
    try:
        if igtl_port is not None:
            server = IGTLServer(host, igtl_port, log=options.log)
        if out:
            writer = NavigationWriter(Path(out) / NAVIGATION_CSV, guidance=guide is not None)
    except BaseException:
        source.stop()
        if server is not None:
            server.close()
        raise
    link = guard_for(source)
    trust = session.trust_monitor(options.say)
    device = session.device_name
    navigator = LiveNavigator(np.asarray(session.registration.reference_to_image, dtype=float), reference, probe,
                              server, writer, source.period_s, options.stale_periods, max_quality, out=options.log,
                              device_name=device, link=link, check_ports=link is not None,  # ports judged live
                              trust=trust, tip_to_probe=None if tool is None else tool.tip_to_probe, guide=guide,
                              prediction_trust=_prediction_trust(session.registration))
    navigator.max_frames = options.max_samples
    if guide is not None and server is not None:
        guide.keep_plan_published(server)
    where = f"OpenIGTLink {host}:{server.port} ({device}, RAS)" if server else ""
    if writer:
        where += (" and " if where else "") + str(writer.path)
    options.say(f"[emreg] navigating from {source.description} -> {where}")
    deadline = None if options.duration_s is None else time.monotonic() + options.duration_s
    reconnects = 0
    try:
        with StopFlag() as stop:
            while True:
                source.start(navigator.on_sample)
                try:
                    left = None if deadline is None else max(0.0, deadline - time.monotonic())
                    why = run_loop(source, stop, left,
                                   lambda: options.max_samples is not None and navigator.frames >= options.max_samples,
                                   lambda: _tick_or_refuse(navigator))
                    break
                except SensorPortsError:
                    raise  # the ports are wrong: exit 2 (clients already have the not-OK STATUS)
                except EMRegError as exc:  # the device failed: cable pulled, tracker switched off or killed
                    source.stop()
                    navigator.device_lost(f"tracker lost: {exc}")  # the last STATUS a client sees is not OK
                    back = _reconnect(source_url, reference, probe, options, reconnect_s, stop, exc)
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
        if out:
            write_checkpoints(trust.report, Path(out) / CHECKPOINTS_JSON)
            if guide is not None:
                _write_live_guidance(Path(out), guide, tool, navigator.frames)
    again = f", {reconnects} reconnection(s)" if reconnects else ""
    guided = "" if guide is None else f"; {_guidance_summary(guide)}"
    return LiveOutcome(f"{navigator.published} {'probe' if tool is None else 'tool tip'} poses published, "
                       f"{navigator.withheld} withheld by the watchdog ({why}{again}); {trust.report.summary()}"
                       f"{guided}", framing_text(source))


def _tick_or_refuse(navigator: LiveNavigator) -> None:
    """The watchdog's tick; raises :class:`SensorPortsError` once the port check found swapped ports."""
    navigator.tick()
    if navigator.fatal:
        raise SensorPortsError(navigator.fatal)


def _reconnect(source_url: str, reference: int, probe: int, options: LiveOptions, window_s: float, stop: StopFlag,
               cause: Exception):
    """Reopen the source once a second for up to ``window_s`` seconds (bounded retries).

    Returns the new source, or None when interrupted; raises :class:`EMRegError` (exit 2) when the
    device did not come back in time. Replays are not reopened.
    """
    window = float(window_s or 0)
    if window <= 0 or parse_device_url(source_url).kind == "replay":
        raise EMRegError(f"{cause}; not reconnecting (--reconnect 0)") if window <= 0 else cause
    options.say(f"[emreg] tracker lost ({cause}); trying to reconnect for up to {window:g} s")
    give_up = time.monotonic() + window
    attempts = 0
    while time.monotonic() < give_up:
        if stop.event.wait(RECONNECT_INTERVAL_S):
            return None
        attempts += 1
        try:
            source = open_source(source_url, reference, probe, fast=options.fast, loop=options.loop)
        except Exception:  # noqa: BLE001 - any failure to open or configure it: not back yet
            continue
        options.say(f"[emreg] tracker back after {attempts} attempt(s): {source.description}")
        return source
    raise EMRegError(f"{cause}; the tracker did not come back within {window:g} s ({attempts} attempts)")


def _guidance_summary(guide: LiveGuide) -> str:
    """The closest approach and the predicted error at the target, in one line."""
    closest = ("no OK pose to approach the target" if guide.closest is None else
               f"closest {guide.closest[1]:.2f} mm from the target at {guide.closest[0]:.2f} s")
    return closest if guide.prediction is None else f"{closest}; {guide.prediction.summary()}"


def _write_live_guidance(out: Path, guide: LiveGuide, tool: ToolCalibration | None, frames: int) -> None:
    """``OUT/navigation.json`` of live navigation with a plan (as the replay writes it), atomically."""
    numbers = closest_numbers(guide)
    closest = None if numbers is None else {name: float(getattr(numbers, name)[0]) for name in
                                            ("target_distance_mm", "lateral_mm", "angle_deg", "to_go_mm")}
    report = GuidanceReport(guide.plan, guide.prediction, None, None if guide.closest is None else guide.closest[0],
                            None if guide.closest is None else guide.closest[2], closest, frames, tool_summary(tool))
    atomic_write_json(out / NAVIGATION_JSON, report.to_json())


def _prediction_trust(registration: RegistrationResult) -> dict | None:
    """The registration's ``prediction_trust`` block (None: an older registration that has none)."""
    distortion = None if registration.error is None else registration.error.distortion
    return None if distortion is None else distortion.prediction_trust()
