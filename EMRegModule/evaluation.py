"""Evaluation: TRE at the targets and the board-phantom edge table (paper section 3, Table 1).

- **TRE.** The navigation recording is mapped into image space (paper Eq. 12); each dwell at
  a target (a labelled run, or an automatically found still period assigned to the nearest
  target) gives one error: the distance between the target and the dwell's robust mean
  probe position. Per target: mean, std, number of dwells; overall: over all dwells.
- **Board.** The board recording's probe positions are taken in the Reference frame (no
  registration involved: this measures the tracker and the probe). Each hole dwell gives a
  hole position; a round is one pass over the holes in order (a new round starts when the
  hole number does not increase). Per round the edge lengths L1 = |H1-H2|, L2 = |H2-H3|,
  L3 = |H3-H4|, L4 = |H4-H1|; per edge their mean, std and count, and, when the nominal
  edges are given (``case.toml`` ``[board] edges_mm``), the absolute and relative error of
  the mean and the mean +- std of the per-round errors (the paper's Table 1 layout).

Standard deviations are sample standard deviations (ddof = 1; 0 for a single value).
"""

from __future__ import annotations

import os
import re
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from .dwell import Dwell, DwellSettings, find_dwells, group_by_place, robust_mean
from .errors import EMRegError, NoSafeAnswerError
from .io.atomic import atomic_write_json
from .io.case import Case
from .tracking import TrackingRecording, probe_in_reference

#: Dwells farther than this from every target (mm) are not counted for TRE (unlabelled recordings).
DEFAULT_MAX_TARGET_DISTANCE_MM = 15.0
#: Stillness radius (mm) for finding dwells in navigation and board recordings without labels.
DEFAULT_STILL_RADIUS_MM = 1.0
#: Shortest unlabelled dwell (s) in navigation and board recordings: a hand-held probe held still
#: for 0.4 s at 80 Hz (32 samples, 0.39 s from first to last) is a dwell; a mid-air hesitation of
#: up to 0.3 s is not, nor is transit motion (it drifts more than twice the stillness radius, see
#: :class:`EMRegModule.dwell.DwellSettings`).
DEFAULT_MIN_DURATION_S = 0.35


def evaluation_dwell_settings(section: Mapping[str, Any] | None) -> DwellSettings:
    """Dwell settings of ``case.toml`` ``[evaluation]`` over the evaluation defaults (hand-held probe)."""
    section = {k: v for k, v in dict(section or {}).items() if k != "max_target_distance_mm"}
    return DwellSettings.from_settings({"still_radius_mm": DEFAULT_STILL_RADIUS_MM,
                                        "min_duration_s": DEFAULT_MIN_DURATION_S, **section}, "evaluation")


def evaluate_case(case: Case, reference_to_image: np.ndarray, reference_sensor: int = 1,
                  probe_sensor: int = 2, tolerant: bool = False) -> dict[str, Any]:
    """The ``evaluation.json`` content for a case folder: ``tre`` when the case has a navigation
    recording and targets, ``board`` when it has a board recording (see module docstring).

    ``reference_to_image``: Reference -> CT LPS (mm). Settings: ``case.toml`` ``[evaluation]``
    (dwell keys as in ``[calibration]``, ``still_radius_mm`` defaulting to 1 mm here, and
    ``max_target_distance_mm``) and ``[board] edges_mm``.

    ``tolerant`` (``emreg run``): a part that cannot be evaluated (no dwell found, a bad
    recording) is left out and named with its reason under ``not_evaluated`` and in ``warnings``
    instead of raising; ``emreg evaluate`` raises.
    """
    from .io.markups import read_markups
    from .io.recording import read_recording

    section = case.section("evaluation")
    # Hand-held touches at targets shake more than a probe resting in a pinhole: a wider
    # stillness radius and a shorter dwell by default (targets and holes are tens of mm apart).
    dwell_settings = evaluation_dwell_settings(section)
    result: dict[str, Any] = {}
    not_evaluated: dict[str, str] = {}
    warnings: list[str] = []  # time resets / gaps / invalid frames found in the recordings

    def part(name: str, compute) -> None:
        try:
            result[name] = compute()
        except NoSafeAnswerError:
            raise
        except EMRegError as exc:
            if not tolerant:
                raise
            not_evaluated[name] = str(exc)

    if case.navigation is not None and case.targets is not None:
        def tre() -> dict[str, Any]:
            labels, positions = read_markups(case.targets)
            recording = read_recording(case.navigation, case.settings, reference_sensor, probe_sensor)
            warnings.extend(recording.warnings)
            return evaluate_targets(
                recording, labels, positions, reference_to_image, reference_sensor, probe_sensor, dwell_settings,
                float(section.get("max_target_distance_mm", DEFAULT_MAX_TARGET_DISTANCE_MM)),
            )

        part("tre", tre)
    if case.board is not None:
        def board() -> dict[str, Any]:
            nominal = case.section("board").get("edges_mm")
            if nominal is not None:
                try:
                    nominal = [float(v) for v in nominal]
                except (TypeError, ValueError):
                    raise EMRegError(f"{case.folder / 'case.toml'}: [board] edges_mm must be a list of "
                                     "numbers") from None
            recording = read_recording(case.board, case.settings, reference_sensor, probe_sensor)
            warnings.extend(recording.warnings)
            return evaluate_board(recording, reference_sensor, probe_sensor, nominal, dwell_settings)

        part("board", board)
    if not_evaluated:
        result["not_evaluated"] = not_evaluated
        warnings += [f"{'TRE' if name == 'tre' else name} not evaluated: {reason}"
                     for name, reason in not_evaluated.items()]
    if warnings:
        result["warnings"] = warnings
    return result


# --- TRE -------------------------------------------------------------------------------------


def evaluate_targets(
    recording: TrackingRecording,
    target_labels: Sequence[str],
    targets_image: np.ndarray,
    reference_to_image: np.ndarray,
    reference_sensor: int = 1,
    probe_sensor: int = 2,
    settings: DwellSettings | None = None,
    max_target_distance_mm: float = DEFAULT_MAX_TARGET_DISTANCE_MM,
) -> dict[str, Any]:
    """TRE per target over its dwells and overall (mm). ``targets_image`` (K, 3) LPS mm."""
    from .navigation import navigate_recording

    targets_image = np.asarray(targets_image, dtype=float).reshape(-1, 3)
    if len(targets_image) == 0:
        raise EMRegError("evaluation: the targets file holds no target points")
    navigation = navigate_recording(recording, reference_to_image, reference_sensor, probe_sensor)
    position = navigation.position_mm
    dwells = find_dwells(navigation.time_s, position, navigation.label, navigation.quality, settings)
    index_of = {str(label): k for k, label in enumerate(target_labels)}
    per_target: dict[str, list[float]] = {str(label): [] for label in target_labels}
    details = []
    unmatched = 0
    for dwell in dwells:
        mean = robust_mean(position[dwell.indices]).mean
        if dwell.label:
            k = index_of.get(dwell.label)
            if k is None:
                unmatched += 1
                continue
        else:
            distance = np.linalg.norm(targets_image - mean, axis=1)
            k = int(np.argmin(distance))
            if distance[k] > max_target_distance_mm:
                unmatched += 1
                continue
        error = float(np.linalg.norm(mean - targets_image[k]))
        label = str(target_labels[k])
        per_target[label].append(error)
        details.append({"target": label, "error_mm": round(error, 4), "start_s": round(dwell.start_s, 4),
                        "end_s": round(dwell.end_s, 4), "samples": len(dwell),
                        "position": [round(float(v), 4) for v in mean]})
    errors = np.array([d["error_mm"] for d in details])
    if len(errors) == 0:
        from .dwell import describe_still_periods

        if dwells and dwells[0].label:
            seen = ", ".join(sorted({d.label for d in dwells})[:6])
            found = (f"{len(dwells)} labelled dwell(s), none with a target's label "
                     f"({seen} vs {', '.join(map(str, target_labels[:6]))})")
        else:
            found = (f"{len(dwells)} dwell(s), none within {max_target_distance_mm:g} mm of a target "
                     "([evaluation] max_target_distance_mm)" if dwells else
                     describe_still_periods(navigation.time_s, position, navigation.quality, settings,
                                            targets_image, "target"))
        raise EMRegError(f"{recording.source}: no probe dwell at any target was found: {found}")
    targets = {label: _stats(values) for label, values in per_target.items() if values}
    return {"mean_mm": round(float(errors.mean()), 4), "std_mm": round(_std(errors), 4), "n": len(errors),
            "max_mm": round(float(errors.max()), 4), "targets": targets, "dwells": details,
            "unmatched_dwells": unmatched, "labelled": bool(dwells and dwells[0].label)}


# --- board phantom ---------------------------------------------------------------------------


def evaluate_board(
    recording: TrackingRecording,
    reference_sensor: int = 1,
    probe_sensor: int = 2,
    nominal_edges_mm: Sequence[float] | None = None,
    settings: DwellSettings | None = None,
) -> dict[str, Any]:
    """Board-phantom edge lengths from a recording of the probe in each corner hole in turn
    (positions in the Reference frame; in the Tracker frame if the recording has no reference)."""
    settings = settings or DwellSettings()
    frame = "Reference"
    if reference_sensor in recording.sensors:
        samples = probe_in_reference(recording, reference_sensor, probe_sensor)
        time_s, position, labels, quality = samples.time_s, samples.position_mm, samples.label, samples.quality
    else:
        probe = recording.for_sensor(probe_sensor, "probe")
        time_s, position, labels, quality = probe.time_s, probe.position_mm, probe.label, probe.quality
        frame = "Tracker"
    dwells = find_dwells(time_s, position, labels, quality, settings)
    if not dwells:
        from .dwell import describe_still_periods

        raise EMRegError(f"{recording.source}: no probe dwell found in the board recording: "
                         + describe_still_periods(time_s, position, quality, settings, section="evaluation"))
    centres = np.array([robust_mean(position[d.indices]).mean for d in dwells])
    hole_of_dwell, hole_names = _board_holes(dwells, centres, settings)
    n_holes = len(hole_names)
    if n_holes < 3:
        raise EMRegError(f"{recording.source}: the board recording visits {n_holes} hole(s); at least 3 needed")
    rounds = _rounds(hole_of_dwell)
    edges: dict[str, Any] = {}
    nominal = None if nominal_edges_mm is None else list(nominal_edges_mm)
    if nominal is not None and len(nominal) != n_holes:
        raise EMRegError(f"case.toml [board] edges_mm has {len(nominal)} values but the board recording "
                         f"visits {n_holes} holes")
    for k in range(n_holes):
        h1, h2 = k, (k + 1) % n_holes
        lengths = []
        for round_dwells in rounds:
            if h1 in round_dwells and h2 in round_dwells:
                lengths.append(float(np.linalg.norm(centres[round_dwells[h1]] - centres[round_dwells[h2]])))
        entry = _stats(lengths)
        entry["holes"] = [hole_names[h1], hole_names[h2]]
        if nominal is not None and lengths:
            length = np.asarray(lengths)
            error = np.abs(length - nominal[k])
            entry.update({
                "nominal_mm": nominal[k],
                "abs_error_mm": round(abs(float(length.mean()) - nominal[k]), 4),
                "rel_error_percent": round(100 * abs(float(length.mean()) - nominal[k]) / nominal[k], 4),
                "abs_error_mean_mm": round(float(error.mean()), 4), "abs_error_std_mm": round(_std(error), 4),
                "rel_error_mean_percent": round(float(100 * (error / nominal[k]).mean()), 4),
                "rel_error_std_percent": round(100 * _std(error / nominal[k]), 4),
            })
        edges[f"L{k + 1}"] = entry
    holes = {name: [round(float(v), 4) for v in robust_mean(
        np.concatenate([position[dwells[d].indices] for d in np.nonzero(hole_of_dwell == h)[0]])).mean]
        for h, name in enumerate(hole_names)}
    return {"edges": edges, "rounds": len(rounds), "dwells": len(dwells), "frame": frame, "holes": holes,
            "labelled": bool(dwells[0].label)}


def _board_holes(dwells: list[Dwell], centres: np.ndarray, settings: DwellSettings) -> tuple[np.ndarray, list[str]]:
    """Hole number of each dwell and the hole names: by label (natural order: H1, H2, ...),
    or without labels by place, numbered in order of first visit."""
    if dwells[0].label:
        names = sorted({d.label for d in dwells}, key=_natural_key)
        return np.array([names.index(d.label) for d in dwells]), names
    group = group_by_place(centres, settings.merge_radius_mm)
    return group, [f"H{g + 1}" for g in range(int(group.max()) + 1)]


def _rounds(hole_of_dwell: np.ndarray) -> list[dict[int, int]]:
    """Split the dwell sequence into rounds (hole -> dwell index); a round ends when the hole
    number does not increase."""
    rounds: list[dict[int, int]] = []
    previous = None
    for d, hole in enumerate(hole_of_dwell.tolist()):
        if previous is None or hole <= previous:
            rounds.append({})
        rounds[-1][hole] = d
        previous = hole
    return rounds


def _natural_key(text: str) -> list[Any]:
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", text)]


def _std(values: Sequence[float] | np.ndarray) -> float:
    values = np.asarray(values, dtype=float)
    return float(values.std(ddof=1)) if len(values) > 1 else 0.0


def _stats(values: Sequence[float]) -> dict[str, Any]:
    values = np.asarray(values, dtype=float)
    if len(values) == 0:
        return {"mean_mm": None, "std_mm": None, "n": 0}
    return {"mean_mm": round(float(values.mean()), 4), "std_mm": round(_std(values), 4), "n": int(len(values))}


def write_evaluation(result: Mapping[str, Any], path: str | os.PathLike[str]) -> None:
    """Write ``evaluation.json`` atomically."""
    atomic_write_json(path, dict(result))
