"""``emreg serve``: every sensor of a tracker published over OpenIGTLink (``ReferenceToTracker``,
``ProbeToTracker``, ``STATUS Tracker``) under the watchdog."""

from __future__ import annotations

from ..devices.igtl_server import IGTLServer
from ..devices.link_quality import guard_for
from ..devices.sources import open_source
from ..errors import EMRegError
from .loop import LiveOptions, LiveOutcome, StopFlag, check_ports_attached, framing_text, max_quality_limit, run_loop
from .navigator import TrackerPublisher


def serve(device: str, host: str, igtl_port: int, reference: int, probe: int, options: LiveOptions) -> LiveOutcome:
    """Publish the samples of ``device`` (a device URL) on ``host:igtl_port`` until a limit of ``options``, the
    source's end or a signal."""
    source = open_source(device, reference, probe, fast=options.fast, loop=options.loop)
    check_ports_attached(source, reference, probe)
    try:
        server = IGTLServer(host, igtl_port, log=options.log)
    except BaseException:
        source.stop()
        raise
    publisher = TrackerPublisher(server, reference, probe, source.period_s, options.stale_periods,
                                 max_quality_limit(options.max_quality, getattr(source, "default_max_quality", None)),
                                 out=options.log, link=guard_for(source))
    publisher.max_samples = options.max_samples
    options.say(f"[emreg] serving {source.description} on OpenIGTLink {host}:{server.port} "
                f"(ReferenceToTracker, ProbeToTracker, STATUS Tracker)")
    try:
        with StopFlag() as stop:
            source.start(publisher.on_sample)
            try:
                why = run_loop(source, stop, options.duration_s,
                               lambda: options.max_samples is not None and publisher.samples >= options.max_samples,
                               publisher.tick)
            except EMRegError as exc:
                publisher.device_lost(f"tracker lost: {exc}")  # the last STATUS a client sees is not OK
                raise
    finally:
        source.stop()
        server.close()
    return LiveOutcome(f"{publisher.published} transforms published to {server.connections} client(s) ({why})",
                       framing_text(source))
