"""The host without pymeshlab (issue 14): the optional extra ``lamina-host[meshlab]``.

Each test runs ``lamina`` in a fresh process where ``import pymeshlab`` fails, as on a
system that cannot install it (glibc older than 2.35, no GL libraries).
"""

from __future__ import annotations

import json
import sqlite3
import subprocess
import sys
from collections.abc import Callable
from contextlib import closing
from pathlib import Path

import numpy as np

from lamina_host.reconstruct.mesh import load_ply, stl_triangles

# sys.modules[name] = None makes every later `import name` raise ImportError.
HIDDEN = (
    "import sys; sys.modules['pymeshlab'] = None; "
    "from lamina_host.cli import main; sys.exit(main(sys.argv[1:]))"
)


def lamina_without_meshlab(*args: str) -> subprocess.CompletedProcess[str]:
    """Run the host command line with pymeshlab impossible to import."""
    return subprocess.run(
        [sys.executable, "-c", HIDDEN, *args], capture_output=True, text=True, timeout=300
    )


def test_scan_with_default_mesh_and_exports_need_no_meshlab(tmp_path: Path) -> None:
    """A whole simulated scan, its contour mesh, accuracy and every mesh export."""
    library = str(tmp_path / "library.sqlite")
    out = tmp_path / "cyl"
    done = lamina_without_meshlab(
        "scan", "--device", "sim", "--object", "cylinder:d=19.05", "--sections", "2",
        "--views", "8", "--expect", "cylinder:d=19.05", "--library", library, "-o", str(out),
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    report = json.loads((out / "report.json").read_text())
    for row in report["accuracy"]["rows"]:
        assert row["rms_mean_mm"] <= 0.03, row  # issue 5's target, as with pymeshlab
    assert report["mesh"]["topology"]["watertight"]
    assert report["mesh"]["topology"]["two_manifold"]
    vertices, faces = load_ply((out / "mesh.ply").read_bytes())
    centred = vertices[:, :2] - vertices[:, :2].mean(axis=0)
    radius = np.hypot(centred[:, 0], centred[:, 1])
    assert abs(np.median(radius) - 19.05 / 2) < 0.05

    for name in ("m.obj", "m.stl", "m.ply", "r.json"):
        target = str(tmp_path / name)
        done = lamina_without_meshlab("export", "1", "--library", library, "-o", target)
        assert done.returncode == 0, done.stderr
    triangles = vertices.astype(np.float32)[faces]
    assert np.array_equal(stl_triangles((tmp_path / "m.stl").read_bytes()), triangles)
    obj_lines = (tmp_path / "m.obj").read_text().splitlines()
    assert sum(line.startswith("v ") for line in obj_lines) == len(vertices)
    assert sum(line.startswith("f ") for line in obj_lines) == len(faces)


def test_ball_pivoting_and_poisson_name_the_extra(
    tmp_path: Path, refusal: Callable[[subprocess.CompletedProcess[str]], str]
) -> None:
    """One line naming the extra, non-zero exit, refused before anything is scanned."""
    library = tmp_path / "library.sqlite"
    for method in ("ball-pivoting", "poisson"):
        done = lamina_without_meshlab(
            "scan", "--device", "sim", "--sections", "1", "--views", "4", "--mesh", method,
            "--library", str(library), "-o", str(tmp_path / method),
        )  # fmt: skip
        line = refusal(done)
        assert f"--mesh {method}" in line and "pip install 'lamina-host[meshlab]'" in line
        assert not (tmp_path / method).exists()
    if library.exists():  # opened, perhaps, but no scan was created
        with closing(sqlite3.connect(library)) as db:
            assert db.execute("SELECT COUNT(*) FROM scans").fetchone() == (0,)
