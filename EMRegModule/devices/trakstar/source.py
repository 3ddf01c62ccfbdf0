"""The live sample source behind ``trakstar:///dev/ttyUSB0?baud=115200``: a trakSTAR (or the simulator)
streaming every sensor in group mode through :class:`~.driver.TrakstarDriver` (``SensorToTracker``, mm;
tracker frame, unchanged)."""

from __future__ import annotations

from ..device_url import DeviceURL
from ..source_base import DriverSource, SampleCallback
from .driver import TrakstarDriver


class TrakstarSource(DriverSource):
    """A trakSTAR (or the simulator) streaming every sensor in group mode."""

    watch_name = "trakstar-watch"

    def __init__(self, url: DeviceURL) -> None:
        super().__init__()
        options = url.options
        self.driver = TrakstarDriver(url.path, url.baud, max_gap_ms=float(options.get("gap_ms", 50)))
        self.driver.open()
        try:
            self.driver.configure(
                options.get("format", "POSITION/ANGLES"), metal=options.get("metal", "1") not in ("0", "false", "no"),
                group=True, rate_hz=float(options["rate"]) if "rate" in options else None,
                scale_inches=int(options["scale"]) if "scale" in options else None)
        except BaseException:
            self.driver.close()
            raise
        self.period_s = 1.0 / self.driver.rate_hz
        self.description = f"trakSTAR on {url.path} at {url.baud} baud, {self.driver.rate_hz:g} Hz"

    def attached_ports(self) -> tuple[int, ...]:
        """Ports with a sensor plugged in (the tracker's sensor serial number is non-zero)."""
        return tuple(s for s in self.driver.group_sensors if self.driver.sensor_attached(s))

    def link_counts(self) -> tuple[int, int]:
        """Cumulative (accepted, rejected) records of the serial link (for the link-quality monitor)."""
        stats = self.driver.stats
        return stats.records, stats.rejected

    def _start_driver(self, callback: SampleCallback) -> None:
        self.driver.start_stream(callback)
