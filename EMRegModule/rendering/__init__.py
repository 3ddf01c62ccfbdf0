"""Offscreen rendering for the verification report: 3D scenes, CT slice mosaics, plots.

Everything here is deterministic for the same inputs (fixed camera, window size, lighting,
no anti-aliasing, no timestamps), so images can be compared against golden baselines in
``Testing/Baseline`` (the comparison lives with the tests: ``Testing/Python/fixtures/compare.py``).
Images are RGB ``uint8`` arrays of shape (height, width, 3).

- :mod:`.colors`: colour maps (OpenCV's tables, so matplotlib is not needed).
- :mod:`.images`: PNG encoding / atomic writing / reading.
- :mod:`.scene3d`: the fiducial frame in 3D with the fitted marker models (pyvista offscreen).
- :mod:`.slices`: per-marker orthogonal CT slices with the fitted model outline (OpenCV).
- :mod:`.plots`: bar charts and curves drawn with OpenCV.
"""
