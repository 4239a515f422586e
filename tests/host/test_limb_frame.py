"""The limb-frame export for prosthetic CAD: limb axis on +z, distal end at z = 0, volume kept.

A synthetic limb of known axis (circular sections whose centres lie on a tilted line) checks
the frame exactly; a simulated scan checks ``lamina export -o X.limb.stl`` end to end.
"""

from __future__ import annotations

import json
import math
import subprocess
from pathlib import Path

import numpy as np
import pytest

from lamina_host.clinical.limb_frame import limb_frame, rotation_onto_z
from lamina_host.reconstruct.efd import efd_fit
from lamina_host.reconstruct.mesh import load_ply, signed_volume, stl_triangles, tube_mesh
from lamina_host.store.library import Library
from tests.helpers.cli import host_command

SLOPE = np.array([0.10, -0.05])
"""The synthetic limb's centre line: x, y = CENTRE + SLOPE z (a tilt of 6.4 degrees)."""
CENTRE = np.array([3.0, -2.0])
HEIGHTS_MM = np.arange(0.0, 101.0, 5.0)


def synthetic_limb(distal_top: bool) -> tuple[dict[str, object], np.ndarray, np.ndarray]:
    """Return a report (outlines with EFDs) and the mesh of a tapered limb on a tilted line."""
    t = np.linspace(0.0, 2.0 * math.pi, 96, endpoint=False)
    rings = []
    for z in HEIGHTS_MM:
        radius = 40.0 - 0.15 * z if distal_top else 25.0 + 0.15 * z
        centre = CENTRE + SLOPE * z
        rings.append(centre + radius * np.column_stack([np.cos(t), np.sin(t)]))
    sections = [
        {"z_mm": float(z), "part": 0, "status": "measured", "efd": efd_fit(ring, 6).to_dict()}
        for z, ring in zip(HEIGHTS_MM, rings, strict=True)
    ]
    vertices, faces = tube_mesh(np.stack(rings), HEIGHTS_MM)
    return {"sections": sections}, vertices, faces


def test_rotation_onto_z_is_a_proper_rotation() -> None:
    for d in ([0.1, -0.05, 1.0], [0.0, 0.0, -1.0], [0.0, 0.0, 1.0], [1.0, 2.0, -0.5]):
        r = rotation_onto_z(np.array(d))
        assert np.allclose(r @ r.T, np.eye(3)) and math.isclose(np.linalg.det(r), 1.0)
        assert np.allclose(r @ (np.array(d) / np.linalg.norm(d)), [0.0, 0.0, 1.0])


@pytest.mark.parametrize("distal_top", [False, True])
def test_the_frame_puts_the_axis_on_z_and_the_distal_end_at_the_origin(distal_top: bool) -> None:
    report, vertices, faces = synthetic_limb(distal_top)
    frame = limb_frame(report, vertices, 1)
    assert frame.distal_top is distal_top
    assert frame.axis.method == "centreline"
    expected = np.append(SLOPE, 1.0) / np.linalg.norm(np.append(SLOPE, 1.0))
    assert np.allclose(frame.axis.direction, expected, atol=1e-9)
    moved = frame.apply(vertices)
    # Every ring's centre (its vertices' mean: a uniformly sampled circle) lies on the z axis.
    rings = moved[: len(HEIGHTS_MM) * 96].reshape(len(HEIGHTS_MM), 96, 3)
    centres = rings.mean(axis=1)
    assert np.abs(centres[:, :2]).max() < 1e-9
    # z grows from the distal end: the distal ring (the narrow one) is the lowest, at z ~ 0.
    distal = rings[-1] if distal_top else rings[0]
    assert moved[:, 2].min() == pytest.approx(0.0, abs=1e-9)
    assert distal[:, 2].min() == pytest.approx(0.0, abs=1e-9)
    assert np.all(np.diff(centres[:, 2]) < 0 if distal_top else np.diff(centres[:, 2]) > 0)
    length = 100.0 * np.linalg.norm(np.append(SLOPE, 1.0))  # centre line, end ring to end ring
    assert abs(centres[:, 2].max() - centres[:, 2].min()) == pytest.approx(length, rel=1e-9)
    assert signed_volume(moved, faces) == pytest.approx(signed_volume(vertices, faces), rel=1e-12)
    # The 4x4 matrix the sidecar records does the same.
    homogeneous = np.column_stack([vertices, np.ones(len(vertices))]) @ frame.matrix().T
    assert np.allclose(homogeneous[:, :3], moved, atol=1e-9)


def export_scan_1(library: Path, out: Path) -> subprocess.CompletedProcess[str]:
    """Run ``lamina export 1 -o OUT`` on ``library``."""
    return subprocess.run(
        host_command("export", "1", "-o", str(out), "--library", str(library)),
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_cli_exports_a_scan_in_the_limb_frame(scanned_library: Path, tmp_path: Path) -> None:
    out = tmp_path / "leg.limb.stl"
    done = export_scan_1(scanned_library, out)
    assert done.returncode == 0, done.stderr
    sidecar = json.loads((tmp_path / "leg.limb.json").read_text())
    data = out.read_bytes()
    assert data[:80].decode("ascii").startswith("Lamina limb frame: +z limb axis (centreline")
    triangles = stl_triangles(data).astype(np.float64)
    with Library(scanned_library) as library:
        vertices, faces = load_ply(library.result_mesh(1))
    matrix = np.array(sidecar["scanner_to_limb"])
    expected = (np.column_stack([vertices, np.ones(len(vertices))]) @ matrix.T)[:, :3]
    assert np.allclose(triangles, expected[faces], atol=1e-4)  # float32 in the STL
    assert triangles[..., 2].min() == pytest.approx(0.0, abs=1e-4)
    axis = np.array(sidecar["axis_scanner"]["direction"])
    up = -axis if sidecar["distal_end"] == "top" else axis
    assert np.allclose(matrix[:3, :3] @ up, [0.0, 0.0, 1.0])
    flat = triangles.reshape(-1, 3)
    volume = signed_volume(flat, np.arange(len(flat)).reshape(-1, 3))
    assert volume == pytest.approx(signed_volume(vertices, faces), rel=1e-5)
    # A rigid move keeps the volume; the sum of the faces' triple products about another
    # origin rounds differently (1.3e-9 apart seen on one mesh), far below any real change.
    assert sidecar["volume_mm3"] == pytest.approx(signed_volume(vertices, faces), rel=1e-7)
    assert sidecar["landmark"] == "distal end" and sidecar["units"] == "mm"


def test_cli_refuses_a_limb_export_over_an_existing_sidecar(
    scanned_library: Path, tmp_path: Path
) -> None:
    (tmp_path / "leg.limb.json").write_text("earlier")
    out = tmp_path / "leg.limb.stl"
    done = export_scan_1(scanned_library, out)
    assert done.returncode != 0 and done.stderr.count("\n") == 1
    assert "leg.limb.json already exists" in done.stderr
    assert not out.exists() and (tmp_path / "leg.limb.json").read_text() == "earlier"
