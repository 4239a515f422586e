"""One random shape scanned through the product path and judged against the truth.

The random-shape campaign (issue 18) of ``tests/test_random_shapes.py`` and
``tests/benchmarks/bench_campaign.py``: the simulated device (``open_sim``: renderer,
mechanics, stripe extraction via :func:`lamina_device.acquisition.acquire`) acquires the
calibration board, the cylinder and the object; the host reconstructs
(:func:`lamina_host.reconstruct.pipeline.reconstruct`), builds ``report.json`` and writes the output
files. Only the link between them is left out (it has its own tests and bench), and the
board and cylinder frames, which do not depend on the object, are acquired once per
process and rig. Every exception is caught and named by the stage it came from, so a
campaign counts crashes instead of stopping at the first.
"""

from __future__ import annotations

import math
import tempfile
import time
import traceback
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from lamina_device.acquisition import acquire, grab_grid, row_turn_deg
from lamina_device.config import DeviceConfig, load_config, next_turn_frame_us
from lamina_device.hardware import Hardware
from lamina_device.sim import Mechanics, NoiseModel, Rig, SimScene, open_sim
from lamina_device.sim.axes import SimTurntable
from lamina_device.sim.backend import DEFAULT_CYLINDER_PLAN
from lamina_device.sim.objects import section_curves
from lamina_device.sim.random_shapes import RandomShape, ShapeFeatures, random_shape
from lamina_device.sim.truth import (
    TrueSurface,
    lit_and_seen_points,
    scan_accuracy,
    segment_views,
)
from lamina_host.reconstruct.axis import AxisCalibration
from lamina_host.reconstruct.continuity import outline_jumps
from lamina_host.reconstruct.measure import polygon_area
from lamina_host.reconstruct.pipeline import (
    ProcessOptions,
    Reconstruction,
    calibrate_rig,
    reconstruct,
)
from lamina_host.store.outputs import build_report, measured_cloud, write_outputs
from lamina_shared.errors import LaminaError
from lamina_shared.types import ScanPlan, Segment

NOISE = "harsh"

FINE_RELIEF_SIGMAS = 13.7
"""Relief of a wavelength under this many laser-sheet sigmas is finer than the sheet
resolves: a Gaussian sheet of sigma s passes exp(-2 pi^2 s^2 / L^2) of a relief of
wavelength L running up the object, under 90 % below 13.7 s (6.9 mm for the limb rig's
0.5 mm sheet, 2.2 mm for the thesis rig's 0.16 mm). The stripe then lies on the sheet's
average of the surface, not on the surface at its centre, whatever the software does."""

SHAPE_GROUPS = ("smooth", "relief", "fine relief", "wide")
"""The kinds of shape the campaign's figures are also given for (``shape_group``)."""


def shape_group(features: ShapeFeatures | None, sheet_sigma_mm: float) -> str:
    """Return which of ``SHAPE_GROUPS`` a random shape belongs to (the first that fits).

    Args:
        features: the shape's features (None: a designed shape, taken as smooth).
        sheet_sigma_mm: the rig's laser-sheet sigma (``Rig.laser_sigma_mm``).

    Returns:
        "wide" (parts beyond what every view sees), "fine relief" (relief finer than the
        sheet resolves, ``FINE_RELIEF_SIGMAS``), "relief" or "smooth".
    """
    if features is None:
        return "smooth"
    if features.wide:
        return "wide"
    if not features.relief_mm:
        return "smooth"
    fine = features.relief_wavelength_mm < FINE_RELIEF_SIGMAS * sheet_sigma_mm
    return "fine relief" if fine else "relief"


@dataclass(frozen=True)
class CampaignPlan:
    """How each seed is scanned: the rig, the plan and the noise preset."""

    scale: str  # "thesis" or "limb": the shape's scale and the rig preset
    sections: int
    pitch_mm: float
    views: int
    noise: str = NOISE
    resolution: float = 1.0  # < 1: the preset rig's camera binned down (fast tests)
    mode: str = "stop-and-go"
    off_frames: str = "interleaved"  # a continuous scan's laser-off frames (the box's config)
    counts_turns: bool = True
    """False: the host as it was before issue 22's mend, each view's whole turns dropped, so
    the gear's shortfall is corrected within the turn only (the gear bench's comparison)."""
    gear_ratio_factor: float = 1.0
    """The box's ``[turntable] gear_ratio`` times this, its pulleys the shipped ones
    (:meth:`Mechanics.on_box`): the factor a calibration names
    (:func:`lamina_host.reconstruct.axis.gear_ratio_factor`) takes the table's shortfall
    out. The calibration cylinder is scanned on the same box."""

    def rig(self) -> Rig:
        """Return the rig: the preset, its image and focal length scaled by ``resolution``."""
        rig = Rig.preset(self.scale)
        if self.resolution == 1.0:
            return rig
        w, h = rig.image_size
        size = (round(w * self.resolution), round(h * self.resolution))
        return replace(rig, image_size=size, focal_px=rig.focal_px * self.resolution)

    def scan_plan(self) -> ScanPlan:
        """Return the object's scan plan."""
        return ScanPlan.regular(self.sections, self.pitch_mm, self.views, self.mode)

    def box(self, hardware: Hardware, object_scan: bool = True) -> Hardware:
        """Return the simulated ``hardware`` configured as this plan's box: its gear ratio
        (:attr:`gear_ratio_factor`) and, for the object's scan, its laser-off frames (a
        turn later: :func:`next_turn_config`)."""
        turntable = hardware.turntable
        assert isinstance(turntable, SimTurntable)
        config = self.geared(turntable.clock.config)
        if object_scan and self.off_frames == "next-turn":
            config = next_turn_config(config)
        if config is not turntable.clock.config:
            shipped = turntable.clock.config.turntable.gear_ratio
            turntable.clock.config = hardware.timing = config
            turntable.mechanics = turntable.mechanics.on_box(config.turntable, shipped)
        return hardware

    def geared(self, config: DeviceConfig) -> DeviceConfig:
        """Return ``config`` with its turntable's gear ratio times :attr:`gear_ratio_factor`."""
        if self.gear_ratio_factor == 1.0:
            return config
        ratio = config.turntable.gear_ratio * self.gear_ratio_factor
        return replace(config, turntable=replace(config.turntable, gear_ratio=ratio))

    def mechanics(self) -> Mechanics:
        """Return the simulated axes' errors on this plan's box (its gear ratio's shortfall)."""
        shipped = load_config()
        mechanics = Mechanics.preset(self.noise)
        return mechanics.on_box(self.geared(shipped).turntable, shipped.turntable.gear_ratio)

    def as_counted(self, segments: list[Segment]) -> list[Segment]:
        """Return ``segments`` as this plan's host takes them: whole turns and all, or,
        without ``counts_turns``, with them dropped."""
        return segments if self.counts_turns else [replace(s, turns=0) for s in segments]


def next_turn_config(config: DeviceConfig) -> DeviceConfig:
    """Return ``config`` taking continuous laser-off frames a turn later, with the frame
    period nearest its own that a turn divides (``config.next_turn_frame_us``)."""
    table = replace(config.turntable, continuous_off_frames="next-turn")
    frame_us = next_turn_frame_us(table, config.camera.frame_duration_us)
    camera = replace(config.camera, frame_duration_us=frame_us)
    return replace(config, turntable=table, camera=camera)


@dataclass(frozen=True)
class OutlineCheck:
    """One outline the host reported, against the true surface (aligned frame, mm)."""

    section: int
    part: int
    status: str
    measured_samples: int  # contour samples not flagged estimated
    p95_measured_mm: float  # 95th percentile distance of those samples to the truth
    p95_raw_mm: float  # of the outline's measured (raw) points


@dataclass
class SeedResult:
    """What one seed's scan gave: figures, or the stage and exception it failed with."""

    seed: int
    scale: str
    features: str = ""
    group: str = ""  # one of SHAPE_GROUPS
    closed_shape: bool = False
    stage: str = ""  # where it failed; empty when it finished
    error_type: str = ""  # exception class; "LaminaError" subclasses are honest refusals
    error: str = ""  # the message (one line)
    refusal: bool = False  # a LaminaError: the user got one line, not a traceback
    trace: str = ""  # the last frames of a crash's traceback
    mean_distance_mm: float = math.nan  # points.ply to the truth, aligned
    coverage: float = math.nan  # lit-and-seen surface within 0.25 mm of points.ply
    lit_points: int = 0
    volume_error_percent: float = math.nan  # closed shapes with every section closed
    statuses: dict[str, int] = field(default_factory=dict)
    outlines: list[OutlineCheck] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    internal_errors: list[str] = field(default_factory=list)
    """Reasons of outlines failed by a bug, not by Lamina's own refusal: each is a
    traceback the product caught (the outline marked failed, the rest processed)."""
    motion_warnings: list[str] = field(default_factory=list)
    """The outlines the report warns of as if the subject had moved (its views apart, or
    standing off its neighbours' line): the shapes hold still, so each is a false alarm."""
    wall_s: float = 0.0

    @property
    def crashed(self) -> bool:
        """Return True when the scan ended in an exception that is not an honest refusal."""
        return bool(self.stage) and not self.refusal

    @property
    def failure_kind(self) -> str:
        """Return ``ExceptionType@stage`` (empty when it finished)."""
        return f"{self.error_type}@{self.stage}" if self.stage else ""


@dataclass
class _Calibration:
    """The board image and cylinder segments of one rig (they do not depend on the object)."""

    grid_image: np.ndarray
    cylinder: list[Segment]


# Per process (frames are pure): by scale, resolution, noise and gear ratio factor.
_CALIBRATIONS: dict[tuple[str, float, str, float], _Calibration] = {}


def _calibration(plan: CampaignPlan) -> _Calibration:
    """Return the rig's board and cylinder data, acquiring them on first use."""
    key = (plan.scale, plan.resolution, plan.noise, plan.gear_ratio_factor)
    if key not in _CALIBRATIONS:
        hardware = plan.box(open_sim(None, 0, plan.noise, plan.scale, plan.rig()), False)
        cylinder: list[Segment] = []
        try:
            grid = grab_grid(hardware)
            acquire(hardware, "cylinder", DEFAULT_CYLINDER_PLAN, cylinder.append)
        finally:
            hardware.close()
        _CALIBRATIONS[key] = _Calibration(grid, cylinder)
    return _CALIBRATIONS[key]


def calibrated_axis(plan: CampaignPlan) -> AxisCalibration:
    """Return the host's turntable calibration of ``plan``'s box, as :func:`reconstruct`
    makes it with the default options from the board and cylinder it scans first.

    Args:
        plan: the rig, noise and box (its gear ratio).

    Returns:
        The axis, with the gear's angle scale the cylinder measured.
    """
    calibration, rig = _calibration(plan), plan.rig()
    assert rig.board is not None
    cylinder = plan.as_counted(calibration.cylinder)
    _, axis, _ = calibrate_rig(
        calibration.grid_image, rig.board, cylinder, rig.cylinder_diameter_mm,
        ProcessOptions(), rig.lift_reference(),
    )  # fmt: skip
    return axis


def _fail(result: SeedResult, stage: str, exc: BaseException) -> SeedResult:
    """Record a failure of ``stage`` on ``result``."""
    result.stage = stage
    result.error_type = type(exc).__name__
    result.error = (str(exc).strip().splitlines() or [""])[0][:300]
    result.refusal = isinstance(exc, LaminaError)
    frames = traceback.extract_tb(exc.__traceback__)[-3:]
    result.trace = " <- ".join(
        f"{Path(f.filename).name}:{f.lineno} {f.name}" for f in reversed(frames)
    )
    return result


def scan_seed(seed: int, plan: CampaignPlan) -> SeedResult:
    """Scan random shape ``seed`` along ``plan`` and measure it; never raises.

    Args:
        seed: the shape's seed (``--object random:seed=N,scale=...`` replays it).
        plan: the rig, plan and noise.

    Returns:
        The figures, or the stage and exception the scan failed with.
    """
    start = time.perf_counter()
    result = SeedResult(seed, plan.scale)
    stage = "generate"
    try:
        shape = random_shape(seed, plan.scale)
        result.group = shape_group(shape.features, plan.rig().laser_sigma_mm)
        if shape.features is not None:
            result.features = shape.features.summary()
            result.closed_shape = shape.features.closed
        stage = "calibration-acquire"
        calibration = _calibration(plan)
        stage = "acquire"
        spec = f"random:seed={seed},scale={plan.scale}"
        hardware = plan.box(open_sim(spec, 0, plan.noise, plan.scale, plan.rig()))
        segments: list[Segment] = []
        object_plan = plan.scan_plan()
        try:
            acquire(hardware, "object", object_plan, segments.append)
        finally:
            hardware.close()
        stage = "process"
        assert hardware.board is not None and hardware.cylinder_diameter_mm is not None
        recon = reconstruct(
            calibration.grid_image,
            hardware.board,
            plan.as_counted(calibration.cylinder),
            hardware.cylinder_diameter_mm,
            plan.as_counted(segments),
            ProcessOptions(),
            row_turn_deg=row_turn_deg(hardware) if object_plan.continuous else 0.0,
            laser_off_turn_later=object_plan.continuous and plan.off_frames == "next-turn",
        )
        # Outlines and meshes the product caught failing by a bug: tracebacks all the same.
        caught = [f.reason for f in recon.failed] + [
            w for w in recon.warnings if w.startswith("the ") and "could not be built" in w
        ]
        result.internal_errors = [c for c in caught if "internal error (" in c]
        stage = "report"
        report = build_report(recon, {"kind": "sim"}, segments, None, {})
        with tempfile.TemporaryDirectory() as tmp:
            write_outputs(Path(tmp), recon, report)
        stage = "measure"
        _measure(result, shape, recon, plan, segments)
    except Exception as exc:
        _fail(result, stage, exc)
    result.wall_s = time.perf_counter() - start
    return result


def motion_warnings(recon: Reconstruction) -> list[str]:
    """Return the outlines a scan's report warns of as moved, each with its figure.

    Args:
        recon: the processed scan.

    Returns:
        ``"S.P views X mm apart"`` for each outline whose views stand apart beyond the
        warning, and ``"S.P Y mm off its neighbours"`` for each flagged section jump.
    """
    apart = [
        f"{s.index}.{s.part} views {s.views_apart_mm:.2f} mm apart"
        for s in recon.sections
        if s.views_moved
    ]
    jumps = [
        f"{j.index}.{j.part} {j.jump_mm:.2f} mm off its neighbours"
        for j in outline_jumps(recon.sections)
        if j.flagged
    ]
    return apart + jumps


def _measure(
    result: SeedResult,
    shape: RandomShape,
    recon: Reconstruction,
    plan: CampaignPlan,
    segments: list[Segment],
) -> None:
    """Fill in the figures of a finished scan against the truth (the surface its
    ``segments`` lit, each where the simulated gear put the object)."""
    result.warnings = list(recon.warnings)
    result.motion_warnings = motion_warnings(recon)
    for s in recon.sections:
        result.statuses[s.status] = result.statuses.get(s.status, 0) + 1
    rig = plan.rig()
    scene = SimScene(rig, shape, NoiseModel.preset(plan.noise))
    mechanics = plan.mechanics()
    lit = lit_and_seen_points(scene, segment_views(segments), mechanics)
    result.lit_points = len(lit)
    contour, _ = measured_cloud(recon)
    raw = (
        np.vstack([np.column_stack([s.raw, np.full(len(s.raw), s.z_mm)]) for s in recon.sections])
        if recon.sections
        else np.empty((0, 3))
    )
    if len(contour) and len(lit):
        acc = scan_accuracy(shape, raw, contour, lit)
        result.mean_distance_mm = acc.aligned.mean_distance_mm
        result.coverage = acc.aligned.coverage_percent / 100.0
        alignment = acc.alignment
    elif len(lit):
        result.coverage = 0.0
        alignment = None
    else:
        alignment = None
    surface = TrueSurface(shape)
    for s in recon.sections:
        keep = np.ones(len(s.contour), bool) if s.estimated is None else ~s.estimated
        pts = np.column_stack([s.contour[keep], np.full(int(keep.sum()), s.z_mm)])
        rpts = np.column_stack([s.raw, np.full(len(s.raw), s.z_mm)])
        if alignment is not None:
            pts, rpts = alignment.apply(pts), alignment.apply(rpts)
        d = surface.distance_mm(pts)
        dr = surface.distance_mm(rpts)
        result.outlines.append(
            OutlineCheck(
                s.index,
                s.part,
                s.status,
                len(pts),
                float(np.percentile(d, 95)) if len(d) else 0.0,
                float(np.percentile(dr, 95)) if len(dr) else 0.0,
            )
        )
    result.volume_error_percent = _volume_error(shape, recon, mechanics)


def _volume_error(shape: RandomShape, recon: Reconstruction, mechanics: Mechanics) -> float:
    """Return the contour stack's volume error in %, NaN unless shape and scan are closed.

    Both stacks integrate (trapezoid) over the sections' TRUE heights, the measured areas
    against the true ones, so the lift's scale error is left out and what remains is the
    host's own error in the sections' areas.
    """
    if shape.features is None or not shape.features.closed:
        return math.nan
    by_index: dict[int, list[float]] = {}
    heights: dict[int, float] = {}
    for s in recon.sections:
        if not s.closed:
            return math.nan
        by_index.setdefault(s.index, []).append(polygon_area(s.contour))
        heights[s.index] = s.z_mm
    if len(by_index) < 2:
        return math.nan
    order = sorted(by_index)
    z = np.array([mechanics.true_z_mm(heights[k]) for k in order])
    measured = np.array([sum(by_index[k]) for k in order])
    true = np.array(
        [sum(polygon_area(c.points) for c in section_curves(shape, float(v))) for v in z]
    )
    truth = float(np.trapezoid(true, z))
    if truth <= 0.0:
        return math.nan
    return 100.0 * (float(np.trapezoid(measured, z)) - truth) / truth
