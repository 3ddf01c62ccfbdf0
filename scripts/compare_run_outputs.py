"""Compare two ``emreg run`` output folders file by file (before/after a refactoring).

JSON files must be byte-identical once the keys the newer version adds are left out: the
``provenance`` object of each output, and in ``run.json`` every key the older one did not have;
the output folder's own path is normalised in ``run.json``'s summary. ``navigation.csv``,
``markers.mrk.json`` must be byte-identical; ``ReferenceToImage.h5`` must hold exactly the same
transform (HDF5 stores the time of writing, so two writes of one transform differ in a few bytes).
Prints one line per file and exits 1 on any difference.

    .venv/bin/python scripts/compare_run_outputs.py BEFORE_OUT AFTER_OUT
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

BYTES = ("navigation.csv", "markers.mrk.json")
JSON = ("markers.json", "frame_calibration.json", "registration.json", "evaluation.json", "run.json")


def _dump(document: object) -> str:
    return json.dumps(document, indent=2) + "\n"


def _normalise_run(before: dict, after: dict, before_dir: Path, after_dir: Path) -> tuple[dict, dict]:
    after = {k: v for k, v in after.items() if k in before}  # keys the newer run.json adds
    for document, folder in ((before, before_dir), (after, after_dir)):
        document["summary"] = [line.replace(str(folder), "OUT") for line in document.get("summary", [])]
    return before, after


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


def compare(before_dir: Path, after_dir: Path) -> int:
    failures = 0
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
        after.pop("provenance", None)
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
