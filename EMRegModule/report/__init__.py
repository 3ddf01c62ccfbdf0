"""The verification report: ``OUT/report.html``, one self-contained page showing a run's evidence.

:func:`~EMRegModule.report.writer.write_report` reads whatever a run left in OUT (spec formats): ``markers.json``,
``frame_calibration.json``, ``registration.json``, ``navigation.csv``, ``evaluation.json``,
``run.json``, and the CT of the case (from ``case_dir`` or ``run.json``'s ``"case"``). It
renders offscreen (pyvista, OpenCV) a 3D view of the frame with every fitted marker model
coloured by its registration residual, the reference sensor, the calibration points mapped
into image space and the CT's surface without its metal-streak sheets; per-marker CT slices
with the fitted outline; plots of the residual per marker, FRE(l) with the chosen l, TRE per
target; and tables (pairs, calibration points, rejected candidates, TRE, board). A section
whose inputs are missing is left out with a note; warnings (outliers, unpaired points,
refused steps) come first.

Images are embedded as base64 PNG (the page opens anywhere) and also written to
``OUT/report_figures/``. Every file is written atomically; the page holds no timestamps, so
the same inputs give the same bytes. :func:`~EMRegModule.report.batch.write_reports_batch` renders many runs, in
parallel processes within the available memory, with a progress bar.

Modules: :mod:`.inputs` (the typed outputs of a run, read by the stages' readers),
:mod:`.derived` (pairs joined to markers, FRE(l), predicted TRE), :mod:`.checks` (warnings, by
the stages' own policies), :mod:`.figures` (one function per figure, in a registry),
:mod:`.html` and :mod:`.sections` (the page, one function per section), :mod:`.writer`
(:func:`~.writer.write_report`), :mod:`.batch` (:func:`~.batch.write_reports_batch`). The package re-exports
nothing: import from the module (one way: inputs -> derived -> checks -> figures -> html/sections -> writer -> batch).

Frames: positions in the tables are image space (CT LPS, mm) unless they say Reference.
"""
