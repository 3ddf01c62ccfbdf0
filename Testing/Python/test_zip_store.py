"""The stored-entry ZIP writer of scene bundles, and the navigation CSV reader: read back by Python's own readers."""

import hashlib
import zipfile

import numpy as np
import pytest

from EMRegModule.errors import EMRegError
from EMRegModule.io import zip_store
from EMRegModule.io.navigation_csv import read_navigation_csv
from EMRegModule.io.zip_store import FileRegion, StoredZipWriter


def _source(tmp_path, size=3_000_001, seed=0):
    data = np.random.default_rng(seed).integers(0, 256, size, dtype=np.uint8).tobytes()
    path = tmp_path / "source.bin"
    path.write_bytes(data)
    return path, data


def _write(target, path, monkeypatch=None, chunk=None):
    if chunk is not None:
        monkeypatch.setattr(zip_store, "_CHUNK_BYTES", chunk)
    with StoredZipWriter(target) as out:
        out.add_directory("Scene", 0.0)
        out.add("Scene/scene.mrml", [b"<MRML/>"], 1.7e9)
        out.add("Scene/Data/ct.nrrd", [b"NRRD0004\n\n", FileRegion(path, 17, 2_500_000), b"tail"])
        out.add("Scene/Data/n\u00e4me.txt", [])
        return out.close()


@pytest.mark.parametrize("chunk", [None, 1 << 16, 100_003])
def test_entries_read_back_with_their_crc_and_the_hash_is_the_files(tmp_path, monkeypatch, chunk):
    path, data = _source(tmp_path)
    target = tmp_path / "out.zip"
    digest = _write(target, path, monkeypatch, chunk)
    assert digest == hashlib.sha256(target.read_bytes()).hexdigest()
    with zipfile.ZipFile(target) as archive:
        assert archive.testzip() is None  # every CRC-32 checked
        assert archive.namelist() == ["Scene/", "Scene/scene.mrml", "Scene/Data/ct.nrrd", "Scene/Data/n\u00e4me.txt"]
        assert archive.getinfo("Scene/").is_dir()
        assert archive.read("Scene/scene.mrml") == b"<MRML/>"
        assert archive.read("Scene/Data/ct.nrrd") == b"NRRD0004\n\n" + data[17:2_500_017] + b"tail"
        assert archive.read("Scene/Data/n\u00e4me.txt") == b""
        assert all(info.compress_type == zipfile.ZIP_STORED for info in archive.infolist())


def test_zip64_records_where_sizes_and_offsets_need_them(tmp_path, monkeypatch):
    """Sizes and offsets from the limit on go into ZIP64 fields (lowered here: 4 GB archives are not made in tests)."""
    monkeypatch.setattr(zip_store, "ZIP64_LIMIT", 1000)
    path, data = _source(tmp_path, 5000)
    target = tmp_path / "out.zip"
    with StoredZipWriter(target) as out:
        out.add("small", [b"x" * 10])
        out.add("large", [FileRegion(path, 0, 5000)])
        out.add("after", [b"y" * 20])  # its local header lies beyond the limit
        digest = out.close()
    assert digest == hashlib.sha256(target.read_bytes()).hexdigest()
    raw = target.read_bytes()
    assert b"PK\x06\x06" in raw and b"PK\x06\x07" in raw  # ZIP64 end record and locator
    with zipfile.ZipFile(target) as archive:
        assert archive.testzip() is None
        assert archive.read("large") == data and archive.read("after") == b"y" * 20


@pytest.mark.parametrize("kernel_copies", [0, 7])
def test_bytes_the_kernel_does_not_copy_are_written(tmp_path, monkeypatch, kernel_copies):
    """Where ``copy_file_range`` is missing or copies less (other file systems), the rest is written from the map."""
    real = zip_store._kernel_copy
    monkeypatch.setattr(zip_store, "_kernel_copy", lambda src, dst, offset, count: real(src, dst, offset,
                                                                                        min(count, kernel_copies)))
    path, data = _source(tmp_path)
    target = tmp_path / "out.zip"
    digest = _write(target, path)
    assert digest == hashlib.sha256(target.read_bytes()).hexdigest()
    with zipfile.ZipFile(target) as archive:
        assert archive.testzip() is None
        assert archive.read("Scene/Data/ct.nrrd") == b"NRRD0004\n\n" + data[17:2_500_017] + b"tail"


def test_a_region_beyond_the_end_of_its_file_is_an_error(tmp_path):
    path, _ = _source(tmp_path, 100)
    with StoredZipWriter(tmp_path / "out.zip") as out, pytest.raises(OSError, match="shorter than expected"):
        out.add("x", [FileRegion(path, 0, 1 << 20)])


def test_navigation_csv_fast_and_row_by_row_readings_agree(tmp_path):
    rows = [(0.5 * i, 10.0 + i / 3, -20.0 - i / 7, 1e-3 * i, "T1" if i % 3 == 0 else "") for i in range(50)]
    lines = [f"{t:.4f},{x:.4f},{y:.4f},{z:.4f},{lab}\n" for t, x, y, z, lab in rows]
    text = "time_s,x_mm,y_mm,z_mm,label\n" + "".join(lines)
    plain = tmp_path / "plain.csv"
    plain.write_text(text)
    quoted = tmp_path / "quoted.csv"  # a quoted label: read row by row
    quoted.write_text(text.replace(",T1\n", ',"T1"\n'))
    positions, labels = read_navigation_csv(plain)
    assert positions.shape == (50, 3) and labels == [lab for *_, lab in rows]
    np.testing.assert_array_equal(positions, [[float(f"{v:.4f}") for v in r[1:4]] for r in rows])
    positions_quoted, labels_quoted = read_navigation_csv(quoted)
    np.testing.assert_array_equal(positions_quoted, positions)
    assert labels_quoted == labels
    bad = tmp_path / "bad.csv"
    bad.write_text(text.replace("10.0000", "ten", 1))
    with pytest.raises(EMRegError, match="non-numeric position"):
        read_navigation_csv(bad)
    missing = tmp_path / "missing.csv"
    missing.write_text("time_s,x_mm,label\n1,2,\n")
    with pytest.raises(EMRegError, match="lacks column"):
        read_navigation_csv(missing)
