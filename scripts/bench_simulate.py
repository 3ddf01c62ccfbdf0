"""Benchmark of CT synthesis: brick-skipping painter vs a plain painter that evaluates every voxel.

Both paint the same phantom (the CI-sized frame by default) into the same grid; the plain
baseline walks each solid's bounding box slab by slab and evaluates every voxel. The
script prints both times, their ratio, the largest difference between the two volumes,
and the wall time / peak memory of a complete ``simulate_case`` run.

    .venv/bin/python scripts/bench_simulate.py [--full] [--spacing MM]
"""

from __future__ import annotations

import argparse
import resource
import tempfile
import time
from pathlib import Path

import numpy as np

from EMRegModule.core.transforms import apply_transform, invert_rigid
from EMRegModule.marker_model import MarkerModel
from EMRegModule.simulation import ct
from EMRegModule.simulation.case import _frame_to_image, _rng, simulate_case
from EMRegModule.simulation.frame import build_phantom
from EMRegModule.simulation.options import resolve_options


def plain_paint(volume: np.ndarray, grid: ct.Grid, image_to_frame: np.ndarray, layers: list[ct.Layer]) -> None:
    """Baseline: every voxel of every layer's bounding box is evaluated (no brick skipping)."""
    index_to_frame = image_to_frame @ grid.index_to_image
    frame_to_index = np.linalg.inv(index_to_frame)
    a, b = index_to_frame[:3, :3], index_to_frame[:3, 3]
    spacing = np.linalg.norm(a, axis=0)
    ramp = float(np.prod(spacing) ** (1 / 3))
    half_diag = 0.5 * float(np.linalg.norm(spacing))
    for layer in layers:
        lo, hi = layer.shape.bounds
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        idx = apply_transform(frame_to_index, corners)
        start = np.maximum(np.floor(idx.min(axis=0)).astype(int) - 1, 0)
        stop = np.minimum(np.ceil(idx.max(axis=0)).astype(int) + 2, np.asarray(grid.size))
        if np.any(stop <= start):
            continue
        for k0 in range(start[2], stop[2], 8):
            k1 = min(k0 + 8, stop[2])
            fraction = ct._brick_fraction(layer, a, b, (start[0], stop[0]), (start[1], stop[1]), (k0, k1),
                                          ramp, half_diag)
            if fraction is not None:
                view = volume[k0:k1, start[1]:stop[1], start[0]:stop[0]]
                view += fraction * (np.float32(layer.hu) - view)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--full", action="store_true", help="the full 350 x 350 x 200 mm frame with 28 markers")
    parser.add_argument("--spacing", type=float, default=0.6)
    args = parser.parse_args()
    options = {} if args.full else {"frame_size_mm": (220.0, 220.0, 140.0), "n_markers": 16}
    opts = resolve_options("standard", args.spacing, options)
    model = MarkerModel()
    phantom = build_phantom(_rng(0, 1), model, opts.frame_size_mm, opts.n_markers)
    frame_to_image = _frame_to_image(_rng(0, 2), phantom, opts)
    grid = ct.grid_around(apply_transform(frame_to_image, phantom.extent_points), np.asarray(opts.spacing),
                          np.eye(3), 8.0)
    image_to_frame = invert_rigid(frame_to_image)
    print(f"grid {grid.size} = {grid.n_voxels / 1e6:.0f} M voxels, {len(phantom.layers)} solids")

    fast = np.full(grid.shape_kji, ct.AIR_HU, dtype=np.float32)
    start = time.perf_counter()
    ct.paint_layers(fast, grid, image_to_frame, phantom.layers)
    t_fast = time.perf_counter() - start

    plain = np.full(grid.shape_kji, ct.AIR_HU, dtype=np.float32)
    start = time.perf_counter()
    plain_paint(plain, grid, image_to_frame, phantom.layers)
    t_plain = time.perf_counter() - start
    difference = float(np.abs(fast - plain).max())
    del fast, plain
    print(f"plain painter  {t_plain:7.2f} s (baseline)")
    print(f"brick painter  {t_fast:7.2f} s  ratio {t_plain / t_fast:5.1f}x faster; "
          f"max |difference| {difference:.3g} HU")

    with tempfile.TemporaryDirectory() as folder:
        start = time.perf_counter()
        simulate_case(Path(folder) / "case", seed=0, spacing_mm=args.spacing, **options)
        total = time.perf_counter() - start
    peak_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
    print(f"simulate_case (CT + recordings + files) {total:.1f} s; process peak RSS {peak_gb:.2f} GB "
          f"(includes the two benchmark volumes)")


if __name__ == "__main__":
    main()
