"""Field distortion seen at registration: residuals that are spatially coherent, beyond what noise explains.

The CT is geometrically true; the EM measurements are not once metal distorts the field. After the
rigid fit (with l), the residual of each calibration point is its tracking noise plus the non-rigid
part of the distortion, a smooth field (neighbouring pinholes displaced alike). Noise is independent
from pinhole to pinhole; a distortion is not. Everything here is in the **Reference frame** (mm): the
field is the displacement of an EM measurement from where it should be, less the rigid motion the
registration absorbs of it.

**Model.** The residual vector ``r`` (3N) is ``P (f + e)``: ``P`` removes what the rigid fit (rotation,
translation, and l when solved) absorbs; ``e`` is noise of unknown size, independent per point (the probe's
per-dwell error and the CT's localisation); ``f`` is a smooth field of *unknown family*. The detector was designed
around EMReg's induced dipole and measured only on it; on fields of other shapes it missed (issue 37). So the
candidates are now of several kinds, the dipole one among them:

- an induced dipole (:mod:`EMRegModule.core.em_field`) at positions around the frame, linear in its six
  polarisability coefficients (only when the calibration kept where the transmitter was, ``TrackerToReference``);
- single smooth Gaussian bumps (3 amplitudes each) at and outside the pinholes, widths a fraction of the frame;
- generic smooth fields of no physics: polynomial displacement fields of degree 1-3 in position, and the smoothest
  modes of Gaussian processes of several lengths on the pinholes (extended elsewhere by the kernel).

**Test.** Each candidate's share of ``|r|^2`` is turned into its own tail probability under isotropic noise (the
share a rank-P subspace takes of an isotropic vector in the m residual dimensions is Beta(P/2, (m-P)/2)), so that
candidates of 3 and of 50 columns compete on one scale; the statistic is the smallest of these. Its distribution
under noise alone does not depend on the noise's size (only the geometry enters): it is drawn by Monte Carlo once
per geometry (deterministic seed), which accounts exactly for having tried every candidate, and the p-value is
compared with ``[registration] distortion_false_alarm``. No noise level is used at all, so a distortion cannot hide
inside a noise estimate made from its own residuals. (A permutation null, the residual vectors shuffled among the
pinholes, is available as :data:`.NULL`; the Gaussian one is the default, exact for isotropic noise.)

**Noise from independent evidence.** The share test divides by the residuals' own sum of squares, the signal
included, and loses power as the noise grows. When the probe's per-dwell error is known from evidence other than
the residuals (:class:`.NoisePrior`: the within-dwell spread of the calibration samples times the tracker's ratio,
``[registration] dwell_error_ratio``), a second statistic compares each candidate's explained sum of squares with
that noise (its chi-square tail), the smallest over the candidates; the reported p-value is that of the smaller of
the two tests' p-values against the same over the Monte Carlo null draws of both (the false-alarm rate stays
``alpha``, where twice the smaller, Bonferroni, would cost power), the known-noise one
counted only when the share test leans the same way (:data:`.SHARE_SUPPORT`): a noise level set
too small (a tracker of another ratio, a tool whose tip error the dwells do not show) would make any residual look
coherent, and the largest candidate fit it. The noise level grows
with the tracker's real noise, while a field's coherent residual stays. The same prior checks the FRE
(:attr:`.DistortionEstimate.fle_ratio`): in the Fitzpatrick model the residual sum of squares is ``(3N - P) FLE^2``,
so an FRE above what the prior explains (beside any fitted field) means an error the model does not know of; the
prediction then takes the larger FLE the residuals show, says it is not to be trusted, and above
``[registration] max_fle_ratio`` the registration is refused.

**One bad pair or a field.** A probe not fully inserted moves one point; a field moves several neighbours. The
evidence is put down to one bad pair only when all three hold: the largest residual is an outlier by itself (its
share of the sum of squares beyond what noise gives in this geometry, :data:`.OUTLIER_LEVEL`), the other pinholes
alone are not even weakly significant (:data:`.WITHOUT_LARGEST_LEVEL`), and the field they pick does not predict
the largest residual (:data:`.PREDICTED_SHARE`). A strong test is no longer overruled merely because dropping its
largest residual leaves a p-value a little above the false-alarm rate (issue 37, cases C and E).

Why not a chi-square against the error model's FLE: with one dwell per pinhole the FLE is estimated from
these same residuals (a dwell's spread shows the tracker's jitter, not its per-dwell error, which is
several times larger), so the ratio is one by construction; a noise level known beforehand would make
the test only as good as that guess.

**Estimate.** When detected, the best candidate (a dipole's position refined by Nelder-Mead) is fitted by
least squares: its non-rigid field at the pinholes gives ``rms_mm`` / ``max_mm``; its field and the
covariance of its amplitudes give the distortion's mean square at any point probed in the same field
(:meth:`.DistortionEstimate.mean_square_at`, the error model's distortion term), plus what the fitted family
misses where it was not fitted, measured by its own leave-one-out errors at the pinholes beyond their noise (a
field of another family than the fitted one is predicted with that miss, not as if its family were known), and
the noise that remains beside it replaces the probe's per-dwell error of the error model.
:meth:`.DistortionEstimate.prediction_trust` says, for ``registration.json``, why the prediction may not be
trusted: a distortion measured, one suspected (p below :data:`.SUSPECT_LEVEL`), or no test possible.

**What a clean result means.** "Nothing detected" speaks only for fields the test could have seen.
:func:`.detectable_rms` measures, per session, the smallest field (RMS of its non-rigid part at the pinholes) the
test finds in :data:`.POWER_LEVEL` of random smooth fields at this session's noise and pinholes; it is written to
``registration.json`` (``detectable_rms_mm``), and above ``[registration] max_undetectable_distortion_mm`` the
registration warns and :meth:`.DistortionEstimate.prediction_trust` says the prediction cannot be trusted (refused
with ``refuse_undetectable_distortion``): with that much tracking noise, or that few pinholes, no distortion found
does not mean no distortion.

**Layout.** :mod:`.fields`: the candidate fields as columns per amplitude; :mod:`.scan`: the test (the candidates
projected beyond the rigid fit, their shares and the Monte Carlo null); :mod:`.power`: the detectable size;
:mod:`.estimate`: :class:`.DistortionEstimate`, the verdict and the fitted field, what the error model and
``registration.json`` take of it; :mod:`.detect`: :func:`.estimate_distortion`, the test run on a registration's
residuals with the one-bad-pair rule and the fit.

**Validation.** ``emreg study trust`` measures detection, false alarms and predicted / measured TRE on field
families the detector was not designed around (:mod:`EMRegModule.simulation.field_families`: magpylib bodies
solved as a tracker does, several bodies with a field gradient), beside the development ones (the induced dipole,
random smooth Gaussian-process fields) the constants here were chosen on.
"""

from __future__ import annotations

from .detect import estimate_distortion, fit_field
from .estimate import SUSPECT_LEVEL, DistortionEstimate, size_words
from .power import POWER_LEVEL, detectable_rms
from .scan import NoisePrior, null_statistics

__all__ = ["POWER_LEVEL", "SUSPECT_LEVEL", "DistortionEstimate", "NoisePrior", "detectable_rms", "estimate_distortion",
           "fit_field", "null_statistics", "size_words"]
