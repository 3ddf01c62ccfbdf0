#!/usr/bin/env python3
"""Benchmark of the live path: trakSTAR rate at 115200 baud and added latency to OpenIGTLink.

1. Rate: the simulator (its own process, ``--fast``) streams four sensors in group mode as fast as
   115200 baud allows (POSITION/ANGLES + METAL byte + address byte = 14 bytes per record, 56 per
   cycle, 11520 bytes/s -> 205.7 cycles/s). The driver must decode every record sent (no loss).
2. Latency: from the moment the simulator wrote the probe record's last byte to the pty (its
   ``--emit-log``, CLOCK_MONOTONIC) to the moment EMReg handed the ``ProbeToImage`` OpenIGTLink
   message to the kernel (driver -> framing -> decode -> watchdog -> Eq. 12 -> TRANSFORM pack ->
   non-blocking send; then, off that path, the checkpoint and reference-jump watch that live navigation
   runs beside every pose), median and 99th percentile; goal < 2 ms / < 5 ms.
3. Baseline, same run, same pty and TCP client: a plain loop that reads the serial port with
   pyserial and sends each raw record on a socket as soon as its bytes are in (no framing checks,
   no decoding, no OpenIGTLink).
2b. With ``--guidance`` (issue 38): the same path once more in the same run with a tool (a needle whose tip is
   118 mm along the probe sensor's +x: ``StylusTipToImage`` is published) and a plan (the guidance numbers of
   every pose, the ``Guidance`` STRING at most 20 times a second, the plan once a second); the latency it adds
   per pose over the run without them (goal: at most 0.2 ms median), at the same line rate with no loss.

The NDI Aurora (``--model aurora`` or ``both``, the default) on the same terms:

4. Rate: ``emreg sim-tracker --model aurora`` (own process) measures at its configured rate (40 Hz)
   with two 6-DOF tools; EMReg's driver (ndicapi) polls BX at 115200 baud; frames per second
   delivered and frame numbers skipped (no loss = none skipped, no reply rejected).
5. Latency: from the last byte of the BX reply that first carried a frame (the simulator's
   ``--emit-log``) to the ``ProbeToImage`` message handed to TCP.
6. Baseline: a plain pyserial loop that sends the same ``BX:0801`` command, reads the reply by its
   length header and sends the raw bytes on a socket (no CRC check, no decoding, no OpenIGTLink).

Run: ``.venv/bin/python scripts/bench_tracker.py [--seconds 4] [--model trakstar|aurora|both]``.
Loopback only; stops by itself.
"""

from __future__ import annotations

import argparse
import csv
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from EMRegModule.devices.aurora import protocol as ndi  # noqa: E402
from EMRegModule.devices.device_url import parse_device_url  # noqa: E402
from EMRegModule.devices.igtl_server import IGTLServer  # noqa: E402
from EMRegModule.devices.simulator.scene import BuiltinScene  # noqa: E402
from EMRegModule.devices.sources import open_source  # noqa: E402
from EMRegModule.devices.trakstar import protocol as tp  # noqa: E402
from EMRegModule.devices.trakstar.source import TrakstarSource  # noqa: E402
from EMRegModule.live.navigator import LiveNavigator  # noqa: E402

DRAIN = """
import socket, sys
s = socket.create_connection(("127.0.0.1", int(sys.argv[1])))
n = 0
while True:
    data = s.recv(1 << 16)
    if not data:
        break
    n += len(data)
print(n)
"""


def start_drain(port: int) -> subprocess.Popen:
    """A TCP client in its own process that reads and discards everything."""
    return subprocess.Popen([sys.executable, "-c", DRAIN, str(port)], stdout=subprocess.PIPE, text=True)


def read_emit_log(path: Path) -> dict[int, list[tuple[int, np.ndarray]]]:
    """Per sensor: (emit ns, truth [x, y, z, azimuth, elevation, roll]) of every record sent."""
    out: dict[int, list[tuple[int, np.ndarray]]] = {}
    keys = ("x_mm", "y_mm", "z_mm", "azimuth_deg", "elevation_deg", "roll_deg")
    with open(path, newline="") as f:
        for row in csv.DictReader(f):
            truth = np.array([float(row[k]) for k in keys])
            out.setdefault(int(row["sensor"]), []).append((int(row["emit_ns"]), truth))
    return out


def _same(truth: np.ndarray, decoded: np.ndarray) -> bool:
    position_ok = np.max(np.abs(truth[:3] - decoded[:3])) <= 0.5 * 4 * 36 / 32768 * 25.4 + 1e-6
    angles = (truth[3:] - decoded[3:] + 180.0) % 360.0 - 180.0
    return bool(position_ok and np.max(np.abs(angles)) <= 0.5 * 4 * 180 / 32768 + 1e-6)


def match_emits(poses: list[np.ndarray], emitted: list[tuple[int, np.ndarray]]) -> list[int | None]:
    """For each decoded probe pose [x, y, z, az, el, roll] (in order), the emit time of its record."""
    out: list[int | None] = []
    i = 0
    for pose in poses:
        j = i
        while j < len(emitted) and not _same(emitted[j][1], pose):
            j += 1
        if j == len(emitted):
            out.append(None)
            continue
        out.append(emitted[j][0])
        i = j + 1
    return out


def _trust():
    """The checkpoint and reference-jump watch live ``emreg navigate`` runs beside every pose (28 pinholes of a
    full frame, 350 x 350 mm, around the scene's probe), as
    :meth:`EMRegModule.pipeline.live_session.LiveNavigation.trust_monitor` builds it."""
    from EMRegModule.core.checkpoints import Pinholes, TrustMonitor

    rng = np.random.default_rng(0)
    axis = rng.normal(size=(28, 3))
    return TrustMonitor(Pinholes([f"I{i + 1:02d}" for i in range(28)], BuiltinScene(0).reference_position
                                 + rng.uniform(-175.0, 175.0, (28, 3)), axis / np.linalg.norm(axis, axis=1)[:, None]))


def _guided() -> dict:
    """A needle (tip 118 mm along the sensor's +x) and a plan of 80 mm ending 40 mm from the scene's reference, as
    live ``emreg navigate --tool --plan`` builds them (:mod:`EMRegModule.pipeline.live_session`)."""
    from EMRegModule.core.guidance import Plan, predicted_at_target, shaft_in_tip
    from EMRegModule.live.guide import LiveGuide

    tip_to_probe = np.eye(4)
    tip_to_probe[0, 3] = 118.0
    target = BuiltinScene(0).reference_position + np.array([40.0, 0.0, 0.0])
    plan = Plan(target, target - np.array([0.0, 0.0, 80.0]), "bench")
    guide = LiveGuide(plan, shaft_in_tip(tip_to_probe), predicted_at_target(0.5, 0.4))
    return {"device_name": "StylusTipToImage", "tip_to_probe": tip_to_probe, "guide": guide}


def run_emreg(path: str, seconds: float, port: int, guided: bool = False) -> dict:
    """EMReg's live path: driver -> navigator -> OpenIGTLink server -> one TCP client (``guided``: with a tool and
    a plan, :func:`_guided`)."""
    source = TrakstarSource(parse_device_url(f"trakstar://{path}?metal=1"))
    server = IGTLServer("127.0.0.1", port)
    drain = start_drain(server.port)
    server.wait_for_clients(1, 5.0)
    navigator = LiveNavigator(np.eye(4), 1, 2, server, None, period_s=1 / 205.0, out=None, trust=_trust(),
                              **(_guided() if guided else {}))
    probe_positions: dict[int, np.ndarray] = {}
    samples = [0]

    def on_sample(sample) -> None:
        samples[0] += 1
        if sample.sensor == 2:
            probe_positions[sample.frame] = np.concatenate([sample.position_mm, sample.angles_deg])
        navigator.on_sample(sample)

    start = time.monotonic()
    source.start(on_sample)
    time.sleep(seconds)
    elapsed = time.monotonic() - start
    stats = source.driver.stats
    source.stop()
    server.close()
    drain.wait(timeout=10)
    frames = sorted({f for f, _, _ in navigator.latencies})
    return {"samples": samples[0], "elapsed": elapsed, "stats": stats, "latencies": list(navigator.latencies),
            "probe_positions": probe_positions, "frames": len(frames), "published": navigator.published,
            "withheld": navigator.withheld}


def run_baseline(path: str, seconds: float) -> dict:
    """A plain loop: pyserial read -> raw record bytes -> socket.send (no checks, no decoding)."""
    import serial

    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen(1)
    drain = start_drain(listener.getsockname()[1])
    conn, _ = listener.accept()
    conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    ser = serial.Serial(path, 115200, timeout=0.05)
    fmt = tp.get_format("POSITION/ANGLES")
    for sensor in (1, 2, 3, 4):
        ser.write(bytes([tp.address_byte(sensor), fmt.command, tp.address_byte(sensor), tp.METAL, 1, 32]))
    ser.write(bytes([tp.CHANGE_VALUE, tp.PARAM_GROUP_MODE, 1]))
    time.sleep(0.05)
    ser.reset_input_buffer()
    start_ns = time.monotonic_ns()
    ser.write(bytes([tp.STREAM]))
    length = tp.record_length(fmt, metal=True, group=True)
    buffer = bytearray()
    sent: list[tuple[bytes, int]] = []
    stop = time.monotonic() + seconds
    while time.monotonic() < stop:
        chunk = ser.read(1)
        if not chunk:
            continue
        waiting = ser.in_waiting
        if waiting:
            chunk += ser.read(waiting)
        buffer.extend(chunk)
        while len(buffer) >= length:
            record = bytes(buffer[:length])
            del buffer[:length]
            conn.sendall(record)
            sent.append((record, time.monotonic_ns()))
    ser.write(bytes([tp.POINT]))
    time.sleep(0.05)
    ser.close()
    conn.close()
    listener.close()
    drain.wait(timeout=10)
    return {"sent": sent, "start_ns": start_ns}


def percentiles(values_ms: np.ndarray) -> tuple[float, float]:
    return float(np.median(values_ms)), float(np.percentile(values_ms, 99))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=4.0, help="length of each measuring phase")
    parser.add_argument("--igtl-port", type=int, default=0)
    parser.add_argument("--model", choices=("trakstar", "aurora", "both"), default="both")
    parser.add_argument("--guidance", action="store_true",
                        help="trakSTAR: also measure the path with a tool and a plan in the same run (issue 38)")
    args = parser.parse_args()
    if args.model in ("trakstar", "both"):
        print("=== trakSTAR ===")
        bench_trakstar(args)
    if args.model in ("aurora", "both"):
        print("\n=== NDI Aurora ===")
        bench_aurora(args)
    return 0


def bench_trakstar(args: argparse.Namespace) -> None:
    fmt = tp.get_format("POSITION/ANGLES")
    record_bytes = tp.record_length(fmt, metal=True, group=True)
    theoretical_hz = tp.max_stream_rate_hz(fmt, 4, 115200, metal=True, group=True)
    print(f"4 sensors, POSITION/ANGLES + METAL + group address: {record_bytes} bytes/record, "
          f"{4 * record_bytes} bytes/cycle; 115200 baud 8N1 = {tp.bytes_per_second(115200):.0f} bytes/s "
          f"-> theoretical {theoretical_hz:.1f} cycles/s ({4 * theoretical_hz:.0f} records/s)")

    with tempfile.TemporaryDirectory() as tmp:
        link = Path(tmp) / "trakstar"
        emit_log = Path(tmp) / "emit.csv"
        sim = subprocess.Popen([sys.executable, "-m", "EMRegModule", "sim-tracker", "--fast", "--link", str(link),
                                "--emit-log", str(emit_log), "--duration", str(4 * args.seconds + 20), "--quiet"],
                               stdout=subprocess.PIPE, text=True, cwd=ROOT,
                               env=dict(os.environ, PYTHONUNBUFFERED="1"))
        sim.stdout.readline()
        ours = run_emreg(str(link), args.seconds, args.igtl_port)
        time.sleep(0.2)
        guided = run_emreg(str(link), args.seconds, args.igtl_port, guided=True) if args.guidance else None
        time.sleep(0.2)
        base = run_baseline(str(link), args.seconds)
        sim.terminate()
        sim.wait(timeout=20)
        emitted = read_emit_log(emit_log)

    # --- rate -------------------------------------------------------------------------------------
    stats = ours["stats"]
    achieved_hz = ours["frames"] / ours["elapsed"]
    print(f"\nEMReg driver: {stats.records} records decoded in {ours['elapsed']:.2f} s = "
          f"{stats.records / ours['elapsed']:.0f} records/s, {achieved_hz:.1f} cycles/s "
          f"({100 * achieved_hz / theoretical_hz:.1f}% of theoretical); rejected {stats.rejected}, "
          f"stray bytes {stats.stray_bytes}; {ours['published']} ProbeToImage published, "
          f"{ours['withheld']} withheld")

    # --- latency: EMReg ----------------------------------------------------------------------------
    ours_ms, lost, matched, sent_in_window = _latency_ms(ours, emitted)
    # --- latency: baseline ---------------------------------------------------------------------------
    probe_records = [(r, t) for r, t in base["sent"] if r[-1] == 2 and r[0] & 0x80]
    decoded = [tp.decode_record(fmt, r, 36, metal=True, group=True) for r, _ in probe_records]
    base_positions = [np.concatenate([d.position_mm, d.angles_deg]) for d in decoded]
    base_emits = match_emits(base_positions, [e for e in emitted.get(2, []) if e[0] >= base["start_ns"]])
    base_ms = np.array([(t - e) / 1e6 for (_, t), e in zip(probe_records, base_emits, strict=True) if e is not None])

    om, op = percentiles(ours_ms)
    bm, bp = percentiles(base_ms)
    print(f"\nlatency, last byte of the probe record written -> message handed to TCP (n = {len(ours_ms)}):")
    print(f"  EMReg (framing, decode, watchdog, Eq. 12, OpenIGTLink TRANSFORM): median {om:.3f} ms, p99 {op:.3f} ms "
          f"(goal < 2 / < 5 ms)")
    print(f"  baseline (raw pty read + socket send, n = {len(base_ms)}):          median {bm:.3f} ms, p99 {bp:.3f} ms")
    print(f"  added by EMReg over the baseline: median {om - bm:+.3f} ms, p99 {op - bp:+.3f} ms; "
          f"ratio median {om / bm:.2f}x, p99 {op / bp:.2f}x")
    print(f"  probe records published: {len(matched)} of the {sent_in_window} the simulator sent in that window; "
          f"unmatched to its log: {lost}")
    loss_free = stats.rejected == 0 and stats.stray_bytes == 0 and lost == 0 and len(matched) == sent_in_window
    print(f"\nno loss at the line-limited rate: {'yes' if loss_free else 'NO'}; "
          f"latency goal met: {'yes' if om < 2 and op < 5 else 'NO'}")
    if guided is not None:
        _report_guided(guided, emitted, om, op, theoretical_hz)


def _latency_ms(ours: dict, emitted: dict) -> tuple[np.ndarray, int, list[int], int]:
    """Per published pose, the latency (ms) from the probe record's last byte to the TRANSFORM handed to TCP; the
    poses unmatched to the simulator's log, the matched emit times, and the probe records sent in that window."""
    frames = [f for f, _, _ in ours["latencies"]]
    positions = [ours["probe_positions"][f] for f in frames]
    emits = match_emits(positions, emitted.get(2, []))
    ours_ms = np.array([(sent - e) / 1e6 for (_, _, sent), e in zip(ours["latencies"], emits, strict=True)
                        if e is not None])
    matched = [e for e in emits if e is not None]
    # every probe record the simulator sent between the first and the last one EMReg published
    sent_in_window = sum(1 for t, _ in emitted.get(2, []) if min(matched) <= t <= max(matched))
    return ours_ms, sum(e is None for e in emits), matched, sent_in_window


def _report_guided(guided: dict, emitted: dict, plain_median: float, plain_p99: float, theoretical_hz: float) -> None:
    """The run with a tool and a plan against the plain one of the same run (issue 38: at most +0.2 ms median)."""
    guided_ms, lost, matched, sent_in_window = _latency_ms(guided, emitted)
    gm, gp = percentiles(guided_ms)
    stats = guided["stats"]
    achieved_hz = guided["frames"] / guided["elapsed"]
    loss_free = stats.rejected == 0 and stats.stray_bytes == 0 and lost == 0 and len(matched) == sent_in_window
    print(f"\nwith a tool and a plan (StylusTipToImage, guidance numbers, Guidance STRING <= 20 Hz, plan 1 Hz; "
          f"n = {len(guided_ms)}): median {gm:.3f} ms, p99 {gp:.3f} ms; {achieved_hz:.1f} cycles/s "
          f"({100 * achieved_hz / theoretical_hz:.1f}% of theoretical), no loss: {'yes' if loss_free else 'NO'}")
    print(f"  added by the tool and the plan: median {gm - plain_median:+.3f} ms, p99 {gp - plain_p99:+.3f} ms "
          f"(goal: median at most +0.2 ms): {'met' if gm - plain_median <= 0.2 else 'NOT met'}")


# --- the Aurora --------------------------------------------------------------------------------------------

AURORA_RATE_HZ = 40.0
AURORA_HANDLES = (0x0A, 0x0B)


def read_aurora_log(path: Path) -> list[tuple[int, int, bool]]:
    """(frame, emit ns of the reply's last byte, corrupted) of every BX/TX reply the simulator sent."""
    with open(path, newline="") as f:
        return [(int(r["frame"]), int(r["emit_ns"]), r["corrupted"] == "1") for r in csv.DictReader(f)]


def run_emreg_aurora(path: str, seconds: float, port: int) -> dict:
    """EMReg's live path for the Aurora: ndicapi driver -> navigator -> OpenIGTLink -> one TCP client."""
    source = open_source(f"aurora://{path}?baud=115200&rate={AURORA_RATE_HZ:g}")
    server = IGTLServer("127.0.0.1", port)
    drain = start_drain(server.port)
    server.wait_for_clients(1, 5.0)
    navigator = LiveNavigator(np.eye(4), 1, 2, server, None, period_s=1 / AURORA_RATE_HZ, out=None,
                              max_quality=None, trust=_trust())
    start = time.monotonic()
    source.start(navigator.on_sample)
    time.sleep(seconds)
    elapsed = time.monotonic() - start
    stats = source.driver.stats
    source.stop()
    server.close()
    drain.wait(timeout=10)
    return {"elapsed": elapsed, "stats": stats, "latencies": list(navigator.latencies),
            "published": navigator.published, "withheld": navigator.withheld}


def run_baseline_aurora(path: str, seconds: float) -> dict:
    """A plain loop on the same simulator: pyserial writes BX:0801, reads the reply by its length, sends it."""
    import serial

    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen(1)
    drain = start_drain(listener.getsockname()[1])
    conn, _ = listener.accept()
    conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    ser = serial.Serial(path, 9600, timeout=1.0)

    def ask(text: str) -> bytes:
        ser.write(ndi.frame_command(text))
        return ser.read_until(b"\r")

    ask("INIT:")
    ask("COMM:50000")
    time.sleep(0.1)
    ser.baudrate = 115200
    for h in AURORA_HANDLES:
        ask(f"PINIT:{h:02X}")
        ask(f"PENA:{h:02X}D")
    ask("TSTART:")
    bx = ndi.frame_command("BX:0801")
    sent: list[int] = []
    start_ns = time.monotonic_ns()
    stop = time.monotonic() + seconds
    while time.monotonic() < stop:
        ser.write(bx)
        header = ser.read(4)
        length = int.from_bytes(header[2:4], "little")
        reply = header + ser.read(length + 4)
        conn.sendall(reply)
        sent.append(time.monotonic_ns())
    ser.baudrate = 115200
    ask("TSTOP:")
    ser.close()
    conn.close()
    listener.close()
    drain.wait(timeout=10)
    return {"sent": sent, "start_ns": start_ns}


def bench_aurora(args: argparse.Namespace) -> None:
    reply_bytes = len(ndi.bx_reply([ndi.ToolReport(h, "valid", np.array([1.0, 0, 0, 0]), np.zeros(3))
                                    for h in AURORA_HANDLES]))
    line_s = (reply_bytes + len(ndi.frame_command("BX:0801"))) * 10 / 115200
    print(f"2 tools, BX:0801 at 115200 baud: {reply_bytes}-byte reply, {1e3 * line_s:.2f} ms of line time per poll "
          f"-> at most {1 / line_s:.0f} polls/s; measuring rate {AURORA_RATE_HZ:g} Hz")
    with tempfile.TemporaryDirectory() as tmp:
        link = Path(tmp) / "aurora"
        emit_log = Path(tmp) / "emit.csv"
        sim = subprocess.Popen([sys.executable, "-m", "EMRegModule", "sim-tracker", "--model", "aurora", "--tools",
                                "1:6dof,2:6dof", "--rate", str(AURORA_RATE_HZ), "--link", str(link), "--emit-log",
                                str(emit_log), "--duration", str(4 * args.seconds + 20), "--quiet"],
                               stdout=subprocess.PIPE, text=True, cwd=ROOT, env=dict(os.environ, PYTHONUNBUFFERED="1"))
        sim.stdout.readline()
        ours = run_emreg_aurora(str(link), args.seconds, args.igtl_port)
        time.sleep(0.3)
        base = run_baseline_aurora(str(link), args.seconds)
        sim.terminate()
        sim.wait(timeout=20)
        log = read_aurora_log(emit_log)

    st = ours["stats"]
    fps = st.frames / ours["elapsed"]
    print(f"\nEMReg driver (ndicapi): {st.frames} frames in {ours['elapsed']:.2f} s = {fps:.1f} frames/s "
          f"({100 * fps / AURORA_RATE_HZ:.1f}% of {AURORA_RATE_HZ:g} Hz); {st.polls} polls, {st.repeated} repeated "
          f"frame numbers, {st.missed_frames} frame numbers skipped, {st.rejected} replies rejected; "
          f"{ours['published']} ProbeToImage published, {ours['withheld']} withheld")
    first_emit: dict[int, int] = {}
    for frame, emit_ns, corrupted in log:
        if not corrupted and emit_ns and frame not in first_emit:
            first_emit.setdefault(frame, emit_ns)
    ours_ms = np.array([(sent - first_emit[f]) / 1e6 for f, _, sent in ours["latencies"] if f in first_emit])
    base_emits = [e for _, e, _ in log if e >= base["start_ns"]]
    base_ms = np.array([(t - e) / 1e6 for t, e in zip(base["sent"], base_emits, strict=False)])
    om, op = percentiles(ours_ms)
    bm, bp = percentiles(base_ms)
    print(f"\nlatency, last byte of the BX reply -> message handed to TCP (n = {len(ours_ms)}):")
    print(f"  EMReg (ndicapi CRC + parse, decode, watchdog, Eq. 12, OpenIGTLink TRANSFORM): median {om:.3f} ms, "
          f"p99 {op:.3f} ms")
    print(f"  baseline (raw pty read + socket send, n = {len(base_ms)}): median {bm:.3f} ms, p99 {bp:.3f} ms")
    print(f"  added by EMReg over the baseline: median {om - bm:+.3f} ms, p99 {op - bp:+.3f} ms")
    loss_free = st.missed_frames == 0 and st.rejected == 0
    print(f"\nno loss at {AURORA_RATE_HZ:g} Hz: {'yes' if loss_free else 'NO'}")


if __name__ == "__main__":
    sys.exit(main())
