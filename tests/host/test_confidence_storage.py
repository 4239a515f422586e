"""Per-point confidence survives the library and segments.npz; older scans still load."""

from __future__ import annotations

import sqlite3

import numpy as np
import pytest

from lamina_host.store.library import Library
from lamina_host.store.outputs import load_segments, save_segments
from lamina_shared.types import ScanPlan, Segment

PLANS = {"object": ScanPlan.regular(2, 2.0, 2)}


def segment(seq: int, n: int = 40) -> Segment:
    """Return a segment whose confidence differs from point to point."""
    rng = np.random.default_rng(seq)
    view = PLANS["object"].views[seq]
    return Segment(
        "object", view.section, seq % 2, view.z_mm, view.angle_deg,
        np.sort(rng.choice(640, n, replace=False)).astype(np.uint16),
        (rng.integers(0, 480 * 64, n) / 64).astype(np.float32),
        rng.integers(1, 256, n).astype(np.uint8),
        rng.integers(1, 20, n).astype(np.uint8),
        rng.integers(0, 256, n).astype(np.uint8),
    )  # fmt: skip


def test_library_keeps_confidence(tmp_path):
    with Library(tmp_path / "library.sqlite") as library:
        scan_id = library.create_scan("S-01", PLANS)
        for seq in range(4):
            library.add_segment(scan_id, seq, segment(seq))
        got = library.segments(scan_id, "object")
    assert len(got) == 4
    for seq, s in enumerate(got):
        assert s.same_as(segment(seq))
        assert s.confidence.tolist() == segment(seq).confidence.tolist()


def test_library_rows_from_before_confidence_load_as_unknown(tmp_path):
    path = tmp_path / "library.sqlite"
    with Library(path) as library:
        scan_id = library.create_scan("S-01", PLANS)
        library.add_segment(scan_id, 0, segment(0))
    with sqlite3.connect(path) as db:  # cut the confidence bytes off: a version-2 row
        (data,) = db.execute("SELECT data FROM segments").fetchone()
        db.execute("UPDATE segments SET data = ?", (data[: 8 * 40],))
    with Library(path) as library:
        (old,) = library.segments(scan_id, "object")
    assert old.confidence.tolist() == [0] * 40
    assert np.array_equal(old.rows, segment(0).rows) and np.array_equal(old.peak, segment(0).peak)


def test_segments_npz_keeps_confidence_and_reads_older_files(tmp_path):
    segments = [segment(seq) for seq in range(3)]
    save_segments(tmp_path / "segments.npz", segments)
    for got, want in zip(load_segments(tmp_path / "segments.npz"), segments, strict=True):
        assert got.same_as(want)
    with np.load(tmp_path / "segments.npz") as data:  # an older file: no confidence arrays
        older = {k: data[k] for k in data.files if not k.endswith("_confidence")}
    np.savez_compressed(tmp_path / "older.npz", **older)
    for got, want in zip(load_segments(tmp_path / "older.npz"), segments, strict=True):
        assert got.confidence.tolist() == [0] * len(want)
        assert np.array_equal(got.rows, want.rows)


def test_segment_refuses_a_confidence_of_another_length():
    s = segment(0)
    with pytest.raises(ValueError, match="differ in length"):
        Segment(s.target, 0, 0, 0.0, 0.0, s.cols, s.rows, s.peak, s.width, s.confidence[:-1])
