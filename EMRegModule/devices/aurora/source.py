"""The live sample source behind ``aurora:///dev/ttyUSB0[?baud=...]``: an Aurora (or the simulator) polled
through :class:`~.driver.AuroraDriver`; one :class:`~EMRegModule.devices.samples.SensorSample` per tool and frame
(``SensorToTracker``, mm; tracker frame, unchanged)."""

from __future__ import annotations

from ...errors import EMRegError
from ..device_url import DeviceURL
from ..source_base import DriverSource, SampleCallback
from .driver import DEFAULT_RATE_HZ, AuroraDriver, sensors_from_text


class AuroraSource(DriverSource):
    """An Aurora (or the simulator) polled through :class:`AuroraDriver`; samples per tool and frame.

    URL options: ``baud`` (default 115200), ``reply`` (auto, bx, tx), ``five_dof`` (sensor numbers of
    5-DOF sensors), ``rate`` (the Aurora's measuring rate in Hz: sample times and the watchdog's period;
    default 40).
    """

    #: Worst acceptable RMS error (mm) when ``--max-quality`` is not given (choice: a clean Aurora solution
    #: reports a few hundredths to tenths of a millimetre; the simulator's distortion fault reports 2.5).
    default_max_quality = 1.0
    watch_name = "aurora-watch"

    def __init__(self, url: DeviceURL) -> None:
        super().__init__()
        options = url.options
        try:
            rate_hz = float(options.get("rate", DEFAULT_RATE_HZ))
        except ValueError:
            raise EMRegError(f"device {url.text!r}: rate must be a number of Hz") from None
        self.driver = AuroraDriver(url.path, url.baud, options.get("reply", "auto"),
                                   sensors_from_text(options.get("five_dof")), rate_hz)
        self.driver.open()
        self.period_s = 1.0 / rate_hz
        tools = ", ".join(f"port {t.port}{'/' + str(t.channel) if t.channel else ''} -> sensor {t.sensor}"
                          for t in self.driver.tools)
        self.description = (f"Aurora on {url.path} at {url.baud} baud ({self.driver.freeze_tag or 'firmware ?'}, "
                            f"{'BX' if self.driver.use_bx else 'TX'}; {tools})")

    def attached_ports(self) -> tuple[int, ...]:
        """The sensor numbers of the enabled tools (each coil of a dual-5-DOF tool its own)."""
        return tuple(sorted(int(tool.sensor) for tool in self.driver.tools))

    def port_dof(self, port: int) -> int | None:
        """5 for a 5-DOF coil (``five_dof`` of the URL), 6 for a 6-DOF tool; None for a port with no tool."""
        return next((int(tool.dof) for tool in self.driver.tools if tool.sensor == port), None)

    def link_counts(self) -> tuple[int, int]:
        """Cumulative (accepted, rejected) samples of the serial link, for the tracker-agnostic link-quality
        monitor: every tool's sample of an accepted new frame, and one lost sample per tool for every reply
        ndicapi rejected (bad CRC, timeout, error)."""
        st, tools = self.driver.stats, len(self.driver.tools)
        return st.frames * tools, st.rejected * tools

    def _start_driver(self, callback: SampleCallback) -> None:
        self.driver.start(callback)

    def framing_summary(self) -> str:
        st = self.driver.stats
        return (f"[emreg] Aurora replies: {st.frames} frames, {st.repeated} repeated polls, {st.missed_frames} frame "
                f"numbers skipped; rejected {st.rejected} (CRC {st.crc_errors}, timeout {st.timeouts}, "
                f"other {st.other_errors}); {st.replugs} restart(s) for a tool plugged in")
