"""Compare two ``emreg run`` output folders file by file (before/after a refactoring).

JSON files must be identical once the keys the newer version adds are left out: the ``provenance``
object of each output, and in ``run.json`` every key the older one did not have, the start and end
times and the sha256 of the outputs whose bytes hold their time of writing (:data:`TIMED`); the
output folder's own path (the demo's: its parent, which holds its case) is normalised. ``navigation.csv``,
``markers.mrk.json`` must be byte-identical; ``ReferenceToImage.h5`` must hold exactly the same
transform (HDF5 stores the time of writing, so two writes of one transform differ in a few bytes);
``checkpoints.json`` and ``tool_calibration.json`` (when present) compare as JSON files do; ``tre_map.nrrd``
must hold the same voxels (exactly) on the same geometry (size, spacing, origin, direction).
Prints one line per file and exits 1 on any difference.

    .venv/bin/python scripts/compare_run_outputs.py BEFORE_OUT AFTER_OUT
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

BYTES = ("navigation.csv", "markers.mrk.json")
JSON = ("markers.json", "frame_calibration.json", "registration.json", "evaluation.json", "checkpoints.json",
        "tool_calibration.json", "run.json")
IMAGES = ("tre_map.nrrd",)


def _dump(document: object) -> str:
    return json.dumps(document, indent=2) + "\n"


#: Outputs whose bytes hold the time they were written (HDF5, the report's page and the bundle that holds it): in
#: ``run.json`` their sha256 is left out (their content is compared above, where it can be).
TIMED = ("ReferenceToImage.h5", "TipToProbe.h5", "report.html", "EMReg.mrb")
#: Keys of ``run.json`` that hold when the run started and ended.
TIMES = ("started_utc", "finished_utc")


def _untimed(document: object) -> object:
    """``document`` with the sha256 of :data:`TIMED` outputs left out, wherever they are listed."""
    if isinstance(document, dict):
        return {k: ("<timed>" if k in TIMED and isinstance(v, str) else _untimed(v))
                for k, v in document.items()}
    if isinstance(document, list):
        return [_untimed(v) for v in document]
    return document


def _normalise_run(before: dict, after: dict, before_dir: Path, after_dir: Path) -> tuple[dict, dict]:
    after = {k: v for k, v in after.items() if k in before}  # keys the newer run.json adds
    normalised = []
    for document, folder in ((before, before_dir), (after, after_dir)):
        for key in TIMES:
            document.pop(key, None)
        outputs = document.get("outputs") or {}
        demo = folder.name == "result"  # its files name its own case's paths: their sha256 differ with the folder
        for name, entry in outputs.items():
            if isinstance(entry, dict) and (demo or name in TIMED):
                entry.pop("sha256", None)
                if demo and isinstance(entry.get("provenance"), dict):
                    entry["provenance"].pop("uses", None)
        root = str(folder.parent) if folder.name == "result" else str(folder)  # the demo's case lies beside it
        text = json.dumps(_untimed(document)).replace(root, "OUT")
        normalised.append(json.loads(text))
    return normalised[0], normalised[1]


def _compare_transform(a: Path, b: Path) -> int:
    if not a.exists() and not b.exists():
        return 0
    import SimpleITK as sitk

    if a.exists() and b.exists() and a.read_bytes() == b.read_bytes():
        print(f"{a.name:24s} identical bytes")
        return 0
    ta, tb = sitk.ReadTransform(str(a)), sitk.ReadTransform(str(b))
    same = ta.GetParameters() == tb.GetParameters() and ta.GetFixedParameters() == tb.GetFixedParameters()
    print(f"{a.name:24s} {'the same transform, exactly (HDF5 write times differ)' if same else 'DIFFERENT'}")
    return 0 if same else 1


def _compare_image(a: Path, b: Path) -> int:
    """Voxels and geometry of two images (a gzip NRRD's bytes may differ in its header's layout only)."""
    if not a.exists() and not b.exists():
        return 0
    if not (a.exists() and b.exists()):
        print(f"{a.name:24s} MISSING on one side")
        return 1
    import numpy as np
    import SimpleITK as sitk

    ia, ib = sitk.ReadImage(str(a)), sitk.ReadImage(str(b))
    geometry = [(getter, getattr(ia, getter)(), getattr(ib, getter)()) for getter in
                ("GetSize", "GetSpacing", "GetOrigin", "GetDirection", "GetPixelID")]
    different = [getter[3:] for getter, x, y in geometry if x != y]
    if not different and not np.array_equal(sitk.GetArrayViewFromImage(ia), sitk.GetArrayViewFromImage(ib)):
        different.append("voxels")
    print(f"{a.name:24s} {'the same voxels and geometry' if not different else 'DIFFERENT: ' + ', '.join(different)}")
    return 1 if different else 0


def compare(before_dir: Path, after_dir: Path) -> int:
    failures = 0
    for name in IMAGES:
        failures += _compare_image(before_dir / name, after_dir / name)
    for name in BYTES:
        a, b = before_dir / name, after_dir / name
        if not a.exists() and not b.exists():
            continue
        same = a.exists() and b.exists() and a.read_bytes() == b.read_bytes()
        print(f"{name:24s} {'identical bytes' if same else 'DIFFERENT'}")
        failures += not same
    failures += _compare_transform(before_dir / "ReferenceToImage.h5", after_dir / "ReferenceToImage.h5")
    for name in JSON:
        a, b = before_dir / name, after_dir / name
        if not a.exists() and not b.exists():
            continue
        if not (a.exists() and b.exists()):
            print(f"{name:24s} MISSING on one side")
            failures += 1
            continue
        text_a = a.read_text()
        before, after = json.loads(text_a), json.loads(b.read_text())
        added = sorted(set(after) - set(before))
        for document in (before, after):
            document.pop("provenance", None)
        if name != "run.json" and before_dir.name == "result":  # the demo: its case lies in each run's own folder
            before = json.loads(json.dumps(before).replace(str(before_dir.parent), "OUT"))
            after = json.loads(json.dumps(after).replace(str(after_dir.parent), "OUT"))
        text_a = _dump(before)
        if name == "run.json":
            before, after = _normalise_run(before, after, before_dir, after_dir)
            text_a = _dump(before)
        same = _dump(after) == text_a
        print(f"{name:24s} {'identical bytes' if same else 'DIFFERENT'} apart from added keys {added}")
        if not same:
            failures += 1
            for key in sorted(set(before) | set(after)):
                if before.get(key) != after.get(key):
                    print(f"    differs at {key!r}")
    return 1 if failures else 0


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    sys.exit(compare(Path(sys.argv[1]), Path(sys.argv[2])))
