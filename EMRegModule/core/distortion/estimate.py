"""The distortion test's verdict and the field it fitted: what ``registration.json`` keeps, what the error model adds
at a target, and why a prediction may not be trusted (Reference frame, mm)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..error_model import fiducial_jacobian
from .fields import Bumps, Dipole, Modes, Polynomial, gaussian_kernel
from .power import POWER_LEVEL

#: Share of the largest residual's square the field fitted to the other pinholes must predict, when those alone are
#: not significant (simulated, 12 each: a bad pair at most 0.14, a rod's field 0.44-0.96).
PREDICTED_SHARE = 0.5
#: Below this p-value a distortion not detected is still named as a reason not to trust the prediction.
SUSPECT_LEVEL = 0.05


def size_words(size_mm: float) -> str:
    """A detectable size in words: "up to 1.20 mm", or "any size" when infinite."""
    return f"up to {size_mm:.2f} mm" if np.isfinite(size_mm) else "any size"


@dataclass
class DistortionEstimate:
    """The distortion test and the non-rigid field fitted at registration (Reference frame, mm).

    ``labels`` / ``image_markers``: the paired pinholes; ``points_mm`` (N, 3): their calibration points;
    ``residuals_mm`` (N, 3): measured point minus the registered CT pinhole; ``statistic``: the largest
    share of the residuals' sum of squares one candidate field explains; ``p_value``: its Monte Carlo
    p-value under noise alone; ``alpha``: the false-alarm rate it is compared with. The fitted field:
    ``model`` (a dipole or bumps; None: noise alone) with ``amplitudes`` (P,) and their covariance
    (P, P); ``rigid_per_amplitude`` (6, P): the rigid motion (rotation rad, translation mm, about the
    pinholes' centroid) the registration absorbs of each amplitude's field; ``at_pinholes_mm`` (N, 3):
    the non-rigid field at the pinholes; ``noise_sigma_mm`` (per axis) and ``noise_dof``: the noise beside it.
    """

    labels: list[str]
    points_mm: np.ndarray
    residuals_mm: np.ndarray
    statistic: float
    p_value: float
    alpha: float
    noise_sigma_mm: float
    noise_dof: float = float("inf")
    model: Any = None
    amplitudes: np.ndarray = field(default_factory=lambda: np.zeros(0))
    amplitude_covariance: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    rigid_per_amplitude: np.ndarray = field(default_factory=lambda: np.zeros((6, 0)))
    at_pinholes_mm: np.ndarray | None = None
    tested: bool = True
    image_markers: list[str] = field(default_factory=list)
    note: str = ""
    #: One bad pair (a probe not fully inserted) is not a field: the pinhole of the largest residual (``left_out``)
    #: must be explained by the others too, either because they alone are significant (their p-value) or because
    #: the field they fit predicts at least :data:`.PREDICTED_SHARE` of its residual's square (NaN: not computed).
    p_value_without_largest: float = float("nan")
    largest_predicted_share: float = float("nan")
    left_out: str = ""
    #: The evidence was put down to one bad pair at ``left_out`` (:func:`._several_points`): not a distortion.
    one_bad_pair: bool = False
    #: Calibration points the pairing left out that joined the test (near a CT pinhole no pair took): they add
    #: evidence; the field and the noise are measured on the pairs (``labels``) alone.
    tested_unpaired: list[str] = field(default_factory=list)
    #: The probe's per-dwell error known apart from the residuals (:class:`.NoisePrior`; NaN: none) and its source.
    noise_prior_sigma_mm: float = float("nan")
    noise_prior_source: str = ""
    #: The smallest field (RMS of its non-rigid part at the pinholes, mm) this test finds in :data:`.POWER_LEVEL` of
    #: random smooth fields at this session's noise and geometry (:func:`.detectable_rms`; NaN: not tested).
    detectable_rms_mm: float = float("nan")
    #: The largest field the test may be unable to see before the prediction is not to be trusted (mm,
    #: ``[registration] max_undetectable_distortion_mm``; NaN: not checked).
    undetectable_limit_mm: float = float("nan")
    #: The fitted field's leave-one-out errors at the pinholes (:func:`._leave_one_out`): their mean square (mm^2, 3D)
    #: and the mean of ``tr((I - H_ii)^-1)``, what noise of unit variance per axis gives them (:attr:`.extension_ms`).
    loo_ms: float = 0.0
    loo_noise_factor: float = 0.0

    @property
    def extension_ms(self) -> float:
        """What the fitted family misses where it was not fitted (mm^2, 3D, per point): the leave-one-out errors'
        mean square beyond what the noise gives them, the noise being the tracker's own known apart from the residuals
        when smaller than the noise beside the fit (which a misfit inflates, and would hide), else the latter. Added
        to the distortion predicted anywhere: a field of another family than the fitted one."""
        sigma = self.noise_sigma_mm
        if self.noise_prior_sigma_mm > 0:
            sigma = min(sigma, self.noise_prior_sigma_mm)
        return float(max(self.loo_ms - sigma**2 * self.loo_noise_factor, 0.0))

    @property
    def fle_ratio(self) -> float:
        """The per-dwell error the residuals show (beside the fitted field when one was detected) over the one known
        apart from them (NaN without a prior): near 1 when the FRE is what the tracker's noise explains."""
        if not (self.noise_prior_sigma_mm > 0):
            return float("nan")
        return float(self.noise_sigma_mm / self.noise_prior_sigma_mm)

    def fle_p_value(self) -> float:
        """The chance of residuals at least this much larger than the prior explains (chi-square on the noise's
        degrees of freedom; NaN without a prior)."""
        from scipy.special import gammaincc

        ratio = self.fle_ratio
        if not np.isfinite(ratio) or not np.isfinite(self.noise_dof):
            return float("nan")
        return float(gammaincc(self.noise_dof / 2.0, self.noise_dof * ratio**2 / 2.0))

    @property
    def fle_consistent(self) -> bool:
        """False when the residuals are larger than the prior explains at :data:`.SUSPECT_LEVEL` (True without one)."""
        p = self.fle_p_value()
        return not (np.isfinite(p) and p <= SUSPECT_LEVEL)

    @property
    def detected(self) -> bool:
        return self.tested and self.p_value <= self.alpha and not self.one_bad_pair

    @property
    def undetectable(self) -> bool:
        """A test that found nothing but could have missed a field of ``undetectable_limit_mm``
        (``detectable_rms_mm`` above it): the warning, the untrusted prediction, the refusal when asked."""
        return self.tested and not self.detected and self.detectable_rms_mm > self.undetectable_limit_mm

    # --- the fitted field -------------------------------------------------------------------

    def _amplitude_columns(self) -> np.ndarray:
        """The fitted amplitudes and the square-root factor of their covariance side by side (P, 1 + P): the field's
        columns give the fitted field, then its variance as their sum of squares."""
        values, vectors = np.linalg.eigh(np.asarray(self.amplitude_covariance, dtype=float))
        return np.concatenate([np.asarray(self.amplitudes, dtype=float).reshape(-1, 1),
                               vectors * np.sqrt(np.clip(values, 0.0, None))], axis=1)

    def _operator(self, points: np.ndarray, columns: np.ndarray) -> np.ndarray:
        """``G(x) @ columns`` (K, 3, C) for amplitude columns (P, C): the model's field at x minus the rigid
        motion the registration absorbed of it."""
        raw = self.model.columns(points) @ columns
        motion = fiducial_jacobian(points, np.asarray(self.points_mm, dtype=float).mean(axis=0))
        return raw - motion @ (self.rigid_per_amplitude @ columns)

    def field_at(self, points_reference: np.ndarray) -> np.ndarray:
        """The fitted non-rigid displacement (K, 3, mm) at points (K, 3) of the Reference frame, probed with the
        frame where it was calibrated."""
        points = np.asarray(points_reference, dtype=float).reshape(-1, 3)
        if self.model is None:
            return np.zeros_like(points)
        return self._operator(points, np.asarray(self.amplitudes, dtype=float).reshape(-1, 1))[..., 0]

    def mean_square_at(self, points_reference: np.ndarray) -> np.ndarray:
        """Expected squared distortion error (K,) (mm^2) at points (K, 3) of the Reference frame probed in the same
        field: the fitted field squared less its variance (navigation is not corrected by the fitted field, so the
        error holds the true field, whose square the fitted one's overstates by that variance on average; never
        below 0), plus what the fitted family itself misses where it was not fitted (:attr:`.extension_ms`, from its
        leave-one-out errors at the pinholes: a field of another family than the fitted one), or where more, what a
        Gaussian process's fitted modes leave unseen at the point (:meth:`._unseen_ms`); 0 everywhere when no
        distortion was detected. (Until issue 37's second round it was the fitted square plus the variance, and never
        less than the mean square measured at the pinholes: that overshot by 1.2-1.4x at targets inside the frame,
        where the rigid fit leaves the least of a field.)"""
        points = np.asarray(points_reference, dtype=float).reshape(-1, 3)
        if not self.detected or self.model is None:
            return np.zeros(len(points))
        columns = self._amplitude_columns()
        fitted, variance = np.empty(len(points)), np.empty(len(points))
        for start in range(0, len(points), 16384):
            chunk = np.sum(self._operator(points[start:start + 16384], columns) ** 2, axis=1)  # (k, columns)
            fitted[start:start + len(chunk)] = chunk[:, 0]
            variance[start:start + len(chunk)] = np.sum(chunk[:, 1:], axis=1)
        return np.clip(fitted - variance, 0.0, None) + np.maximum(self.extension_ms, self._unseen_ms(points))

    def _unseen_ms(self, points: np.ndarray) -> np.ndarray:
        """For a Gaussian process's modes fitted (a smooth field of no physics): its posterior variance at the points
        (K,) (mm^2, 3D), the field's mean square at the pinholes times ``1 - k(x) (K + s I)^-1 k(x)``, which is 0 at a
        pinhole and the whole of it where no pinhole is within the process's length (``s``: the noise beside the
        field per its variance). The modes' own extension falls to 0 away from the pinholes, where such a field does
        not; 0 for the other candidates, whose shape says how they extend."""
        if not isinstance(self.model, Modes) or not len(points):
            return np.zeros(len(points))
        field_ms = self.rms_mm**2
        if not field_ms > 0:
            return np.zeros(len(points))
        centres = np.asarray(self.model.centres_mm, dtype=float)
        gram = gaussian_kernel(centres, centres, self.model.length_mm)
        ridge = max(3.0 * self.noise_sigma_mm**2 / field_ms, 1e-6)
        factor = np.linalg.cholesky(gram + ridge * np.eye(len(centres)))
        out = np.empty(len(points))
        for start in range(0, len(points), 16384):
            chunk = points[start:start + 16384]
            squared = np.sum(chunk**2, axis=1)[:, None] + np.sum(centres**2, axis=1)[None] - 2.0 * chunk @ centres.T
            across = np.exp(-np.clip(squared, 0.0, None) / (2.0 * self.model.length_mm**2))  # k(x), (k, B)
            half = np.linalg.solve(factor, across.T)  # L^-1 k(x)^T, (B, k)
            out[start:start + len(across)] = field_ms * np.clip(1.0 - np.sum(half**2, axis=0), 0.0, 1.0)
        return out

    def measured_ms(self) -> float:
        """The non-rigid field's mean square over the pinholes (mm^2) with its uncertainty (the fitted field's
        variance there): the distortion measured at registration; 0 when none was detected."""
        if not self.detected or self.model is None:
            return 0.0
        columns = self._amplitude_columns()
        return float(np.mean(np.sum(self._operator(np.asarray(self.points_mm, dtype=float), columns) ** 2,
                                    axis=(1, 2))))

    def prediction_trust(self) -> dict[str, Any]:
        """The ``registration.json`` ``prediction_trust`` block: whether the predicted TRE rests on a model the
        registration's own residuals agree with, and the reasons it may not (words for the user)."""
        reasons = []
        if not self.tested:
            why = self.note or "too few pinholes"
            reasons.append(f"the residuals could not be tested for field distortion ({why})")
        elif self.detected:
            reasons.append(f"field distortion measured at the pinholes ({self.rms_mm:.2f} mm RMS, up to "
                           f"{self.largest()[0]:.2f} mm near {self.where()}): the prediction adds the fitted field "
                           "and what its family misses between the pinholes, but how the field extends beyond them is "
                           "not known")
        elif self.p_value <= SUSPECT_LEVEL:
            why = (f"; the evidence was put down to one bad pair at {self.left_out}" if self.one_bad_pair else "")
            reasons.append(f"the residuals are more coherent than noise (p = {self.p_value:.2g}) without reaching the "
                           f"false-alarm rate of the distortion test ({self.alpha:g}){why}: a field distortion may be "
                           "hiding in the tracking error the prediction assumes")
        if self.undetectable:
            reasons.append(f"with this tracking noise and these {len(self.labels) + len(self.tested_unpaired)} "
                           "pinholes, the distortion test could "
                           f"miss a field of {size_words(self.detectable_rms_mm)} RMS at the pinholes (above "
                           f"{self.undetectable_limit_mm:g} mm): no distortion found does not mean none is there, "
                           "and the prediction does not include one")
        if self.tested and not self.fle_consistent:
            reasons.append(f"the calibration residuals show a per-dwell error {self.fle_ratio:.1f} times what the "
                           f"tracker's own noise explains ({self.noise_prior_source}): the predicted TRE takes the "
                           "larger error the residuals show, but its cause (a probe not seated, a bent probe, an "
                           "unmodelled distortion) is not known")
        return {"trusted": not reasons, "reasons": reasons,
                "distortion_ms_mm2": round(self.measured_ms(), 6)}

    # --- summary and files ------------------------------------------------------------------

    def pinhole_field(self) -> np.ndarray:
        """The fitted non-rigid field at the pinholes (N, 3, mm)."""
        if self.at_pinholes_mm is None:
            return np.zeros_like(np.asarray(self.points_mm, dtype=float))
        return np.asarray(self.at_pinholes_mm, dtype=float)

    @property
    def rms_mm(self) -> float:
        sizes = np.linalg.norm(self.pinhole_field(), axis=1)
        return float(np.sqrt(np.mean(sizes**2))) if len(sizes) else 0.0

    def largest(self) -> tuple[float, int]:
        """The largest fitted field size at a pinhole (mm) and that pinhole's index (-1 without pinholes)."""
        sizes = np.linalg.norm(self.pinhole_field(), axis=1)
        return (float(sizes.max()), int(np.argmax(sizes))) if len(sizes) else (0.0, -1)

    def where(self) -> str:
        """The pinhole where the field is largest, named by calibration point (and CT marker)."""
        _, k = self.largest()
        if k < 0:
            return "-"
        marker = f" (CT marker {self.image_markers[k]})" if k < len(self.image_markers) else ""
        return f"{self.labels[k]}{marker}"

    def to_json(self) -> dict[str, Any]:
        """The ``registration.json`` ``distortion`` block."""
        largest, k = self.largest()

        def rounded(values: Any, digits: int = 6) -> list:
            return np.round(np.asarray(values, dtype=float), digits).tolist()

        model: dict[str, Any] | None = None
        if isinstance(self.model, Dipole):
            model = {"kind": "dipole", "object_tracker_mm": rounded(self.model.object_mm),
                     "TrackerToReference": rounded(self.model.tracker_to_reference, 9),
                     "amplitudes": "polarisability (mm^3): xx, yy, zz, xy, xz, yz in the Tracker frame",
                     "formula": "d(x) = T_R @ dx(inv(T) x): the first-order position error of an induced dipole "
                                "(EMRegModule.core.em_field.position_error), T = TrackerToReference"}
        elif isinstance(self.model, Bumps):
            model = {"kind": "bumps", "centres_mm": rounded(self.model.centres_mm),
                     "length_scales_mm": rounded(self.model.lengths_mm),
                     "amplitudes": "displacement (mm) x, y, z per bump",
                     "formula": "d(x) = sum_b exp(-|x - c_b|^2 / (2 L_b^2)) a_b"}
        elif isinstance(self.model, Polynomial):
            model = {"kind": "polynomial", "centre_mm": rounded(self.model.centre_mm), "scale_mm": self.model.scale_mm,
                     "degree": self.model.degree, "exponents": self.model.exponents().tolist(),
                     "amplitudes": "displacement (mm) x, y, z per monomial",
                     "formula": "d(x) = sum_m prod(((x - centre) / scale) ** exponents_m) a_m"}
        elif isinstance(self.model, Modes):
            model = {"kind": "modes", "centres_mm": rounded(self.model.centres_mm), "length_mm": self.model.length_mm,
                     "weights": rounded(self.model.weights, 12),
                     "amplitudes": "displacement (mm) x, y, z per mode",
                     "formula": "d(x) = sum_m (exp(-|x - c|^2 / (2 L^2)) @ weights)_m a_m"}
        return {
            "detected": self.detected, "rms_mm": round(self.rms_mm, 4), "max_mm": round(largest, 4),
            "max_at": self.labels[k] if k >= 0 else None, "tested": self.tested,
            "test": "share of the rigid fit's residual sum of squares the best candidate field explains (an induced "
                    "dipole near the frame, smooth bumps, polynomial fields, a Gaussian process's smoothest modes; "
                    "chosen by its tail probability), against the Monte Carlo distribution of the smallest tail "
                    "probability under independent noise" + ("; and the sum of squares it explains against the "
                                                              "noise_prior (chi-square), the smaller p-value's own"
                                                              if self.noise_prior_sigma_mm > 0 else ""),
            "statistic": round(float(self.statistic), 6), "p_value": round(float(self.p_value), 6),
            "alpha": float(self.alpha), **({"note": self.note} if self.note else {}),
            "p_value_without_largest": None if not np.isfinite(self.p_value_without_largest)
            else round(float(self.p_value_without_largest), 6),
            "largest_predicted_share": None if not np.isfinite(self.largest_predicted_share)
            else round(float(self.largest_predicted_share), 4),
            "left_out": self.left_out or None, "one_bad_pair": self.one_bad_pair,
            "tested_unpaired": list(self.tested_unpaired),
            "noise_sigma_mm": round(float(self.noise_sigma_mm), 5),
            **({"extension_ms_mm2": round(float(self.extension_ms), 6), "loo_ms_mm2": round(float(self.loo_ms), 6),
                "loo_noise_factor": round(float(self.loo_noise_factor), 6)} if self.detected else {}),
            **({"detectable_rms_mm": round(float(self.detectable_rms_mm), 4)
                if np.isfinite(self.detectable_rms_mm) else None,
                "detectable": f"the non-rigid RMS at the pinholes this test finds in {POWER_LEVEL:.0%} of random "
                              "smooth fields at this session's noise and pinholes (smaller fields may go unseen; "
                              "null: no size, the test misses too many smooth fields at any size)",
                **({"undetectable_limit_mm": float(self.undetectable_limit_mm)}
                   if np.isfinite(self.undetectable_limit_mm) else {})}
               if not np.isnan(self.detectable_rms_mm) else {}),
            "noise_dof": round(float(self.noise_dof), 3) if np.isfinite(self.noise_dof) else None,
            **({"noise_prior": {"sigma_mm": round(float(self.noise_prior_sigma_mm), 5),
                                "source": self.noise_prior_source, "fle_ratio": round(self.fle_ratio, 4),
                                "fle_p_value": round(self.fle_p_value(), 6)
                                if np.isfinite(self.fle_p_value()) else None}}
               if self.noise_prior_sigma_mm > 0 else {}),
            "field": {
                "frame": "Reference", "units": "mm",
                "description": "the EM measurement's displacement at x beyond the rigid motion the registration "
                               "absorbs: model(x) @ amplitudes - (omega x (x - centroid) + t), (omega, t) = "
                               "rigid_per_amplitude @ amplitudes",
                "model": model, "amplitudes": rounded(self.amplitudes, 9),
                "amplitude_covariance": rounded(self.amplitude_covariance, 12),
                "rigid_per_amplitude": rounded(self.rigid_per_amplitude, 15),
                "centroid_mm": rounded(np.asarray(self.points_mm, dtype=float).mean(axis=0)),
                "pinholes_mm": rounded(self.points_mm),
                "residuals_mm": rounded(self.residuals_mm),
                "at_pinholes_mm": rounded(self.pinhole_field()),
            },
            "labels": list(self.labels), "image_markers": list(self.image_markers),
        }

    @classmethod
    def from_json(cls, document: Mapping[str, Any]) -> DistortionEstimate:
        """Inverse of :meth:`.to_json`."""
        block = document["field"]
        stored = block.get("model")
        model: Any = None
        if stored and stored.get("kind") == "dipole":
            model = Dipole(np.asarray(stored["object_tracker_mm"], dtype=float).reshape(3),
                            np.asarray(stored["TrackerToReference"], dtype=float).reshape(4, 4))
        elif stored and stored.get("kind") == "bumps":
            model = Bumps(np.asarray(stored["centres_mm"], dtype=float).reshape(-1, 3),
                           np.asarray(stored["length_scales_mm"], dtype=float).reshape(-1))
        elif stored and stored.get("kind") == "polynomial":
            model = Polynomial(np.asarray(stored["centre_mm"], dtype=float).reshape(3), float(stored["scale_mm"]),
                                int(stored["degree"]))
        elif stored and stored.get("kind") == "modes":
            centres = np.asarray(stored["centres_mm"], dtype=float).reshape(-1, 3)
            model = Modes(centres, float(stored["length_mm"]),
                           np.asarray(stored["weights"], dtype=float).reshape(len(centres), -1))
        amplitudes = np.asarray(block.get("amplitudes", []), dtype=float).reshape(-1)
        n = len(amplitudes)
        return cls(labels=[str(v) for v in document.get("labels", [])],
                   points_mm=np.asarray(block["pinholes_mm"], dtype=float).reshape(-1, 3),
                   residuals_mm=np.asarray(block["residuals_mm"], dtype=float).reshape(-1, 3),
                   statistic=float(document["statistic"]), p_value=float(document["p_value"]),
                   alpha=float(document["alpha"]), noise_sigma_mm=float(document["noise_sigma_mm"]),
                   noise_dof=float("inf") if document.get("noise_dof") is None else float(document["noise_dof"]),
                   model=model, amplitudes=amplitudes,
                   amplitude_covariance=np.asarray(block.get("amplitude_covariance", []), dtype=float).reshape(n, n),
                   rigid_per_amplitude=np.asarray(block.get("rigid_per_amplitude", []), dtype=float).reshape(6, n),
                   at_pinholes_mm=np.asarray(block["at_pinholes_mm"], dtype=float).reshape(-1, 3),
                   tested=bool(document.get("tested", True)),
                   image_markers=[str(v) for v in document.get("image_markers", [])],
                   note=str(document.get("note", "")),
                   noise_prior_sigma_mm=float((document.get("noise_prior") or {}).get("sigma_mm", float("nan"))),
                   noise_prior_source=str((document.get("noise_prior") or {}).get("source", "")),
                   p_value_without_largest=float("nan") if document.get("p_value_without_largest") is None
                   else float(document["p_value_without_largest"]),
                   largest_predicted_share=float("nan") if document.get("largest_predicted_share") is None
                   else float(document["largest_predicted_share"]),
                   left_out=str(document.get("left_out") or ""),
                   one_bad_pair=bool(document["one_bad_pair"]) if "one_bad_pair" in document
                   else _older_bad_pair(document),
                   detectable_rms_mm=float("nan") if "detectable_rms_mm" not in document
                   else float("inf") if document["detectable_rms_mm"] is None else float(document["detectable_rms_mm"]),
                   undetectable_limit_mm=float(document.get("undetectable_limit_mm", float("nan"))),
                   tested_unpaired=[str(v) for v in document.get("tested_unpaired", [])],
                   loo_ms=float(document.get("loo_ms_mm2", 0.0)),
                   loo_noise_factor=float(document.get("loo_noise_factor", 0.0)))


def _older_bad_pair(document: Mapping[str, Any]) -> bool:
    """Whether a ``distortion`` block written before ``one_bad_pair`` was (issue 37, second round) put its evidence
    down to one bad pair: then the others' p-value above ``alpha`` and a predicted share below
    :data:`.PREDICTED_SHARE` said so."""
    p_without, share = document.get("p_value_without_largest"), document.get("largest_predicted_share")
    return p_without is not None and share is not None and float(p_without) > float(document["alpha"]) \
        and float(share) < PREDICTED_SHARE
