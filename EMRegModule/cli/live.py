"""The live commands: ``emreg record``, ``emreg sim-tracker``, ``emreg serve`` and live ``emreg navigate``.

``emreg navigate`` (:mod:`.stages`) hands itself to :func:`run_live_navigate` when ``--igtl-port`` is given or the
source is not a ``replay:`` file. Each checks its options, calls its loop (:mod:`EMRegModule.live`,
:mod:`EMRegModule.pipeline.live_session`) and prints how it ended.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import fields

from ..errors import EMRegError
from ..live.loop import LiveOptions, LiveOutcome
from ..live.record import record
from ..live.serve import serve
from ..live.sim_tracker import SimulatorOptions, run_simulator
from ..pipeline.live_session import navigate_live, prepare_live_navigation
from .args import out_file, ports_given, sensor_ports, settings_of, warn

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
        if value is not None and not (math.isfinite(value) and value > 0):
            raise EMRegError(f"{option} {value:g}: give {what}")
    reconnect = getattr(args, "reconnect", None)
    if reconnect is not None and not (math.isfinite(reconnect) and reconnect >= 0):
        raise EMRegError(f"--reconnect {reconnect:g}: give the seconds to try reconnecting (0: end at once)")
    port = getattr(args, "igtl_port", None)
    if port is not None and not 0 <= port <= 65535:
        raise EMRegError(f"--igtl-port {port}: a TCP port is 1..65535 (0: any free port)")


def live_options(args: argparse.Namespace) -> LiveOptions:
    """The options every live loop takes, from the command line (absent ones at their defaults)."""
    return LiveOptions(fast=getattr(args, "fast", False), loop=getattr(args, "loop", False),
                       duration_s=getattr(args, "duration", None), max_samples=getattr(args, "max_samples", None),
                       stale_periods=getattr(args, "stale_periods", 3.0),
                       max_quality=getattr(args, "max_quality", None), quiet=getattr(args, "quiet", False))


def _ended(options: LiveOptions, outcome: LiveOutcome) -> int:
    print(outcome.summary)
    if outcome.framing is not None:
        options.say(f"[emreg] {outcome.framing}")
    return 0


def run_sim_tracker(args: argparse.Namespace) -> int:
    check_live_options(args)
    options = SimulatorOptions(**{f.name: getattr(args, f.name) for f in fields(SimulatorOptions)})
    stopped = run_simulator(options, lambda line: print(line, flush=True))
    live_options(args).say(stopped)
    return 0


def run_record(args: argparse.Namespace) -> int:
    check_live_options(args)
    reference, probe = sensor_ports(args)
    out_file(args.out)
    options = live_options(args)
    return _ended(options, record(args.device, args.out, reference, probe, options))


def run_serve(args: argparse.Namespace) -> int:
    check_live_options(args)
    reference, probe = sensor_ports(args)
    options = live_options(args)
    return _ended(options, serve(args.device, args.host, args.igtl_port, reference, probe, options))


def run_live_navigate(args: argparse.Namespace) -> int:
    """Live navigation: samples from ``--source`` -> ``ProbeToImage`` on ``--igtl-port`` and/or
    ``OUT/navigation.csv``."""
    if args.igtl_port is None and not args.out:
        raise EMRegError("navigate: a live source needs --igtl-port PORT (publish) and/or --out DIR (record)")
    settings = settings_of(args)
    session = prepare_live_navigation(args.registration, settings, ports_given(args, settings),
                                      lambda warnings: warn("navigate", warnings), getattr(args, "tool", None),
                                      getattr(args, "plan", None))
    options = live_options(args)
    return _ended(options, navigate_live(session, args.source, options, args.igtl_port, args.host, args.out,
                                         args.reconnect))


__all__ = ["check_live_options", "run_live_navigate", "run_record", "run_serve",
           "run_sim_tracker"]
