"""Host processing speed and accuracy of a 100-section, 16-view scan, thesis vs Lamina methods.

The segments are synthetic but honest: a tapered, lobed outline (a forearm-like section,
known exactly) is turned to each view's angle on the simulated rig, the arc the camera
sees and the laser reaches is projected through the rig's camera, sampled once per image
column with 0.3 px of stripe-centre noise, and handed over as device segments. The
calibration image is the simulator's rendered board. Timed: everything the host does
after acquisition (grid calibration, axis, assembly, EFD, and the contour mesh with its
topology check), best of 3 runs; ball pivoting is excluded, as the issue asks.
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Any

import numpy as np

from lamina_device.sim import Rig, SimScene
from lamina_host.reconstruct.measure import RadiusModel, centroid, radial_error_table
from lamina_host.reconstruct.pipeline import ProcessOptions, reconstruct
from tests.helpers.shapes import circle, view_segment

TITLE = "host processing of a 100-section x 16-view scan (synthetic segments), <= 2 s target"
SECTIONS, VIEWS, PITCH_MM = 100, 16, 2.0
ROW_NOISE_PX = 0.3


def radius_mm(phi: np.ndarray, z_mm: float, scale_mm: float) -> np.ndarray:
    """The true outline: a tapered, slightly oval and lobed section (a forearm, scaled)."""
    taper = 1.0 - 0.25 * z_mm / (SECTIONS * PITCH_MM)
    return scale_mm * taper * (1.0 + 0.08 * np.cos(2.0 * phi) + 0.03 * np.sin(3.0 * phi + 0.4))


def radius_about_centroid(scale_mm: float) -> RadiusModel:
    """The true outline's radius about its own area centroid, which the table centres on.

    ``radius_mm`` is a radius about the axis, but the lobes put the outline's centroid
    0.0024 x scale off it (0.13 mm at limb scale): measured about the centroid against
    radii about the axis, the exact outline itself scores 0.097 mm RMS at limb scale,
    0.018 mm at thesis scale, and that was the error this benchmark reported.
    """
    phi = np.linspace(0.0, 2.0 * np.pi, 20000, endpoint=False)
    outline = radius_mm(phi, 0.0, scale_mm)[:, None] * np.stack([np.cos(phi), np.sin(phi)], 1)
    rel = outline - centroid(outline)
    psi, rho = np.arctan2(rel[:, 1], rel[:, 0]), np.hypot(rel[:, 0], rel[:, 1])
    order = np.argsort(psi)
    psi, rho = psi[order], rho[order]

    def model(angle: np.ndarray, z_mm: float) -> np.ndarray:
        # The taper scales the whole section about the axis, its centroid included.
        taper = radius_mm(np.zeros(1), z_mm, 1.0)[0] / radius_mm(np.zeros(1), 0.0, 1.0)[0]
        return taper * np.interp(angle, psi, rho, period=2.0 * np.pi)

    return model


def synthetic_scan(
    rig: Rig, scale_mm: float, seed: int = 0, sections: int = SECTIONS, views: int = VIEWS
) -> dict[str, Any]:
    """Return the board image, cylinder segments and object segments of one scan."""
    rng = np.random.default_rng(seed)
    phi = np.linspace(0.0, 2.0 * np.pi, 4000, endpoint=False)
    unit = np.stack([np.cos(phi), np.sin(phi)], axis=1)
    cyl = circle(rig.cylinder_offset_mm, rig.cylinder_diameter_mm / 2.0)
    seen = (view_segment(rig, "cylinder", 0, v, 0.0, 45.0 * v, 45.0 * v, cyl, rng, ROW_NOISE_PX)
            for v in range(8))  # fmt: skip
    cylinder = [s for s in seen if s is not None]
    segments = []
    for k in range(sections):
        z = k * PITCH_MM
        outline = radius_mm(phi, z, scale_mm)[:, None] * unit
        for v in range(views):
            angle = 360.0 * v / views
            s = view_segment(rig, "object", k, v, z, angle, angle, outline, rng, ROW_NOISE_PX)
            if s is not None:
                segments.append(s)
    grid = SimScene(rig).render("grid", 0.0, 0.0, False)
    return {"grid": grid, "board": rig.board, "cylinder": cylinder,
            "cylinder_mm": rig.cylinder_diameter_mm, "segments": segments}  # fmt: skip


def timed(scan: dict[str, Any], options: ProcessOptions, scale_mm: float) -> dict[str, Any]:
    """Reconstruct three times; return the best wall time, its stage timings and accuracy."""
    best: dict[str, Any] = {"total_s": np.inf}
    for _ in range(3):
        start = time.perf_counter()
        result = reconstruct(scan["grid"], scan["board"], scan["cylinder"], scan["cylinder_mm"],
                             scan["segments"], options)  # fmt: skip
        total = time.perf_counter() - start
        if total < best["total_s"]:
            best = {"total_s": total, "stages_s": result.timings_s, "result": result}
    result = best.pop("result")
    main = [s for s in result.sections if s.part == 0]
    table = radial_error_table(
        {s.index: s.contour for s in main}, {s.index: s.z_mm for s in main},
        radius_about_centroid(scale_mm),
    )  # fmt: skip
    best.update(
        mean_rms_mm=table.mean_mean_mm,
        max_rms_mm=table.max_mean_mm,
        points=int(sum(len(s) for s in scan["segments"])),
        topology=result.mesh_topology.to_dict() if result.mesh_topology else {},
    )
    return best


def run() -> dict[str, Any]:
    """Time the Lamina and thesis method sets at thesis and limb scale."""
    out: dict[str, Any] = {}
    for rig_name, rig, scale in (("thesis", Rig(), 10.0), ("limb", Rig.limb(), 55.0)):
        scan = synthetic_scan(rig, scale)
        # The thesis' methods, but its ball pivoting swapped for the contour mesh (excluded).
        thesis = replace(ProcessOptions.thesis(), mesh="contours")
        out[rig_name] = {
            "lamina": timed(scan, ProcessOptions(), scale),
            "thesis methods": timed(scan, thesis, scale),
        }
    return out


def report(results: dict[str, Any]) -> list[str]:
    """Return the table lines."""
    lines = ["  rig     methods          points   total s  mean/max RMS mm  watertight  stages s"]
    for rig_name, rows in results.items():
        for name, row in rows.items():
            stages = ", ".join(f"{k} {v:.2f}" for k, v in row["stages_s"].items())
            topo = row["topology"]
            closed = topo.get("watertight", False) and topo.get("two_manifold", False)
            lines.append(
                f"  {rig_name:<7} {name:<15} {row['points']:>7} {row['total_s']:9.2f}  "
                f"{row['mean_rms_mm']:.4f}/{row['max_rms_mm']:.4f}  {closed!s:>10}  {stages}"
            )
    return lines
