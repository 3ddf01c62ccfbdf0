"""The accuracy studies: what each varies (its tasks), what one task measures, and how rows are summarised.

Each study is a list of independent tasks (one simulated session each, seeded from the study's
seed and the task's index, so results do not depend on how many workers run them); a task returns
JSON-able rows; the summary turns all rows into a table and a figure. Errors are against the
simulator's ground truth. Units: mm.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..core.error_model import ErrorModel
from ..core.evaluation import evaluate_board, evaluate_targets
from ..core.tool import pivot_calibration
from ..core.tracking import probe_in_reference
from ..io.case import open_case
from ..names import DEFAULT_PROBE_PORT, DEFAULT_REFERENCE_PORT
from ..rendering.plots import bar_chart, line_chart
from ..simulation.distortion import nonrigid_errors
from ..simulation.field_families import DEVELOPMENT, FAMILIES, HELD_OUT, place_field
from ..simulation.stylus import simulate_pivot_recording
from .checkpoints import CHECKPOINT_COLUMNS, checkpoint_rows, checkpoint_table
from .frame import Frame, calibrate_and_register, noise_model, reference_placement, simulate_navigation, with_noise

#: The paper's figures (Lin et al. 2020) printed beside ours.
PAPER = {"calibration_fre_mean_mm": 1.38, "tre_mean_mm": 1.38, "tre_std_mm": 0.32,
         "board_abs_error_mm": {"L1": 0.18, "L2": 0.19, "L3": 0.21, "L4": 0.16}}


@dataclass(frozen=True)
class Summary:
    """A study's result: a table (header + rows of text) and a figure (RGB image)."""

    header: list[str]
    rows: list[list[str]]
    figure: np.ndarray
    notes: list[str]


@dataclass(frozen=True)
class Study:
    """One study: ``tasks(quick)`` -> parameters per task; ``run(frame, params, rng)`` -> rows; ``summarize``."""

    name: str
    title: str
    tasks: Callable[[bool], list[dict]]
    run: Callable[[Frame, dict, np.random.Generator], list[dict]]
    summarize: Callable[[list[dict]], Summary]


def _mean_std(values: list[float] | np.ndarray) -> str:
    values = np.asarray(values, dtype=float)
    if values.size == 0:
        return "-"
    return f"{values.mean():.2f} +/- {values.std(ddof=1) if values.size > 1 else 0.0:.2f}"


def _session_rows(frame: Frame, params: dict, rng: np.random.Generator) -> list[dict]:
    """One calibration + registration: FRE, l error, the registration's true RMS error at the targets."""
    subset = None
    if params.get("markers"):
        available = np.nonzero(frame.in_ct)[0]
        subset = np.sort(rng.choice(available, min(params["markers"], len(available)), replace=False))
    session = calibrate_and_register(frame, rng, noise_model(params.get("noise", 1.0)), subset)
    row = {**params, "refused": session.refused}
    if session.registration is not None:
        row.update(fre_mm=session.registration.fre_mm, l_error_mm=session.l_error_mm,
                   registration_tre_rms_mm=float(np.sqrt(np.mean(session.target_errors_mm**2))),
                   worst_target_mm=float(np.max(session.target_errors_mm)))
    return [row]


# --- calibration: FRE over repeated calibrations (paper Fig. 8) -------------------------------


def _calibration_summary(rows: list[dict]) -> Summary:
    done = [r for r in rows if not r["refused"]]
    fre = [r["fre_mm"] for r in done]
    table = [["calibrations", f"{len(done)} ({len(rows) - len(done)} refused)", "30"],
             ["FRE mean (mm)", f"{np.mean(fre):.2f}" if fre else "-", f"{PAPER['calibration_fre_mean_mm']:.2f}"],
             ["FRE std (mm)", _mean_std(fre).split(" +/- ")[-1], "n/a"],
             ["l error mean +/- std (mm)", _mean_std([r["l_error_mm"] for r in done]), "n/a (l unknown)"],
             ["registration error at targets, RMS (mm)", _mean_std([r["registration_tre_rms_mm"] for r in done]),
              "n/a"]]
    figure = bar_chart([str(r["task"] + 1) for r in done], fre, title="FRE per calibration", y_label="FRE (mm)",
                       reference_lines=[(PAPER["calibration_fre_mean_mm"], "paper mean")])
    return Summary(["figure", "EMReg (simulated)", "paper"], table, figure, [])


# --- board: edge lengths (paper Table 1) -------------------------------------------------------


def _board_rows(frame: Frame, params: dict, rng: np.random.Generator) -> list[dict]:
    case = open_case(frame.case_dir)
    nominal = [float(v) for v in frame.truth["board"]["edges_mm"]]
    result = evaluate_board(case.read_recording("board"), case.reference_sensor, case.probe_sensor,
                            nominal).to_json()
    return [{"edge": name, "mean_mm": e["mean_mm"], "std_mm": e["std_mm"], "nominal_mm": e["nominal_mm"],
             "abs_error_mean_mm": e["abs_error_mean_mm"], "abs_error_std_mm": e["abs_error_std_mm"]}
            for name, e in result["edges"].items()]


def _board_summary(rows: list[dict]) -> Summary:
    table = [[r["edge"], f"{r['mean_mm']:.2f}", f"{r['std_mm']:.2f}", f"{r['nominal_mm']:.2f}",
              f"{r['abs_error_mean_mm']:.2f} +/- {r['abs_error_std_mm']:.2f}",
              f"{PAPER['board_abs_error_mm'].get(r['edge'], float('nan')):.2f}"] for r in rows]
    figure = bar_chart([r["edge"] for r in rows], [r["abs_error_mean_mm"] for r in rows],
                       [r["abs_error_std_mm"] for r in rows], title="Board phantom: absolute edge error",
                       y_label="mm", overlay=[PAPER["board_abs_error_mm"].get(r["edge"], np.nan) for r in rows],
                       overlay_label="paper")
    return Summary(["edge", "mean (mm)", "sigma", "nominal", "abs error (mm)", "paper abs error"], table, figure, [])


# --- tre: 6 targets x placements (paper Fig. 12) -------------------------------------------------


def _navigation_rows(frame: Frame, params: dict, rng: np.random.Generator) -> list[dict]:
    """One registration and one navigation session: per target measured and predicted RMS TRE."""
    noise = noise_model(params.get("noise", 1.0))
    if params.get("reference_jitter"):
        noise = with_noise(noise, reference_jitter_mm=noise.reference_jitter_mm * params["reference_jitter"],
                           reference_jitter_deg=noise.reference_jitter_deg * params["reference_jitter"])
    subset = None
    if params.get("markers"):
        available = np.nonzero(frame.in_ct)[0]
        subset = np.sort(rng.choice(available, min(params["markers"], len(available)), replace=False))
    session = calibrate_and_register(frame, rng, noise, subset)
    if session.registration is None:
        return [{**params, "refused": session.refused}]
    model = ErrorModel.with_priors(session.registration.reference_to_image, session.registration.error)
    recording = simulate_navigation(frame, rng, rounds=params.get("placements", 15), noise=noise)
    result = evaluate_targets(recording, frame.target_labels, frame.targets_image,
                              session.registration.reference_to_image, error_model=model).to_json()
    calibration_only = model.budget(frame.targets_image).rms_mm
    rows = []
    for k, label in enumerate(frame.target_labels):
        target = result["targets"].get(label)
        if target is None:
            continue
        errors = [d["error_mm"] for d in result["dwells"] if d["target"] == label]
        rows.append({**params, "refused": None, "target": label, "errors_mm": errors,
                     "measured_rms_mm": target["rms_mm"], "predicted_rms_mm": target["predicted_rms_mm"],
                     "predicted_before_navigation_rms_mm": float(calibration_only[k]),
                     "budget_rms_mm": target["budget_rms_mm"]})
    return rows


def _tre_summary(rows: list[dict]) -> Summary:
    done = [r for r in rows if not r["refused"]]
    labels = sorted({r["target"] for r in done})
    errors = {label: [e for r in done if r["target"] == label for e in r["errors_mm"]] for label in labels}
    overall = [e for v in errors.values() for e in v]
    table = [[label, str(len(v)), _mean_std(v), f"{np.max(v):.2f}"] for label, v in errors.items()]
    table.append(["all", str(len(overall)), _mean_std(overall), f"{np.max(overall):.2f}" if overall else "-"])
    figure = bar_chart(labels, [np.mean(errors[label]) for label in labels],
                       [np.std(errors[label], ddof=1) if len(errors[label]) > 1 else 0.0 for label in labels],
                       title="TRE per target", y_label="TRE (mm)",
                       reference_lines=[(PAPER["tre_mean_mm"], "paper mean")])
    notes = [f"paper (Fig. 12): {PAPER['tre_mean_mm']:.2f} +/- {PAPER['tre_std_mm']:.2f} mm"]
    return Summary(["target", "placements", "TRE mean +/- std (mm)", "max (mm)"], table, figure, notes)


# --- tool: the paper's pinhole probe against a pivot-calibrated pointer ------------------------------------

#: The pointer of the ``tool`` study: the tip 150 mm along its sensor's +X, a little off the axis.
POINTER_TIP_MM = (150.0, 1.5, -2.0)


def _tool_rows(frame: Frame, params: dict, rng: np.random.Generator) -> list[dict]:
    """One session of a route on the same frame and noise: ``pinhole`` (the paper's probe, depth l solved by FRE)
    or ``pivot`` (a pointer calibrated by a simulated pivot, then touching the pinholes and the targets with its
    tip). Rows: the tip's error, FRE, the registration's RMS error at the targets, the measured end-to-end TRE."""
    noise = noise_model(params.get("noise", 1.0))
    tool, tip_error, true_tip = None, None, None
    if params["route"] == "pivot":
        true_tip = np.asarray(POINTER_TIP_MM)
        pivot, _ = simulate_pivot_recording(int(rng.integers(1 << 31)), true_tip, 30.0, noise=noise)
        in_reference = probe_in_reference(pivot, DEFAULT_REFERENCE_PORT, DEFAULT_PROBE_PORT, check_ports=False)
        tool = pivot_calibration(in_reference.probe_to_reference, "pivot")
        tip_error = float(np.linalg.norm(tool.tip_mm - true_tip))
    session = calibrate_and_register(frame, rng, noise, tool=tool, true_tip_mm=true_tip)
    row = {**params, "refused": session.refused, "tip_error_mm": tip_error}
    if session.registration is None:
        return [row]
    recording = simulate_navigation(frame, rng, rounds=params.get("placements", 5), noise=noise, tip_mm=true_tip)
    result = evaluate_targets(recording, frame.target_labels, frame.targets_image,
                              session.registration.reference_to_image,
                              tip_to_probe=None if tool is None else tool.tip_to_probe).to_json()
    errors = [d["error_mm"] for d in result["dwells"]]
    row.update(fre_mm=session.registration.fre_mm,
               registration_tre_rms_mm=float(np.sqrt(np.mean(session.target_errors_mm**2))),
               tre_rms_mm=float(np.sqrt(np.mean(np.square(errors)))) if errors else None)
    return [row]


def _tool_summary(rows: list[dict]) -> Summary:
    table, names, values = [], [], []
    for route, group in _by(rows, "route").items():
        done = [r for r in group if not r["refused"]]
        tips = [r["tip_error_mm"] for r in done if r["tip_error_mm"] is not None]
        tre = [r["tre_rms_mm"] for r in done if r["tre_rms_mm"] is not None]
        table.append([{"pinhole": "pinhole probe, l by FRE (paper)", "pivot": "pivot-calibrated pointer"}[route],
                      f"{len(group) - len(done)}/{len(group)}", _mean_std(tips) if tips else "-",
                      _mean_std([r["fre_mm"] for r in done]), _mean_std([r["registration_tre_rms_mm"] for r in done]),
                      _mean_std(tre)])
        names.append(route)
        values.append(float(np.mean(tre)) if tre else float("nan"))
    figure = bar_chart(names, values, title="End-to-end TRE: pinhole probe vs pivot-calibrated pointer",
                       y_label="RMS TRE (mm)")
    return Summary(["route", "refused", "tip error (mm)", "FRE (mm)", "registration TRE RMS (mm)",
                    "end-to-end TRE RMS (mm)"], table, figure,
                   [f"pointer tip {POINTER_TIP_MM} mm from its sensor, pivot-calibrated with 30-degree swings at the "
                    "same tracker noise; the paper reports the pivot route costing about 2 mm"])


# --- noise and markers: registration accuracy against tracker noise and marker count ----------


def _by(rows: list[dict], key: str) -> dict:
    groups: dict = {}
    for r in rows:
        groups.setdefault(r[key], []).append(r)
    return dict(sorted(groups.items()))


def _sweep_summary(key: str, label: str) -> Callable[[list[dict]], Summary]:
    def summarize(rows: list[dict]) -> Summary:
        table, x, y = [], [], []
        for value, group in _by(rows, key).items():
            done = [r for r in group if not r["refused"]]
            tre = [r["registration_tre_rms_mm"] for r in done]
            table.append([f"{value:g}", f"{len(group) - len(done)}/{len(group)}",
                          _mean_std([r["fre_mm"] for r in done]), _mean_std(tre),
                          f"{np.mean([abs(r['l_error_mm']) for r in done]):.2f}" if done else "-"])
            if tre:
                x.append(value)
                y.append(float(np.mean(tre)))
        figure = line_chart(x, y, title=f"Registration error against {label}", x_label=label,
                            y_label="RMS at targets (mm)") if len(x) > 1 else bar_chart(
            [f"{v:g}" for v in x], y, title=f"Registration error against {label}", y_label="mm")
        return Summary([label, "refused", "FRE (mm)", "registration TRE RMS (mm)", "mean |l error| (mm)"], table,
                       figure, [])

    return summarize


# --- prediction: predicted vs measured end-to-end TRE ----------------------------------------------


def _prediction_summary(rows: list[dict]) -> Summary:
    done = [r for r in rows if not r["refused"]]
    table = []
    conditions = sorted({(r.get("noise", 1.0), r.get("markers") or 0, r.get("reference_jitter") or 1.0)
                         for r in done})
    ratios_all = []
    for noise, markers, jitter in conditions:
        group = [r for r in done if (r.get("noise", 1.0), r.get("markers") or 0,
                                     r.get("reference_jitter") or 1.0) == (noise, markers, jitter)]
        measured = np.sqrt(np.mean([e**2 for r in group for e in r["errors_mm"]]))
        predicted = np.sqrt(np.mean([r["predicted_rms_mm"] ** 2 * len(r["errors_mm"]) for r in group])
                            / np.mean([len(r["errors_mm"]) for r in group]))
        before = np.sqrt(np.mean([r["predicted_before_navigation_rms_mm"] ** 2 for r in group]))
        ratios = np.array([r["predicted_rms_mm"] / r["measured_rms_mm"] for r in group])
        ratios_all.append(predicted / measured)
        table.append([f"x{noise:g}", "all" if not markers else str(markers), f"x{jitter:g}", str(len(group)),
                      f"{measured:.3f}", f"{predicted:.3f}", f"{predicted / measured:.2f}",
                      f"{before / measured:.2f}", f"{np.percentile(ratios, 5):.2f}-{np.percentile(ratios, 95):.2f}",
                      f"{np.mean((ratios >= 0.65) & (ratios <= 1.5)) * 100:.0f} %"])
    figure = bar_chart([f"{row[0]} {row[1]} {row[2]}" for row in table], ratios_all,
                       title="predicted / measured RMS TRE", y_label="ratio",
                       reference_lines=[(1.0, "exact"), (0.8, "0.8"), (1.25, "1.25")])
    notes = [f"{len(rows) - len(done)} of {len(rows)} sessions refused"] if len(done) < len(rows) else []
    return Summary(["tracker noise", "markers", "reference jitter", "target visits", "measured RMS (mm)",
                    "predicted RMS (mm)", "predicted / measured", "before navigation / measured",
                    "per target 5-95 %", "per target in 0.65-1.5"], table, figure, notes)


# --- trust: field distortion detected at registration, and the TRE predicted with it ---------------

#: Distorted sessions of ``emreg study trust`` per field family, size (RMS non-rigid mm at the pinholes) and tracker
#: noise scale; clean sessions per noise scale. Families: :data:`EMRegModule.simulation.field_families.FAMILIES`
#: (development: dipole, gp; held out: magpylib, multi).
TRUST_SIZES_MM = (0.5, 1.0, 1.5, 2.0)
TRUST_NOISES = (1.0, 2.0, 4.0)
TRUST_SESSIONS = 8
TRUST_CLEAN = 40
TRUST_QUICK = {("clean", 0.0, 1.0): 2, ("dipole", 1.0, 1.0): 1, ("magpylib", 1.0, 1.0): 1}
#: Navigations with checkpoints of ``emreg study trust``: (event, tracker noise, hard tracking) -> sessions (a bump:
#: the frame knocked as a whole, the control of the slip test; last, so the other sessions keep their seeds).
TRUST_CHECKPOINTS = {("clean", 1.0, False): 20, ("clean", 2.0, False): 20, ("clean", 4.0, False): 20,
                     ("clean", 1.0, True): 20, ("slip", 1.0, False): 20, ("slip", 2.0, False): 20,
                     ("slip", 1.0, True): 20, ("onset", 1.0, False): 20, ("bump", 1.0, False): 40,
                     ("bump", 2.0, False): 20}
TRUST_CHECKPOINTS_QUICK = {("clean", 1.0, False): 1, ("clean", 4.0, False): 1, ("slip", 1.0, False): 1,
                           ("onset", 1.0, False): 1, ("bump", 1.0, False): 1}


def _trust_tasks(quick: bool) -> list[dict]:
    if quick:
        counts = TRUST_QUICK
    else:
        counts = {("clean", 0.0, noise): TRUST_CLEAN for noise in TRUST_NOISES}
        counts.update({(family, size, noise): TRUST_SESSIONS for family in FAMILIES for size in TRUST_SIZES_MM
                       for noise in TRUST_NOISES})
    tasks = [{"family": family, "distortion_mm": size, "noise": noise, "repetition": r}
             for (family, size, noise), count in counts.items() for r in range(count)]
    return tasks + [{"checkpoints": event, "noise": noise, **({"hard": True} if hard else {}), "repetition": r}
                    for (event, noise, hard), count in (TRUST_CHECKPOINTS_QUICK if quick else TRUST_CHECKPOINTS).items()
                    for r in range(count)]


def _trust_rows(frame: Frame, params: dict, rng: np.random.Generator) -> list[dict]:
    """One calibration + registration + navigation with a steel rod of ``distortion_mm`` (RMS non-rigid at the
    pinholes) beside the frame (0: a clean session), navigated in the same field: detection, estimate, TRE; or a
    navigation with checkpoints (``params["checkpoints"]``: :func:`.checkpoints.checkpoint_rows`)."""
    if "checkpoints" in params:
        return checkpoint_rows(frame, params, rng)
    size = float(params["distortion_mm"])
    placement = reference_placement(rng)
    family = params.get("family", "dipole")
    distortion = place_field(family, rng, frame.pinholes, placement, np.eye(4), size) if size > 0 else None
    noise = noise_model(params.get("noise", 1.0))
    session = calibrate_and_register(frame, rng, noise, reference_to_tracker=placement, distortion=distortion)
    row = {**params, "refused": session.refused}
    if session.registration is None:
        return [row]
    registration = session.registration
    estimate = registration.error.distortion
    truth_rms = 0.0
    if distortion is not None:
        paired = [frame.labels.index(p["calibration_point"]) for p in registration.pairs]
        truth_rms = float(np.sqrt(np.mean(np.sum(
            nonrigid_errors(distortion, frame.pinholes[paired], placement, np.eye(4))[1] ** 2, axis=1))))
    blamed = any(BLAME in w for w in registration.warnings for BLAME in USER_BLAMED)
    row.update(detected=bool(estimate.detected), p_value=estimate.p_value, estimated_rms_mm=estimate.rms_mm,
               detectable_rms_mm=estimate.detectable_rms_mm,
               flagged=estimate.undetectable,
               truth_paired_rms_mm=truth_rms, paired=len(registration.pairs), fre_mm=registration.fre_mm,
               unpaired=len(registration.unpaired_calibration_points),
               user_blamed=blamed and not estimate.detected)
    model = ErrorModel.with_priors(registration.reference_to_image, registration.error)
    recording = simulate_navigation(frame, rng, params.get("placements", 4), noise, reference_to_tracker=placement,
                                    distortion=distortion)
    result = evaluate_targets(recording, frame.target_labels, frame.targets_image, registration.reference_to_image,
                              error_model=model).to_json()
    dwells = result["dwells"]
    if dwells:
        distortion_ms = model.budget(frame.targets_image).distortion_ms
        index = [frame.target_labels.index(d["target"]) for d in dwells]
        predicted = float(np.mean([result["targets"][d["target"]]["predicted_rms_mm"] ** 2 for d in dwells]))
        row.update(measured_ms=float(np.mean([d["error_mm"] ** 2 for d in dwells])), dwells=len(dwells),
                   predicted_ms=predicted, predicted_without_distortion_ms=predicted - (
                       0.0 if distortion_ms is None else float(np.mean(distortion_ms[index]))))
    return [row]


#: Words of a warning that put a left-out point down to the user (see :func:`EMRegModule.core.registration.register`).
USER_BLAMED = ("likely not in a pinhole", "likely not recorded")


def _trust_group_row(label: str, group: list[dict]) -> list[str]:
    """One line of the trust table: sessions, refused, detected, caught (detected or refused), and with those the
    sessions whose test could have missed a field of ``max_undetectable_distortion_mm`` (flagged: a warning, the
    prediction not to be trusted), the median detectable size, the user blamed with no distortion named, the
    estimate against the truth, and the predicted / measured TRE of the sessions not refused."""
    done = [r for r in group if not r["refused"]]
    detected = [r for r in done if r["detected"]]
    caught = len(detected) + len(group) - len(done)
    flagged = sum(1 for r in done if r.get("flagged"))
    detectable = [r["detectable_rms_mm"] for r in done if "detectable_rms_mm" in r]
    navigated = [r for r in done if "measured_ms" in r]
    measured = np.mean([r["measured_ms"] for r in navigated]) if navigated else np.nan
    predicted = np.mean([r["predicted_ms"] for r in navigated]) if navigated else np.nan
    without = np.mean([r["predicted_without_distortion_ms"] for r in navigated]) if navigated else np.nan
    ratios = np.array([np.sqrt(r["predicted_ms"] / r["measured_ms"]) for r in navigated])
    rate = len(detected) / len(done) if done else np.nan
    size = float(group[0].get("distortion_mm", 0.0))
    return [label, str(len(group)), f"{len(group) - len(done)}", f"{rate * 100:.1f} %",
            f"{caught / len(group) * 100:.1f} %", f"{(caught + flagged) / len(group) * 100:.1f} %",
            f"{np.median(detectable):.2f}" if detectable else "-", str(sum(1 for r in done if r.get("user_blamed"))),
            _mean_std([r["estimated_rms_mm"] for r in detected]),
            _mean_std([r["truth_paired_rms_mm"] for r in done]) if size else "-",
            f"{np.sqrt(measured):.3f}", f"{np.sqrt(predicted / measured):.2f}", f"{np.sqrt(without / measured):.2f}",
            f"{np.percentile(ratios, 5):.2f}-{np.percentile(ratios, 95):.2f}" if len(ratios) else "-"]


def _trust_summary(rows: list[dict]) -> Summary:
    """Per field family (held-out ones marked), size and tracker noise; the clean sessions per noise first."""
    table, names, rates = [], [], []
    checkpoint_sessions = [r for r in rows if "checkpoints" in r]
    rows = [r for r in rows if "checkpoints" not in r]
    groups: dict = {}
    for r in rows:
        size = float(r["distortion_mm"])
        family = "clean" if size == 0 else r.get("family", "dipole")
        groups.setdefault((family != "clean", FAMILIES.index(family) if family in FAMILIES else -1, size,
                           float(r.get("noise", 1.0)), family), []).append(r)
    for (_, _, size, noise, family), group in sorted(groups.items()):
        kind = "" if family == "clean" else (" (held out)" if family in HELD_OUT else " (development)")
        label = f"{family}{kind} {size:g} mm, noise x{noise:g}" if size else f"clean, noise x{noise:g}"
        line = _trust_group_row(label, group)
        table.append(line + ["-"] * len(CHECKPOINT_COLUMNS))
        names.append(f"{family[:4]} {size:g} x{noise:g}")
        rates.append(float(line[4].rstrip(" %")))
    figure = bar_chart(names, rates, title="distortion detected or refused at registration",
                       y_label="sessions (%)", reference_lines=[(95.0, "goal at 1 mm"), (1.0, "false alarms")])
    refused = sum(1 for r in rows + checkpoint_sessions if r["refused"])
    notes = [f"{refused} of {len(rows) + len(checkpoint_sessions)} sessions refused"] if refused else []
    notes.append(f"field families: development {', '.join(DEVELOPMENT)}; held out (never tuned on) "
                 f"{', '.join(HELD_OUT)} (EMRegModule.simulation.field_families)")
    header = ["distortion (family, RMS at the pinholes) / checkpoint sessions", "sessions", "refused", "detected",
              "detected or refused", "detected, refused or flagged (could miss 1 mm)",
              "detectable RMS (mm, median)", "user blamed, no distortion named", "estimated RMS (mm, detected)",
              "true RMS at the paired pinholes (mm)", "measured RMS TRE (mm)", "predicted / measured",
              "without the distortion term", "per session 5-95 %", *CHECKPOINT_COLUMNS]
    more, lines = checkpoint_table(checkpoint_sessions, len(header))
    return Summary(header, table + more, figure, notes + lines)


def _grid(quick: bool, full: dict, small: dict, repetitions: int, quick_repetitions: int) -> list[dict]:
    """Every combination of the swept values, ``repetitions`` sessions each."""
    values = small if quick else full
    combos = [{}]
    for key, options in values.items():
        combos = [{**c, key: v} for c in combos for v in options]
    count = quick_repetitions if quick else repetitions
    return [{**c, "repetition": r} for c in combos for r in range(count)]


STUDIES: dict[str, Study] = {s.name: s for s in (
    Study("calibration", "FRE over repeated frame calibrations at different frame positions",
          lambda quick: [{"noise": 1.0}] * (3 if quick else 30), _session_rows, _calibration_summary),
    Study("board", "board phantom edge lengths (paper Table 1)", lambda quick: [{}], _board_rows, _board_summary),
    Study("tre", "TRE at 6 targets x 15 placements (paper Fig. 12)",
          lambda quick: [{"placements": 4 if quick else 15}] * (2 if quick else 5), _navigation_rows, _tre_summary),
    Study("noise", "registration accuracy against tracker noise",
          lambda quick: _grid(quick, {"noise": [0.5, 1.0, 2.0, 4.0]}, {"noise": [1.0, 4.0]}, 10, 2),
          _session_rows, _sweep_summary("noise", "tracker noise scale")),
    Study("markers", "registration accuracy against the number of markers",
          lambda quick: _grid(quick, {"markers": [3, 4, 5, 6, 8, 12, 16, 20, 28]}, {"markers": [3, 6]}, 10, 2),
          _session_rows, _sweep_summary("markers", "markers")),
    Study("tool", "the paper's pinhole probe (l by FRE) against a pivot-calibrated pointer",
          lambda quick: _grid(quick, {"route": ["pinhole", "pivot"]}, {"route": ["pinhole", "pivot"]}, 10, 2),
          _tool_rows, _tool_summary),
    Study("prediction", "predicted against measured end-to-end TRE",
          lambda quick: _grid(quick, {"noise": [0.5, 1.0, 2.0, 4.0], "markers": [0, 8, 5]},
                              {"noise": [1.0, 4.0], "markers": [0]}, 8, 2)
          + ([] if quick else [{"reference_jitter": 5.0, "repetition": r} for r in range(8)]),
          _navigation_rows, _prediction_summary),
    Study("trust", "field distortion: detection at registration, false alarms, predicted against measured TRE; "
          "checkpoints during navigation: clean passes, alarm latency after a reference slip or a distortion onset, "
          "reference-jump warnings", _trust_tasks, _trust_rows, _trust_summary),
)}
