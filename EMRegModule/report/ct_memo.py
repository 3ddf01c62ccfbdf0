"""What the report takes from the CT's voxels, kept beside its figures for the next report of the same run.

A report needs two things from the CT: the block-averaged CT its 3D view's context surface is contoured
from, and each marker's three sampled planes for the slice mosaic. Both cost a full read of the CT (the
inflation of a compressed file is most of a detection's time); both depend only on the CT's bytes, the
markers' poses and the marker model. So a report that made them keeps them in
``OUT/report_figures/ct_context.npz`` (plain ``numpy`` arrays, no pickles), keyed by the CT's sha256 as
``run.json`` records it, the marker model and each marker's ``MarkerToImage``; a later report of that run
(``emreg report OUT``) uses them instead of reading the CT again. It still hashes the CT file on a thread
and refuses a CT whose sha256 is not the recorded one (:func:`~EMRegModule.report.writer._check_run_ct`),
so the figures always come from the bytes the run used. Anything that does not match (another CT,
moved markers, other settings, a file of another format version) is ignored and the CT is read.

Frames: ``index_to_image`` maps the binned CT's continuous (i, j, k) index to image space (LPS mm); the
marker poses are ``MarkerToImage`` (LPS mm).
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import json
import os
import shutil
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..io.atomic import atomic_path, atomic_write_bytes
from ..io.ct_handle import CTGeometry, CTHandle
from ..io.provenance import BackgroundHash
from ..marker_model import MarkerModel
from ..names import PREVIOUS_FOLDER, REPORT_FIGURES
from ..rendering.context import MAX_CONTEXT_VOXELS, BinnedCT, ContextSurface
from ..rendering.slices import MM_PER_PX, VIEW_PX

MEMO_NAME = "ct_context.npz"
#: Bumped whenever what is kept, or how the figures make it (binning, view size, sampling), changes.
MEMO_FORMAT = 2


def _model_key(model: MarkerModel) -> str:
    return hashlib.sha256(json.dumps(dataclasses.asdict(model), sort_keys=True).encode()).hexdigest()


def _key(ct_sha256: str, model: MarkerModel) -> str:
    return json.dumps({"format": MEMO_FORMAT, "ct_sha256": ct_sha256, "model": _model_key(model),
                       "max_context_voxels": MAX_CONTEXT_VOXELS, "view_px": VIEW_PX, "mm_per_px": MM_PER_PX},
                      sort_keys=True)


@dataclass
class CTMemo:
    """The kept CT products: ``binned``; ``planes`` (markers, 3, px, px) float32, each marker's three sampled
    planes in the order of ``marker_to_image`` (markers, 4, 4, ``MarkerToImage``, LPS mm); ``geometry``: the CT's.
    It answers as :class:`~EMRegModule.rendering.slices.StreamingMarkerViews` does (``views``, ``release``)."""

    binned: BinnedCT
    planes: np.ndarray
    marker_to_image: np.ndarray
    geometry: CTGeometry
    source: Path | None = None
    surface: dict[str, Any] | None = None  # the context surface's arrays and figures (see save_ct_memo)

    def context_surface(self, iso_setting: float | None) -> ContextSurface | None:
        """The kept context surface when it was made with this ``[report] iso_value`` setting, else None."""
        import pyvista as pv

        if self.surface is None:
            return None
        meta = dict(self.surface["meta"])
        if meta.pop("iso_setting", "absent") != iso_setting:
            return None
        polydata = pv.PolyData(self.surface["points"], self.surface["faces"])
        if self.surface.get("ct") is not None:
            polydata.point_data["ct"] = self.surface["ct"]
        return ContextSurface(polydata, **meta)

    def matches(self, marker_to_image: list[np.ndarray]) -> bool:
        """Whether these are the planes of exactly these markers, in this order."""
        poses = np.asarray(marker_to_image, dtype=float).reshape(-1, 4, 4)
        return poses.shape == self.marker_to_image.shape and bool(np.array_equal(poses, self.marker_to_image))

    def views(self) -> list[list[np.ndarray]]:
        """Each marker's three planes (float32, px x px), in the order of ``marker_to_image``."""
        return [list(planes) for planes in self.planes]

    def release(self) -> None:
        return None

    def ct_handle(self, path: Path) -> CTHandle:
        """The report's CT when these products are kept: its geometry, no voxels (``result()`` is None), this memo,
        and the file's sha256 computed on a thread (``sha256``), which the report checks against ``run.json``."""
        handle = CTHandle.without_voxels(self.geometry, BackgroundHash(path))
        handle.path, handle.memo = path, self
        return handle


def recorded_ct_sha256(run: dict | None, ct_path: Path | None) -> str | None:
    """The sha256 ``run.json`` records for the CT at ``ct_path`` (None when it records another path or none)."""
    entry = (((run or {}).get("inputs") or {}).get("ct")) or {}
    if ct_path is None or not isinstance(entry, dict) or not isinstance(entry.get("sha256"), str):
        return None
    recorded = entry.get("path")
    if not isinstance(recorded, str) or Path(recorded).resolve() != Path(ct_path).resolve():
        return None
    return entry["sha256"]


def _key_matches(kept: Any, ct_sha256: str, model: MarkerModel | None) -> bool:
    key = json.loads(str(kept["key"]))
    expected = json.loads(_key(ct_sha256, model or MarkerModel()))
    if model is None:  # the early check, before the case's settings are read
        key.pop("model", None)
        expected.pop("model", None)
    return key == expected


def kept_for(path: Path, ct_sha256: str | None) -> bool:
    """Whether ``path`` keeps products of the CT whose sha256 is ``ct_sha256`` (for any marker model)."""
    if ct_sha256 is None or not path.is_file():
        return False
    try:
        with np.load(path, allow_pickle=False) as kept:
            return _key_matches(kept, ct_sha256, None)
    except (OSError, ValueError, KeyError, TypeError, EOFError, zipfile.BadZipFile):
        return False


def load_ct_memo(path: Path, ct_sha256: str | None, model: MarkerModel) -> CTMemo | None:
    """The products kept in ``path`` for the CT whose sha256 is ``ct_sha256`` and this marker model; None when
    absent, unreadable or made for something else."""
    if ct_sha256 is None or not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as kept:
            if not _key_matches(kept, ct_sha256, model):
                return None
            binned = BinnedCT(np.ascontiguousarray(kept["binned"], dtype=np.float32),
                              np.asarray(kept["index_to_image"], dtype=float), int(kept["factor"]))
            geometry = CTGeometry.from_getters(json.loads(str(kept["geometry"])))
            surface = None
            if "surface_points" in kept.files:
                surface = {"points": kept["surface_points"], "faces": kept["surface_faces"],
                           "ct": kept["surface_ct"] if "surface_ct" in kept.files else None,
                           "meta": json.loads(str(kept["surface_meta"]))}
            return CTMemo(binned, np.asarray(kept["views"], dtype=np.float32),
                          np.asarray(kept["marker_to_image"], dtype=float), geometry, path, surface)
    except (OSError, ValueError, KeyError, TypeError, EOFError, zipfile.BadZipFile):
        return None


def save_ct_memo(path: Path, ct_sha256: str, model: MarkerModel, geometry: CTGeometry, binned: BinnedCT,
                 views: list[list[np.ndarray]] | None, marker_to_image: list[np.ndarray],
                 surface: ContextSurface | None = None, iso_setting: float | None = None) -> None:
    """Keep the CT products of a report (atomically); nothing when a marker's planes are missing. ``surface``:
    the context surface made from ``binned`` with the ``[report] iso_value`` setting ``iso_setting``; ``geometry``:
    the CT's (:attr:`~EMRegModule.io.ct_handle.CTHandle.geometry`)."""
    if views is None and marker_to_image:
        return
    planes = views or []
    if any(p is None or len(p) != 3 for p in planes):
        return
    stacked = (np.stack([np.stack(p) for p in planes]).astype(np.float32, copy=False) if planes
               else np.zeros((0, 3, 1, 1), np.float32))
    extra: dict[str, np.ndarray] = {}
    if surface is not None and surface.surface is not None and surface.surface.is_all_triangles:
        polydata = surface.surface
        meta = {name: getattr(surface, name) for name in ("iso_value", "pieces", "dropped_thin_voxels",
                                                          "dropped_pieces", "voxel_mm", "inside_voxels", "otsu")}
        extra = {"surface_points": np.asarray(polydata.points), "surface_faces": np.asarray(polydata.faces),
                 "surface_meta": np.array(json.dumps({**meta, "iso_setting": iso_setting}))}
        if "ct" in polydata.point_data:
            extra["surface_ct"] = np.asarray(polydata.point_data["ct"])
    buffer = io.BytesIO()
    np.savez(buffer, key=np.array(_key(ct_sha256, model)), binned=binned.values,
             index_to_image=binned.index_to_image, factor=np.array(binned.factor), views=stacked,
             marker_to_image=np.asarray(marker_to_image, dtype=float).reshape(-1, 4, 4),
             geometry=np.array(json.dumps(geometry.getters())), **extra)
    atomic_write_bytes(path, buffer.getvalue())


def memo_path(out_dir: str | os.PathLike[str]) -> Path:
    """Where a report of ``out_dir`` keeps its CT products."""
    return Path(out_dir) / REPORT_FIGURES / MEMO_NAME


def memo_candidates(out_dir: str | os.PathLike[str]) -> list[Path]:
    """Where the last report's CT products may be: beside its figures, or in ``previous/`` once a new report
    has started (its stage moves the last report there)."""
    here = memo_path(out_dir)
    return [here, Path(out_dir) / PREVIOUS_FOLDER / here.parent.name / here.name]


def carry_forward(memo: CTMemo, out_dir: str | os.PathLike[str]) -> None:
    """Keep the products a report used beside its new figures (a hard link to the kept file where possible)."""
    target = memo_path(out_dir)
    if memo.source is None or memo.source == target or not memo.source.is_file():
        return
    target.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(target) as tmp:
        try:
            tmp.unlink()
            os.link(memo.source, tmp)
        except OSError:
            shutil.copyfile(memo.source, tmp)
