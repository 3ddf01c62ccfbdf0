"""The trust study's navigation part: checkpoints at the pinholes and reference-jump warnings on simulated sessions.

One task: a calibration and registration (the real code), then a navigation of the targets with unlabelled
rests of the probe in marker pinholes, navigated and checked by the real code
(:func:`EMRegModule.core.checkpoints.check_navigation`, the case's ``[navigation]`` settings, the registration's
error model). The session is clean, or the reference sensor slips in its slot (``SLIP_MM`` / ``SLIP_DEG``)
halfway through, or the frame is knocked as a whole by as much (a bump: the reference jumps as in a slip but
nothing navigated changes, the control of the slip test of :mod:`EMRegModule.core.slip`), or a steel rod
(``ONSET_MM`` RMS non-rigid at the pinholes) is rolled in halfway through. Measured against the simulator's
truth: false checkpoint failures on clean sessions (and those of the fixed limit alone, for comparison; after a
bump every checkpoint is a clean one), whether the first checkpoint after the event failed (after a bump: a false
alarm), the alarm latency (event to the end of the first failed checkpoint: when it is judged), and the
reference-jump warnings. Times in s, errors in mm.
"""

from __future__ import annotations

import numpy as np

from ..core.checkpoints import Pinholes, check_navigation, find_checkpoints, pinholes_from_detection
from ..core.navigation import navigate_recording
from ..core.transforms import apply_transform, axis_angle_to_rotation, invert_rigid, make_transform
from ..names import DEFAULT_PROBE_PORT, DEFAULT_REFERENCE_PORT
from ..simulation.distortion import nonrigid_errors, place_object
from ..simulation.tracking import FieldOnset, FrameBump, ReferenceSlip
from .frame import (
    Frame,
    calibrate_and_register,
    noise_model,
    reference_placement,
    simulate_checked_navigation,
    with_noise,
)

#: The reference slip of the study (the issue's: 2 mm and 0.5 degrees, random directions).
SLIP_MM, SLIP_DEG = 2.0, 0.5
#: The distortion rolled in mid-navigation (RMS non-rigid at the pinholes, mm).
ONSET_MM = 1.0
#: Rests in pinholes per navigation, and rounds of the targets around them.
CHECKPOINTS, ROUNDS = 8, 3
#: The hard difficulty's tracking: twice the bad samples, mid-air pauses.
HARD = {"bad_sample_rate": 0.004, "hesitation_rate": 0.25}
#: A jump warned within this time (s) of the slip is the slip's.
JUMP_MATCH_S = 0.1


def checkpoint_rows(frame: Frame, params: dict, rng: np.random.Generator) -> list[dict]:
    """One session of event ``params["checkpoints"]`` (``clean``, ``slip``, ``bump`` or ``onset``) at tracker noise
    ``params["noise"]`` (``params["hard"]``: the hard difficulty's tracking): one row of what its checkpoints
    and jump warnings showed."""
    event = params["checkpoints"]
    noise = noise_model(params.get("noise", 1.0))
    hard = bool(params.get("hard"))
    if hard:
        noise = with_noise(noise, bad_sample_rate=HARD["bad_sample_rate"])
    placement = reference_placement(rng)
    session = calibrate_and_register(frame, rng, noise, reference_to_tracker=placement)
    row: dict = {**params, "refused": session.refused}
    if session.registration is None:
        return [row]
    slip = onset = distortion = bump = None
    if event in ("slip", "bump"):
        rotation = axis_angle_to_rotation(rng.normal(size=3), np.radians(SLIP_DEG))
        shift = rng.normal(size=3)
        step = make_transform(rotation, shift / np.linalg.norm(shift) * SLIP_MM)
        slip, bump = (ReferenceSlip(0.5, step), None) if event == "slip" else (None, FrameBump(0.5, step))
    elif event == "onset":
        distortion = place_object(rng, frame.pinholes, placement, np.eye(4), ONSET_MM)
        onset = FieldOnset(0.5)
    recording, dwells = simulate_checked_navigation(frame, rng, ROUNDS, CHECKPOINTS, noise, placement, slip,
                                                    distortion, onset, HARD["hesitation_rate"] if hard else 0.0,
                                                    bump)
    registration = session.registration
    navigation = navigate_recording(recording, registration.reference_to_image, DEFAULT_REFERENCE_PORT,
                                    DEFAULT_PROBE_PORT)
    settings = frame.settings.navigation
    pinholes = pinholes_from_detection(frame.detection, registration.sensor_offset_l_mm, registration)
    report = check_navigation(navigation, recording, pinholes, DEFAULT_REFERENCE_PORT, settings)
    fixed = find_checkpoints(navigation.time_s, navigation.position_mm, navigation.direction, navigation.quality,
                             Pinholes(pinholes.ids, pinholes.position_image, pinholes.axis_image), settings)
    rests = [d for d in dwells if not d.label]
    event_s = None if event == "clean" else next(e.time_s for e in (slip, bump, onset) if e is not None)
    settled_s = None if event_s is None else event_s + (distortion.ramp_s if distortion is not None else 0.0)
    clean = [c for c in report.checkpoints if event in ("clean", "bump") or c.end_s < event_s]
    clean_fixed = [c for c in fixed if event in ("clean", "bump") or c.end_s < event_s]
    row.update(rests=len(rests), found=len(report.checkpoints), clean_checkpoints=len(clean),
               clean_failed=sum(not c.ok for c in clean), clean_failed_fixed=sum(not c.ok for c in clean_fixed),
               largest_clean_error_mm=max((c.error_mm for c in clean), default=None),
               largest_threshold_mm=max((c.threshold_mm for c in report.checkpoints), default=None),
               largest_expected_mm=max((c.expected_mm for c in report.checkpoints), default=None),
               jumps=[j.time_s for j in report.reference_jumps], event_s=event_s,
               limit_mm=settings.max_checkpoint_error_mm)
    if settled_s is not None:
        row.update(_after_event(frame, report.checkpoints, rests, event_s, settled_s, slip, distortion, placement))
    return [row]


def _after_event(frame: Frame, checkpoints: list, rests: list, event_s: float, settled_s: float,
                 slip: ReferenceSlip | None, distortion, placement: np.ndarray) -> dict:
    """What the checkpoints after an event showed: the first one (failed?, error, true error there: 0 after a
    bump, slip test verdict), the latency to the first failed one (event to its end, s; None: none failed) and the
    rests that were not recognised."""
    after = [c for c in checkpoints if c.start_s >= settled_s]
    rests_after = [d for d in rests if d.start_s >= settled_s]
    truth = None
    if rests_after:
        pinhole = frame.pinholes[frame.labels.index(rests_after[0].name)]
        if slip is not None:
            truth = float(np.linalg.norm(apply_transform(invert_rigid(slip.reference_after_to_before), pinhole)
                                         - pinhole))
        elif distortion is None:  # a bump: everything moved together
            truth = 0.0
        else:
            raw, _ = nonrigid_errors(distortion, frame.pinholes, placement, np.eye(4), at_body=pinhole[None])
            truth = float(np.linalg.norm(raw[0]))
    failed = [c for c in checkpoints if c.end_s >= event_s and not c.ok]
    first = after[0] if after and rests_after and after[0].start_s <= rests_after[0].end_s else None
    return {"rests_after": len(rests_after), "found_after": len(after),
            "first_flagged": None if not rests_after else bool(first is not None and not first.ok),
            "first_recognised": None if not rests_after else first is not None,
            "first_error_mm": None if first is None else first.error_mm, "first_true_error_mm": truth,
            "first_slip_verdict": None if first is None or first.slip is None else first.slip.verdict,
            "first_within_threshold": None if first is None else bool(
                first.error_mm <= (first.threshold_mm if first.threshold_mm is not None else first.error_mm)),
            "latency_s": None if not failed else float(failed[0].end_s - event_s)}


def _percent(part: int, whole: int) -> str:
    return f"{100.0 * part / whole:.1f} % ({part}/{whole})" if whole else "-"


def checkpoint_table(rows: list[dict], width: int) -> tuple[list[list[str]], list[str]]:
    """The summary rows (``width`` cells: condition, sessions, refused, ``-`` for the distortion columns, then the
    checkpoint columns of :data:`CHECKPOINT_COLUMNS`) per event and noise, and the goal lines."""
    table, notes = [], []
    groups: dict = {}
    for r in rows:
        groups.setdefault((r["checkpoints"], bool(r.get("hard")), float(r.get("noise", 1.0))), []).append(r)
    for (event, hard, noise), group in sorted(groups.items()):
        done = [r for r in group if not r["refused"]]
        checked = sum(r["clean_checkpoints"] for r in done)
        failed = sum(r["clean_failed"] for r in done)
        failed_fixed = sum(r["clean_failed_fixed"] for r in done)
        clean_sessions = sum(r["clean_failed"] == 0 for r in done)
        firsts = [r for r in done if r.get("first_flagged") is not None]
        flagged = sum(bool(r["first_flagged"]) for r in firsts)
        latency = [r["latency_s"] for r in done if r.get("latency_s") is not None]
        warned = sum(any(abs(t - r["event_s"]) <= JUMP_MATCH_S for t in r["jumps"]) for r in done) \
            if event in ("slip", "bump") else None
        false_jumps = sum(sum(r["event_s"] is None or abs(t - r["event_s"]) > JUMP_MATCH_S for t in r["jumps"]) > 0
                          for r in done)
        name = {"clean": "clean", "slip": f"slip {SLIP_MM:g} mm/{SLIP_DEG:g} deg",
                "bump": f"bump {SLIP_MM:g} mm/{SLIP_DEG:g} deg (false alarms)",
                "onset": f"onset {ONSET_MM:g} mm"}[event]
        cells = [f"checkpoints: {name}, noise x{noise:g}{' hard' if hard else ''}", str(len(group)),
                 str(len(group) - len(done))]
        cells += ["-"] * (width - len(cells) - len(CHECKPOINT_COLUMNS))
        cells += [_percent(checked - failed, checked), _percent(clean_sessions, len(done)),
                  _percent(checked - failed_fixed, checked),
                  _percent(flagged, len(firsts)) if firsts else "-",
                  f"{np.median(latency):.1f} / {np.max(latency):.1f} ({len(latency)})" if latency else "-",
                  _percent(warned, len(done)) if warned is not None else "-", _percent(false_jumps, len(done))]
        table.append(cells)
        if event != "clean" and firsts:
            notes.append(_first_note(f"{name}, noise x{noise:g}{' hard' if hard else ''}", event, firsts))
    return table, notes


def _first_note(condition: str, event: str, firsts: list[dict]) -> str:
    """One line on the first checkpoints after the events: which were not flagged and why (or, after a bump, which
    failed), how many the slip test alone flagged, and the flagged share where the true error exceeds the limit."""
    verdicts = [r.get("first_slip_verdict") for r in firsts]
    tested = ", slip test " + ", ".join(f"{v} {verdicts.count(v)}" for v in ("confirmed", "open", "ruled_out")
                                        if verdicts.count(v)) if any(verdicts) else ""
    if event == "bump":
        failed = sum(bool(r["first_flagged"]) for r in firsts)
        return f"{condition}: {failed} of {len(firsts)} first checkpoint(s) after the bump failed{tested}"
    missed = [r for r in firsts if not r["first_flagged"]]
    unrecognised = sum(not r["first_recognised"] for r in missed)
    truths = [r["first_true_error_mm"] for r in missed if r["first_true_error_mm"] is not None]
    by_slip = sum(bool(r["first_flagged"]) and bool(r.get("first_within_threshold")) for r in firsts)
    beyond = [r for r in firsts if (r["first_true_error_mm"] or 0.0) > r.get("limit_mm", float("inf"))]
    return (f"{condition}: {len(missed)} first checkpoint(s) after the event not flagged ({unrecognised} not "
            "recognised as a checkpoint: error beyond the radius)"
            + (f", true error there {min(truths):.2f}-{max(truths):.2f} mm" if truths else "")
            + f"; {by_slip} flagged by the slip test alone (error within its threshold){tested}; where the true "
            f"error there exceeds the limit: {_percent(sum(bool(r['first_flagged']) for r in beyond), len(beyond))}"
            " flagged")


#: The checkpoint columns of the trust study's table.
CHECKPOINT_COLUMNS = ["clean checkpoints passed", "clean sessions all passed", "clean passed, fixed limit alone",
                      "flagged at the first checkpoint after", "alarm latency s (median / max)",
                      "reference jump warned", "sessions with a false jump warning"]
