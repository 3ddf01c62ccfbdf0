"""Evaluation: TRE at the targets and the board-phantom edge table (paper section 3, Table 1).

- **TRE.** The navigation recording is mapped into image space (paper Eq. 12); each dwell at
  a target (a labelled run, or an automatically found still period assigned to the nearest
  target) gives one error: the distance between the target and the dwell's robust mean
  probe position. Per target: mean, std, number of dwells; overall: over all dwells. Poses whose status is
  ``INVALID`` (``navigation.csv``: after a failed checkpoint until one passes, or a tracker quality number worse
  than ``[navigation] max_quality``; :mod:`EMRegModule.core.checkpoints`) are left out, as PLUS and SlicerIGT leave out
  a transform whose status is not OK, and counted (``invalid_poses_left_out``, ``dwells_left_out``).
- **Board.** The board recording's probe positions are taken in the Reference frame (no
  registration involved: this measures the tracker and the probe). Each hole dwell gives a
  hole position; a round is one pass over the holes in order (a new round starts when the
  hole number does not increase). Per round the edge lengths L1 = |H1-H2|, L2 = |H2-H3|,
  L3 = |H3-H4|, L4 = |H4-H1|; per edge their mean, std and count, and, when the nominal
  edges are given (``case.toml`` ``[board] edges_mm``), the absolute and relative error of
  the mean and the mean +- std of the per-round errors (the paper's Table 1 layout).

Standard deviations are sample standard deviations (ddof = 1; 0 for a single value).
The stages take recordings and targets already read and return typed results
(:class:`Evaluation`, :class:`TargetEvaluation`, :class:`BoardEvaluation`) that hold full-precision
values; ``to_json`` rounds (4 decimals) only when ``evaluation.json`` is written.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import EMRegError, NoSafeAnswerError
from ..names import DEFAULT_PROBE_PORT, DEFAULT_REFERENCE_PORT, EVALUATION_JSON
from ..settings import DwellSettings, EvaluationSettings
from .checkpoints import POSE_INVALID
from .dwell import Dwell, describe_still_periods, find_dwells, group_by_place, robust_mean
from .error_model import ErrorBudget, ErrorModel, optimism_limit, repeated_dwell_ms, satterthwaite_dof
from .navigation import NavigationResult, navigate_recording
from .tracking import TrackingRecording, probe_in_reference

#: The pose status of each navigated sample (``OK`` / ``INVALID``) of a recording, as ``navigation.csv`` gives it.
PoseStatus = Callable[[NavigationResult, TrackingRecording], np.ndarray]


# --- typed results ---------------------------------------------------------------------------


@dataclass
class Stats:
    """Mean, sample std (ddof 1; 0 for one value) and count of a set of lengths or errors (mm); None when empty."""

    mean_mm: float | None
    std_mm: float | None
    n: int

    @classmethod
    def of(cls, values: Sequence[float] | np.ndarray) -> Stats:
        values = np.asarray(values, dtype=float)
        if len(values) == 0:
            return cls(None, None, 0)
        return cls(float(values.mean()), _std(values), int(len(values)))

    def to_json(self) -> dict[str, Any]:
        return {"mean_mm": _round(self.mean_mm), "std_mm": _round(self.std_mm), "n": int(self.n)}

    @classmethod
    def from_json(cls, document: Mapping[str, Any]) -> Stats:
        return cls(_maybe_float(document.get("mean_mm")), _maybe_float(document.get("std_mm")), int(document["n"]))


@dataclass
class TargetDwell:
    """One dwell at a target: its error (mm), time span (s), samples, and mean probe position (LPS mm)."""

    target: str
    error_mm: float
    start_s: float
    end_s: float
    samples: int
    position: np.ndarray

    def to_json(self) -> dict[str, Any]:
        return {"target": self.target, "error_mm": round(self.error_mm, 4), "start_s": round(self.start_s, 4),
                "end_s": round(self.end_s, 4), "samples": int(self.samples),
                "position": [round(float(v), 4) for v in self.position]}

    @classmethod
    def from_json(cls, document: Mapping[str, Any]) -> TargetDwell:
        return cls(str(document["target"]), float(document["error_mm"]), float(document["start_s"]),
                   float(document["end_s"]), int(document["samples"]), np.asarray(document["position"], dtype=float))


@dataclass
class TargetPrediction:
    """The end-to-end RMS TRE predicted at one target (mm) and its budget: each term's own RMS (mm),
    adding in quadrature (registration, tracking, reference, placement; :mod:`EMRegModule.core.error_model`)."""

    predicted_rms_mm: float
    budget_rms_mm: dict[str, float]

    def to_json(self) -> dict[str, Any]:
        return {"predicted_rms_mm": _round(_finite_or_none(self.predicted_rms_mm)),
                "budget_rms_mm": {k: _round(_finite_or_none(v)) for k, v in self.budget_rms_mm.items()}}

    @classmethod
    def from_json(cls, document: Mapping[str, Any]) -> TargetPrediction:
        def number(value: Any) -> float:
            return float("inf") if value is None else float(value)

        return cls(number(document["predicted_rms_mm"]),
                   {str(k): number(v) for k, v in document.get("budget_rms_mm", {}).items()})


@dataclass
class TargetEvaluation:
    """TRE: one error per dwell at a target (``dwells``), statistics per target, dwells matched to no target.

    ``predictions``: per target the predicted end-to-end RMS TRE and its budget, when the evaluation
    had the registration's error model; ``tracking_rms_mm`` and ``tracking_source``: the probe's
    per-dwell error the predictions used and where it came from; ``warnings``: what the measured
    errors say of the prediction (one that they show to be optimistic). ``invalid_poses_left_out`` and
    ``dwells_left_out``: the navigated poses of status INVALID left out and the dwells (found with them) that
    were mostly theirs; None when no pose status was judged.
    """

    dwells: list[TargetDwell]
    targets: dict[str, Stats]
    unmatched_dwells: int = 0
    labelled: bool = False
    predictions: dict[str, TargetPrediction] = field(default_factory=dict)
    tracking_rms_mm: float | None = None
    tracking_source: str | None = None
    warnings: list[str] = field(default_factory=list)
    invalid_poses_left_out: int | None = None
    dwells_left_out: int | None = None

    @property
    def errors_mm(self) -> np.ndarray:
        return np.array([d.error_mm for d in self.dwells], dtype=float)

    @property
    def mean_mm(self) -> float:
        return float(self.errors_mm.mean())

    @property
    def std_mm(self) -> float:
        return _std(self.errors_mm)

    @property
    def predicted_rms_mm(self) -> float | None:
        """The predicted RMS TRE over all dwells (each target weighted by its dwells), or None."""
        if not self.predictions:
            return None
        counts = {label: stats.n for label, stats in self.targets.items()}
        squares = sum(counts[k] * p.predicted_rms_mm**2 for k, p in self.predictions.items())
        return float(np.sqrt(squares / sum(counts[k] for k in self.predictions)))

    def to_json(self) -> dict[str, Any]:
        """The ``tre`` block. Its overall figures are over the dwell errors as written (4 decimals), so the
        file is self-consistent: the ``dwells`` listed give back ``mean_mm``, ``std_mm``, ``rms_mm`` and ``max_mm``."""
        dwells = [d.to_json() for d in self.dwells]
        errors = np.array([d["error_mm"] for d in dwells])
        targets = {}
        for label, stats in self.targets.items():
            mine = np.array([d["error_mm"] for d in dwells if d["target"] == label])
            targets[label] = {**stats.to_json(), "rms_mm": _rms(mine)}
            if label in self.predictions:
                targets[label].update(self.predictions[label].to_json())
        document = {"mean_mm": round(float(errors.mean()), 4), "std_mm": round(_std(errors), 4), "n": len(errors),
                    "max_mm": round(float(errors.max()), 4), "rms_mm": _rms(errors), "targets": targets,
                    "dwells": dwells, "unmatched_dwells": int(self.unmatched_dwells), "labelled": bool(self.labelled)}
        if self.invalid_poses_left_out is not None:
            document.update(invalid_poses_left_out=int(self.invalid_poses_left_out),
                            dwells_left_out=int(self.dwells_left_out or 0))
        if self.predictions:
            document.update(predicted_rms_mm=_round(_finite_or_none(self.predicted_rms_mm)),
                            tracking_rms_mm=_round(self.tracking_rms_mm), tracking_source=self.tracking_source)
        return document

    @classmethod
    def from_json(cls, document: Mapping[str, Any]) -> TargetEvaluation:
        targets = document.get("targets", {})
        return cls([TargetDwell.from_json(d) for d in document.get("dwells", [])],
                   {str(k): Stats.from_json(v) for k, v in targets.items()},
                   int(document.get("unmatched_dwells", 0)), bool(document.get("labelled", False)),
                   {str(k): TargetPrediction.from_json(v) for k, v in targets.items() if "predicted_rms_mm" in v},
                   _maybe_float(document.get("tracking_rms_mm")), document.get("tracking_source"),
                   invalid_poses_left_out=_maybe_int(document.get("invalid_poses_left_out")),
                   dwells_left_out=_maybe_int(document.get("dwells_left_out")))


@dataclass
class BoardEdge:
    """One board edge between two holes: its length statistics over the rounds (mm) and, with a nominal
    length, the error of the mean and the mean +- std of the per-round errors (mm and percent)."""

    holes: tuple[str, str]
    length: Stats
    nominal_mm: float | None = None
    abs_error_mm: float | None = None
    rel_error_percent: float | None = None
    abs_error_mean_mm: float | None = None
    abs_error_std_mm: float | None = None
    rel_error_mean_percent: float | None = None
    rel_error_std_percent: float | None = None

    _ERROR_KEYS = ("abs_error_mm", "rel_error_percent", "abs_error_mean_mm", "abs_error_std_mm",
                   "rel_error_mean_percent", "rel_error_std_percent")

    @classmethod
    def measure(cls, holes: tuple[str, str], lengths: Sequence[float], nominal_mm: float | None) -> BoardEdge:
        edge = cls(holes, Stats.of(lengths))
        if nominal_mm is not None and len(lengths):
            length = np.asarray(lengths, dtype=float)
            error = np.abs(length - nominal_mm)
            mean_error = abs(float(length.mean()) - nominal_mm)
            edge.nominal_mm = nominal_mm
            edge.abs_error_mm, edge.rel_error_percent = mean_error, 100 * mean_error / nominal_mm
            edge.abs_error_mean_mm, edge.abs_error_std_mm = float(error.mean()), _std(error)
            edge.rel_error_mean_percent = float(100 * (error / nominal_mm).mean())
            edge.rel_error_std_percent = 100 * _std(error / nominal_mm)
        return edge

    def to_json(self) -> dict[str, Any]:
        document = {**self.length.to_json(), "holes": list(self.holes)}
        if self.nominal_mm is not None:
            document["nominal_mm"] = self.nominal_mm
            document.update({key: _round(getattr(self, key)) for key in self._ERROR_KEYS})
        return document

    @classmethod
    def from_json(cls, document: Mapping[str, Any]) -> BoardEdge:
        a, b = document["holes"]
        return cls((str(a), str(b)), Stats.from_json(document), _maybe_float(document.get("nominal_mm")),
                   **{key: _maybe_float(document.get(key)) for key in cls._ERROR_KEYS})


@dataclass
class BoardEvaluation:
    """The board-phantom table: edges L1..Ln, rounds and dwells counted, the frame the hole positions
    (``holes``, mm) are in, and whether the recording was labelled."""

    edges: dict[str, BoardEdge]
    rounds: int
    dwells: int
    frame: str
    holes: dict[str, np.ndarray]
    labelled: bool

    def to_json(self) -> dict[str, Any]:
        return {"edges": {k: v.to_json() for k, v in self.edges.items()}, "rounds": int(self.rounds),
                "dwells": int(self.dwells), "frame": self.frame,
                "holes": {k: [round(float(v), 4) for v in p] for k, p in self.holes.items()},
                "labelled": bool(self.labelled)}

    @classmethod
    def from_json(cls, document: Mapping[str, Any]) -> BoardEvaluation:
        return cls({str(k): BoardEdge.from_json(v) for k, v in document["edges"].items()}, int(document["rounds"]),
                   int(document["dwells"]), str(document["frame"]),
                   {str(k): np.asarray(v, dtype=float) for k, v in document.get("holes", {}).items()},
                   bool(document.get("labelled", False)))


@dataclass
class Evaluation:
    """What ``emreg evaluate`` found: ``tre`` (navigation recording and targets), ``board`` (board
    recording); either is None when its inputs are absent. ``extra`` keeps keys added by others."""

    tre: TargetEvaluation | None = None
    board: BoardEvaluation | None = None
    warnings: list[str] = field(default_factory=list)
    extra: dict[str, Any] = field(default_factory=dict)
    #: parts that could not be evaluated (``tre``, ``board``) and why (``emreg run``: the run still finishes)
    not_evaluated: dict[str, str] = field(default_factory=dict)
    provenance: dict[str, Any] | None = None  # what it was made from (``EMRegModule.io.provenance``)

    def to_json(self) -> dict[str, Any]:
        """The ``evaluation.json`` document (spec keys; values rounded to 4 decimals)."""
        document: dict[str, Any] = {}
        if self.tre is not None:
            document["tre"] = self.tre.to_json()
        if self.board is not None:
            document["board"] = self.board.to_json()
        if self.not_evaluated:
            document["not_evaluated"] = dict(self.not_evaluated)
        if self.warnings:
            document["warnings"] = list(self.warnings)
        document.update(self.extra)
        if self.provenance is not None:
            document["provenance"] = self.provenance
        return document

    @classmethod
    def from_json(cls, document: Mapping[str, Any], source: str = EVALUATION_JSON) -> Evaluation:
        """Parse an ``evaluation.json`` document; :class:`EMRegError` naming ``source`` if malformed."""
        try:
            tre = document.get("tre")
            board = document.get("board")
            return cls(None if tre is None else TargetEvaluation.from_json(tre),
                       None if board is None else BoardEvaluation.from_json(board),
                       [str(w) for w in document.get("warnings", [])],
                       {k: v for k, v in document.items()
                        if k not in ("tre", "board", "warnings", "not_evaluated", "provenance")},
                       {str(k): str(v) for k, v in (document.get("not_evaluated") or {}).items()},
                       document["provenance"] if isinstance(document.get("provenance"), dict) else None)
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise EMRegError(f"{source}: not an evaluation file ({exc!s:.100})") from None

    def summary(self) -> list[str]:
        """One line per part, for the terminal and ``run.json``."""
        lines = []
        if self.tre is not None:
            tre = self.tre.to_json()
            left_out = tre.get("invalid_poses_left_out")
            lines.append(f"evaluate: TRE {tre['mean_mm']:.2f} +/- {tre['std_mm']:.2f} mm"
                         + (f" ({left_out} INVALID poses left out)" if left_out else ""))
        if self.board is not None:
            edges = self.board.to_json()["edges"]
            lines.append("evaluate: board edges " + ", ".join(f"{k} {v['mean_mm']:.2f}" for k, v in edges.items()))
        for part, reason in self.not_evaluated.items():
            lines.append(f"evaluate: {_PART_NAMES.get(part, part)} not evaluated: {reason}")
        return lines


_PART_NAMES = {"tre": "TRE", "board": "board"}


def evaluate(
    reference_to_image: np.ndarray,
    reference_sensor: int,
    probe_sensor: int,
    settings: EvaluationSettings | None = None,
    navigation: TrackingRecording | None = None,
    targets: tuple[Sequence[str], np.ndarray] | None = None,
    board: TrackingRecording | None = None,
    nominal_edges_mm: Sequence[float] | None = None,
    error_model: ErrorModel | None = None,
    tolerant: bool = False,
    not_evaluated: Mapping[str, str] | None = None,
    tip_to_probe: np.ndarray | None = None,
    settings_file: str = "",
    pose_status: PoseStatus | None = None,
) -> Evaluation:
    """TRE when a navigation recording and targets (labels, (K, 3) LPS mm) are given, the board table
    when a board recording is; ``reference_to_image``: Reference -> CT LPS (mm).

    ``settings``: the ``[evaluation]`` table; ``nominal_edges_mm``: ``[board] edges_mm``;
    ``error_model``: the registration's, for the predicted TRE beside the measured one.
    ``tolerant`` (``emreg run``): a part that cannot be evaluated (no dwell found, a bad recording) is
    left out and named with its reason in ``not_evaluated`` and ``warnings`` instead of raising
    (``emreg evaluate`` raises); ``not_evaluated``: parts the caller could not even read, with why.
    ``tip_to_probe`` (4x4, mm): a tool's tip (:mod:`EMRegModule.core.tool`), the point put on the targets and holes.
    ``pose_status``: the status of each navigated pose (as ``navigation.csv`` has it): INVALID ones are left out
    of the TRE (None: every pose counts).
    """
    settings = settings or EvaluationSettings()
    result = Evaluation(not_evaluated=dict(not_evaluated or {}))

    def part(name: str, compute) -> Any:
        try:
            return compute()
        except NoSafeAnswerError:
            raise
        except EMRegError as exc:
            if not tolerant:
                raise
            result.not_evaluated[name] = str(exc)
            return None

    if navigation is not None and targets is not None:
        labels, positions = targets
        result.tre = part("tre", lambda: evaluate_targets(
            navigation, labels, positions, reference_to_image, reference_sensor, probe_sensor, settings,
            settings.max_target_distance_mm, error_model, tip_to_probe, pose_status))
        result.warnings += navigation.warnings
        if result.tre is not None:
            result.warnings += result.tre.warnings
    if board is not None:
        result.board = part("board", lambda: evaluate_board(board, reference_sensor, probe_sensor, nominal_edges_mm,
                                                            settings, tip_to_probe, settings_file))
        result.warnings += board.warnings  # time resets / gaps / invalid frames found in the recordings
    result.warnings += [f"{_PART_NAMES.get(name, name)} not evaluated: {reason}"
                        for name, reason in result.not_evaluated.items()]
    return result


# --- TRE -------------------------------------------------------------------------------------


def evaluate_targets(
    recording: TrackingRecording,
    target_labels: Sequence[str],
    targets_image: np.ndarray,
    reference_to_image: np.ndarray,
    reference_sensor: int = DEFAULT_REFERENCE_PORT,
    probe_sensor: int = DEFAULT_PROBE_PORT,
    settings: DwellSettings | None = None,
    max_target_distance_mm: float | None = None,
    error_model: ErrorModel | None = None,
    tip_to_probe: np.ndarray | None = None,
    pose_status: PoseStatus | None = None,
) -> TargetEvaluation:
    """TRE per target over its dwells and overall (mm). ``targets_image`` (K, 3) LPS mm.

    ``max_target_distance_mm``: an unlabelled dwell farther from every target is not counted
    (default: the ``[evaluation]`` default). With ``error_model`` (the registration's), each target
    also gets the predicted end-to-end RMS TRE and its budget; the tracking term is then measured
    from the scatter of repeated dwells at the same target when there are any. ``pose_status``: the
    status of each navigated pose; INVALID poses are no part of any dwell (:func:`valid_poses`).
    """
    if max_target_distance_mm is None:
        max_target_distance_mm = EvaluationSettings().max_target_distance_mm
    targets_image = np.asarray(targets_image, dtype=float).reshape(-1, 3)
    if len(targets_image) == 0:
        raise EMRegError("evaluation: the targets file holds no target points")
    navigation = navigate_recording(recording, reference_to_image, reference_sensor, probe_sensor, tip_to_probe)
    position, invalid, left_out = valid_poses(navigation, recording, pose_status, settings)
    dwells = find_dwells(navigation.time_s, position, navigation.label, navigation.quality, settings,
                         source=recording.source, section="evaluation")
    index_of = {str(label): k for k, label in enumerate(target_labels)}
    per_target: dict[str, list[float]] = {str(label): [] for label in target_labels}
    found: list[TargetDwell] = []
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
        found.append(TargetDwell(label, error, float(dwell.start_s), float(dwell.end_s), len(dwell), mean))
    if not found:
        what = _no_dwell(dwells, target_labels, targets_image, navigation.time_s, position, navigation.quality,
                         settings, max_target_distance_mm)
        if invalid is not None and invalid.any():
            what += (f"; {int(invalid.sum())} INVALID poses (a failed checkpoint, a bad tracker quality) were left "
                     f"out, {left_out} dwell(s) among them")
        raise EMRegError(f"{recording.source}: no probe dwell at any target was found: {what}")
    targets = {label: Stats.of(values) for label, values in per_target.items() if values}
    result = TargetEvaluation(found, targets, unmatched, bool(dwells and dwells[0].label))
    if invalid is not None:
        result.invalid_poses_left_out, result.dwells_left_out = int(invalid.sum()), left_out
        if left_out:  # (a few bad samples alone, never part of a dwell anyway, are only counted)
            result.warnings.append(
                f"TRE: {int(invalid.sum())} of {len(invalid)} navigated poses are INVALID (after a failed checkpoint "
                "until one passes, or a tracker quality number worse than [navigation] max_quality: navigation.csv) "
                f"and left out; {left_out} dwell(s) were mostly theirs")
    if error_model is not None:
        _predict(result, target_labels, targets_image, error_model)
    return result


def valid_poses(navigation: NavigationResult, recording: TrackingRecording, pose_status: PoseStatus | None,
                settings: DwellSettings | None) -> tuple[np.ndarray, np.ndarray | None, int]:
    """The navigated positions (N, 3, LPS mm) with the INVALID poses' set to NaN (no dwell uses them), the INVALID
    mask (N,) and how many dwells found with every pose were mostly INVALID; (positions, None, 0) without
    ``pose_status``."""
    position = navigation.position_mm
    if pose_status is None:
        return position, None, 0
    invalid = np.asarray(pose_status(navigation, recording)) == POSE_INVALID
    if not invalid.any():
        return position, invalid, 0
    every = find_dwells(navigation.time_s, position, navigation.label, navigation.quality, settings,
                        source=recording.source, section="evaluation")
    left_out = sum(float(np.mean(invalid[d.indices])) > 0.5 for d in every)
    return np.where(invalid[:, None], np.nan, position), invalid, int(left_out)


def _no_dwell(dwells: list[Dwell], target_labels: Sequence[str], targets_image: np.ndarray, time_s: np.ndarray,
              position: np.ndarray, quality: np.ndarray, settings: DwellSettings | None,
              max_target_distance_mm: float) -> str:
    """Why no dwell at a target was found (for the error message)."""
    if dwells and dwells[0].label:
        seen = ", ".join(sorted({d.label for d in dwells})[:6])
        return (f"{len(dwells)} labelled dwell(s), none with a target's label "
                f"({seen} vs {', '.join(map(str, list(target_labels)[:6]))})")
    if dwells:
        return (f"{len(dwells)} dwell(s), none within {max_target_distance_mm:g} mm of a target "
                "([evaluation] max_target_distance_mm)")
    return describe_still_periods(time_s, position, quality, settings, targets_image, "target")


def _predict(result: TargetEvaluation, target_labels: Sequence[str], targets_image: np.ndarray,
             error_model: ErrorModel) -> None:
    """Fill ``result.predictions``: the error model's budget at each visited target."""
    means: dict[str, list[np.ndarray]] = {}
    for dwell in result.dwells:
        means.setdefault(dwell.target, []).append(dwell.position)
    repeated = repeated_dwell_ms({k: np.array(v) for k, v in means.items()})
    budget = error_model.budget(targets_image, None if repeated is None else repeated[0])
    terms = budget.term_rms_mm()
    for k, label in enumerate(map(str, target_labels)):
        if label in result.targets:
            result.predictions[label] = TargetPrediction(float(budget.rms_mm[k]),
                                                         {name: float(v[k]) for name, v in terms.items()})
    result.tracking_rms_mm = float(np.sqrt(budget.tracking_ms[0]))
    result.tracking_source = "repeated dwells at the targets" if repeated is not None else "calibration"
    calibration_dof = error_model.registration.probe_sigma_dof
    tracking_dof = 3.0 * repeated[1] if repeated is not None else calibration_dof
    warning = _optimism_warning(result, target_labels, budget, calibration_dof, tracking_dof)
    if warning:
        result.warnings.append(warning)


def _optimism_warning(result: TargetEvaluation, target_labels: Sequence[str], budget: ErrorBudget,
                      calibration_dof: float, tracking_dof: float) -> str | None:
    """A warning when the measured RMS TRE is above the prediction by more than the model's own randomness
    explains (:func:`EMRegModule.core.error_model.optimism_limit`, false alarm 1 in 1000), else None."""
    row = {str(label): k for k, label in enumerate(target_labels)}
    visited = np.array([row[d.target] for d in result.dwells])
    common = budget.registration_ms[visited] + budget.reference_ms[visited]
    if budget.distortion_ms is not None:  # the same field at every dwell on a target
        common = common + budget.distortion_ms[visited]
    independent = budget.tracking_ms[visited] + budget.placement_ms[visited]
    predicted_ms = float(np.mean(common + independent))
    if not np.isfinite(predicted_ms) or predicted_ms <= 0:
        return None
    measured_ms = float(np.mean(result.errors_mm**2))
    prediction_dof = satterthwaite_dof(
        [float(np.mean(common)), float(np.mean(budget.tracking_ms[visited])),
         float(np.mean(budget.placement_ms[visited]))], [calibration_dof, tracking_dof, float("inf")])
    limit = optimism_limit(float(np.mean(common)), float(np.mean(independent)), len(visited), prediction_dof)
    if measured_ms <= limit * predicted_ms:
        return None
    return (f"measured RMS TRE {np.sqrt(measured_ms):.2f} mm over {len(visited)} dwells is "
            f"{np.sqrt(measured_ms / predicted_ms):.1f} x the predicted {np.sqrt(predicted_ms):.2f} mm (the model's "
            f"own scatter allows up to {np.sqrt(limit):.2f} x): the prediction is optimistic; an error it does not "
            "model is present (probe tip not where its sensor reports it, reference sensor moved on the patient, wrong "
            "fixed sensor offset l, field distortion): trust the measured TRE, not the prediction or tre_map.nrrd")


# --- board phantom ---------------------------------------------------------------------------


def evaluate_board(
    recording: TrackingRecording,
    reference_sensor: int = DEFAULT_REFERENCE_PORT,
    probe_sensor: int = DEFAULT_PROBE_PORT,
    nominal_edges_mm: Sequence[float] | None = None,
    settings: DwellSettings | None = None,
    tip_to_probe: np.ndarray | None = None,
    settings_file: str = "",
) -> BoardEvaluation:
    """Board-phantom edge lengths from a recording of the probe in each corner hole in turn
    (positions in the Reference frame; in the Tracker frame if the recording has no reference);
    ``tip_to_probe``: a tool's tip, the point put in the holes; ``settings_file``: the settings file
    ``nominal_edges_mm`` came from (named when it does not fit)."""
    settings = settings or DwellSettings()
    frame = "Reference"
    if reference_sensor in recording.sensors:
        samples = probe_in_reference(recording, reference_sensor, probe_sensor)
        time_s, labels, quality = samples.time_s, samples.label, samples.quality
        poses = samples.probe_to_reference
    else:
        probe = recording.for_sensor(probe_sensor, "probe")
        time_s, labels, quality = probe.time_s, probe.label, probe.quality
        poses = probe.transforms()
        frame = "Tracker"
    position = poses[:, :3, 3] if tip_to_probe is None else (poses @ tip_to_probe)[:, :3, 3]
    dwells = find_dwells(time_s, position, labels, quality, settings, source=recording.source, section="evaluation")
    if not dwells:
        raise EMRegError(f"{recording.source}: no probe dwell found in the board recording: "
                         + describe_still_periods(time_s, position, quality, settings))
    centres = np.array([robust_mean(position[d.indices]).mean for d in dwells])
    hole_of_dwell, hole_names = _board_holes(dwells, centres, settings)
    n_holes = len(hole_names)
    if n_holes < 3:
        raise EMRegError(f"{recording.source}: the board recording visits {n_holes} hole(s); at least 3 needed")
    rounds = _rounds(hole_of_dwell)
    nominal = None if nominal_edges_mm is None else [float(v) for v in nominal_edges_mm]
    if nominal is not None and len(nominal) != n_holes:
        raise EMRegError(f"{settings_file or 'the settings'}: [board] edges_mm has {len(nominal)} values but the "
                         f"board recording {recording.source} visits {n_holes} holes")
    edges: dict[str, BoardEdge] = {}
    for k in range(n_holes):
        h1, h2 = k, (k + 1) % n_holes
        lengths = [float(np.linalg.norm(centres[r[h1]] - centres[r[h2]])) for r in rounds if h1 in r and h2 in r]
        edges[f"L{k + 1}"] = BoardEdge.measure((hole_names[h1], hole_names[h2]), lengths,
                                               None if nominal is None else nominal[k])
    holes = {name: robust_mean(np.concatenate([position[dwells[d].indices]
                                               for d in np.nonzero(hole_of_dwell == h)[0]])).mean
             for h, name in enumerate(hole_names)}
    return BoardEvaluation(edges, len(rounds), len(dwells), frame, holes, bool(dwells[0].label))


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


def _round(value: float | None, digits: int = 4) -> float | None:
    return None if value is None else round(float(value), digits)


def _rms(errors: np.ndarray) -> float:
    return round(float(np.sqrt(np.mean(np.square(errors)))), 4)


def _finite_or_none(value: float | None) -> float | None:
    """A prediction for JSON: None (null) when the configuration does not determine it (infinite)."""
    return None if value is None or not np.isfinite(value) else float(value)


def _maybe_float(value: Any) -> float | None:
    return None if value is None else float(value)


def _maybe_int(value: Any) -> int | None:
    return None if value is None else int(value)


