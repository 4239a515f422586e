"""Turntable axis and scale correction from a calibration cylinder (thesis 6.2).

Two methods (``AXIS_METHODS``):

- ``"joint"`` (default): one circle fitted to all the cylinder's arcs at once in the
  object frame: every point ``p`` seen at turntable angle ``theta`` must satisfy
  ``|Rz(-theta)(p - a) - c| = r`` with the axis ``a``, the radius ``r`` and the cylinder's
  offset ``c`` from the axis unknown (and optionally a turntable angle scale, since the
  thesis measured about 0.2 degrees undershoot per 45 degree step, section 8.3). It
  uses every point with its known angle, so it needs neither evenly spread views nor
  a centred cylinder.
- ``"centroid"``: the thesis' method. A circle is fitted to every arc (6.2.1) and the
  axis is the centroid of the arc centres (6.2.2).

The centroid method's correction factor is ``C_f = D_a / D_e`` (6.2.4, eq. 6.3). The joint
fit can instead hold the radius at the known ``D_a / 2`` (``fit_radius=False``, what the
pipeline does): the camera and the laser see every arc from the same side, so a free
radius trades almost one for one against the axis position along that side, and only
the arcs' curvature separates them. At limb scale (0.2 mm/px, 0.5 mm sheet) stripe noise
moves both by ~0.1 mm; ``C_f`` then turns that radius offset into a scale, which cancels
on an object the size of the cylinder (the thesis' set-up) but not on a larger one
(a 120 mm object scanned with a 60 mm cylinder read 0.14 mm too large, ``C_f`` 1.0043).
With the radius known the axis is pinned by the arcs' positions and the board alone
sets the scale. Either way a warning is given when the measured diameter is more than
5 % from the true one.
The joint fit can go on to one angle offset per view (``fit_view_offsets``): the
cylinder is scanned at the object's view angles, so a repeatable gear error (runout, an
eccentric gear) is measured where it acts. This is Lamina's extension; the thesis has one
correction factor.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, overload

import numpy as np
from scipy.optimize import least_squares

from lamina_host.reconstruct.calibration import CalibrationError
from lamina_shared.types import NEXT_TURN_MISMATCH_DEG

CF_WARNING = 0.05
"""Thesis 6.2.4: warn when the correction factor differs from 1 by more than 5 %."""

SCALE_SIGMAS = 3.0
"""A fitted turntable scale within this many standard errors of 1 is held at exactly 1."""

MIN_OFFSET_FOR_SCALE_MM = 0.5
"""The angle scale is only estimated from a cylinder at least this far off the axis."""

MAX_VIEW_OFFSET_SD_DEG = 0.03
"""Per-view turntable angles are used only when the cylinder measures them this well
(median standard error); worse, they would add more error than a 0.15 deg runout. The
standard error treats every stripe point as independent and so understates the offsets'
error: at 0.045 deg (the thesis rig's cylinder at three heights, 0.02 deg runout) they
made an ellipsoid's outlines worse, 0.0111 against 0.0084 mm RMS over five seeds."""

RADIUS_SPREAD_WARNING = 0.02
"""Fitted arc radii that differ by more than 2 % between views suggest bad arcs."""


@dataclass(frozen=True)
class Circle:
    """A fitted circle in mm with the RMS orthogonal distance of its points."""

    cx: float
    cy: float
    r: float
    rms_mm: float


AXIS_METHODS = ("joint", "centroid")
"""Selectable axis methods; the first is the default."""


@dataclass(frozen=True, eq=False)
class AxisCalibration:
    """Turntable axis, scale correction and the per-arc circles they came from.

    ``angle_scale`` maps a turntable step count to the true angle (1.0 unless the joint
    fit estimated it, to about ``angle_scale_sd``), ``angle_wave_deg`` the sine and
    cosine amplitudes of a once-per-turn error on top (:func:`_gear_rad`);
    ``cylinder_offset_mm`` is the cylinder's centre in the object
    frame (joint fit only); ``rms_mm`` is the joint fit's RMS orthogonal residual.
    ``view_offsets_deg`` (per-view fit only) holds one row per calibrated view, its
    commanded angle and its true-minus-commanded offset, measured to about
    ``view_offset_sd_deg`` (standard error); ``view_offsets_note`` says why they are
    missing when the fit was asked for but the cylinder could not measure them well.
    """

    axis_xy_mm: tuple[float, float]
    correction_factor: float
    estimated_diameter_mm: float
    actual_diameter_mm: float
    arc_centres_mm: np.ndarray
    arc_radii_mm: np.ndarray
    warnings: tuple[str, ...]
    method: str = "centroid"
    angle_scale: float = 1.0
    angle_scale_sd: float = float("nan")
    angle_wave_deg: tuple[float, float] = (0.0, 0.0)
    cylinder_offset_mm: tuple[float, float] | None = None
    rms_mm: float = float("nan")
    view_offsets_deg: np.ndarray | None = None
    view_offset_sd_deg: float = float("nan")
    view_offsets_note: str = ""

    @overload
    def true_angle_deg(self, commanded_deg: float) -> float: ...

    @overload
    def true_angle_deg(self, commanded_deg: np.ndarray) -> np.ndarray: ...

    def true_angle_deg(self, commanded_deg: float | np.ndarray) -> float | np.ndarray:
        """Return the turntable angle the object was really at for a commanded angle.

        The commanded angle is the step count (a view's angle plus its whole turns,
        counted from the scan's first turn): a table that turns short of its count falls
        ``1 - scale`` further behind with every degree, over the turns as within them.
        With per-view offsets (``view_offsets_deg`` rows: commanded count, true minus
        commanded), the angle is ``scale x commanded`` plus the periodic remainder of the
        offsets, interpolated round the turn: exactly the fitted offset at a calibrated
        count, and a repeatable gear error, a function of the angle within the turn, in
        between and on later turns (a continuous view's rows either side of a whole turn
        are each taken on their own side).

        Args:
            commanded_deg: one view's step count in degrees, or an array of them (a
                continuous view's rows, each at its own).

        Returns:
            The true angle, or an array of them.
        """
        base = self._geared_deg(commanded_deg)
        if self.view_offsets_deg is None:
            return base
        cmd, offset = self.view_offsets_deg.T
        periodic = offset - (self._geared_deg(cmd) - cmd)
        remainder = np.interp(np.mod(commanded_deg, 360.0), cmd % 360.0, periodic, period=360.0)
        if isinstance(commanded_deg, np.ndarray):
            return base + remainder
        return base + float(remainder)

    @overload
    def _geared_deg(self, count_deg: float) -> float: ...

    @overload
    def _geared_deg(self, count_deg: np.ndarray) -> np.ndarray: ...

    def _geared_deg(self, count_deg: float | np.ndarray) -> float | np.ndarray:
        """Return the fitted gear's true angle of a step count (degrees), offsets aside."""
        gear = np.array([self.angle_scale, *np.deg2rad(self.angle_wave_deg)])
        true = np.rad2deg(_gear_rad(np.deg2rad(count_deg), gear))
        return true if isinstance(count_deg, np.ndarray) else float(true)

    def to_dict(self) -> dict[str, Any]:
        """Return a JSON-ready summary."""
        return {
            "method": self.method,
            "angle_scale": self.angle_scale,
            "undershoot_deg_per_45": 45.0 * (1.0 - self.angle_scale),
            "angle_scale_sd": self.angle_scale_sd,
            "gear_ratio_factor": gear_ratio_factor(self),
            "angle_wave_deg": list(self.angle_wave_deg),
            "cylinder_offset_mm": (
                list(self.cylinder_offset_mm) if self.cylinder_offset_mm is not None else None
            ),
            "rms_mm": self.rms_mm,
            "view_offset_sd_deg": self.view_offset_sd_deg,
            "view_offsets_note": self.view_offsets_note,
            "view_offsets_deg": (
                self.view_offsets_deg.tolist() if self.view_offsets_deg is not None else None
            ),
            "axis_xy_mm": list(self.axis_xy_mm),
            "correction_factor": self.correction_factor,
            "estimated_diameter_mm": self.estimated_diameter_mm,
            "actual_diameter_mm": self.actual_diameter_mm,
            "arc_centres_mm": self.arc_centres_mm.tolist(),
            "arc_radii_mm": self.arc_radii_mm.tolist(),
            "warnings": list(self.warnings),
        }


def taubin_circle(pts: np.ndarray) -> tuple[float, float, float]:
    """Taubin's algebraic circle fit (SVD form); nearly unbiased on short arcs, unlike Kasa.

    Returns:
        (cx, cy, r) in the units of ``pts``.
    """
    pts = np.asarray(pts, dtype=float).reshape(-1, 2)
    if len(pts) < 3:
        raise CalibrationError(
            f"a circle needs at least 3 arc points, got {len(pts)}; check the arc data"
        )
    mean = pts.mean(axis=0)
    x, y = (pts - mean).T
    z = x * x + y * y
    z_mean = z.mean()
    if not z_mean > 0.0:  # also NaN: points not finite
        raise CalibrationError("all arc points coincide; no circle can be fitted to this arc")
    z0 = (z - z_mean) / (2.0 * np.sqrt(z_mean))
    _, _, vt = np.linalg.svd(np.stack([z0, x, y], axis=1), full_matrices=False)
    a = vt[2].copy()
    a[0] /= 2.0 * np.sqrt(z_mean)
    a0, a1, a2 = a
    a3 = -z_mean * a0
    if abs(a0) < 1e-12 * max(abs(a1), abs(a2), 1e-300):
        raise CalibrationError(
            "arc points lie on a straight line; no circle can be fitted (check the arc data)"
        )
    cx = -a1 / (2.0 * a0) + mean[0]
    cy = -a2 / (2.0 * a0) + mean[1]
    r = np.sqrt(a1 * a1 + a2 * a2 - 4.0 * a0 * a3) / (2.0 * abs(a0))
    return float(cx), float(cy), float(r)


def fit_circle(points: np.ndarray) -> Circle:
    """Fit a circle by orthogonal distance, started from Taubin's algebraic fit (thesis 6.2.1).

    The thesis refines an initial fit iteratively until the mean squared error stops
    changing; here Levenberg-Marquardt on the orthogonal distances ``|p - c| - r`` runs to
    convergence from the Taubin estimate.

    Args:
        points: (K, 2) points in mm, K >= 3.

    Returns:
        The best-fit Circle.

    Raises:
        CalibrationError: fewer than 3 points, non-finite values, or collinear points.
    """
    pts = np.asarray(points, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 2 or len(pts) < 3:
        raise CalibrationError(
            f"a circle fit needs at least 3 points in a (K, 2) array, got shape {pts.shape}; "
            "check the arc was extracted"
        )
    if not np.isfinite(pts).all():
        raise CalibrationError("arc points contain NaN or infinity; re-extract the arc")
    cx0, cy0, r0 = taubin_circle(pts)

    def residuals(p: np.ndarray) -> np.ndarray:
        return np.hypot(pts[:, 0] - p[0], pts[:, 1] - p[1]) - p[2]

    def jacobian(p: np.ndarray) -> np.ndarray:
        dx, dy = pts[:, 0] - p[0], pts[:, 1] - p[1]
        d = np.maximum(np.hypot(dx, dy), 1e-300)
        return np.stack([-dx / d, -dy / d, -np.ones_like(d)], axis=1)

    sol = least_squares(
        residuals,
        np.array([cx0, cy0, r0]),
        jac=jacobian,
        method="lm",
        xtol=1e-15,
        ftol=1e-15,
        gtol=1e-15,
        max_nfev=500,
    )
    cx, cy, r = sol.x
    rms = float(np.sqrt(np.mean(residuals(sol.x) ** 2)))
    return Circle(float(cx), float(cy), float(abs(r)), rms)


def _check_inputs(arcs: list[np.ndarray], actual_diameter_mm: float) -> None:
    """Raise CalibrationError for a bad diameter or fewer than 3 arcs."""
    if not np.isfinite(actual_diameter_mm) or actual_diameter_mm <= 0:
        raise CalibrationError(
            f"calibration cylinder diameter must be a positive number of mm, not "
            f"{actual_diameter_mm}; fix calibration_cylinder.diameter_mm"
        )
    if len(arcs) < 3:
        raise CalibrationError(
            f"finding the turntable axis needs at least 3 cylinder views, got {len(arcs)}; "
            "capture the cylinder at several evenly spaced angles (the thesis uses 8)"
        )


def _warnings(cf: float, d_est: float, d_true: float, radii: np.ndarray) -> list[str]:
    """Return the 5 % correction-factor warning and the radius-spread warning, as needed."""
    warnings: list[str] = []
    if abs(cf - 1.0) > CF_WARNING:
        warnings.append(
            f"correction factor {cf:.4f} is more than {CF_WARNING:.0%} from 1 (measured "
            f"diameter {d_est:.3f} mm vs {d_true:.3f} mm); check the grid "
            "calibration and the cylinder diameter"
        )
    spread = float((radii.max() - radii.min()) / radii.mean())
    if spread > RADIUS_SPREAD_WARNING:
        warnings.append(
            f"fitted cylinder radii vary by {spread:.1%} between views; check the cylinder "
            "arcs for outliers or a tilted cylinder"
        )
    return warnings


def find_axis(arcs: list[np.ndarray], actual_diameter_mm: float) -> AxisCalibration:
    """Locate the turntable axis and the scale correction from calibration-cylinder arcs.

    Thesis 6.2: one circle per arc (6.2.1); axis = mean of the arc centres (6.2.2), which
    is the axis only when the views are spread evenly round the turn (e.g. 8 x 45 deg);
    ``D_e`` = mean fitted diameter and ``C_f = D_a / D_e`` (6.2.4, eq. 6.3).

    Args:
        arcs: world-frame (K, 2) arcs in mm, one per view, already trimmed.
        actual_diameter_mm: the cylinder's true diameter ``D_a``.

    Returns:
        AxisCalibration, with warnings for ``|C_f - 1| > 5 %`` and for inconsistent radii.

    Raises:
        CalibrationError: fewer than 3 arcs, a bad diameter, or an arc that cannot be fitted.
    """
    _check_inputs(arcs, actual_diameter_mm)
    circles = [fit_circle(arc) for arc in arcs]
    centres = np.array([[c.cx, c.cy] for c in circles])
    radii = np.array([c.r for c in circles])
    axis = centres.mean(axis=0)
    d_est = float(2.0 * radii.mean())
    cf = float(actual_diameter_mm / d_est)
    return AxisCalibration(
        axis_xy_mm=(float(axis[0]), float(axis[1])),
        correction_factor=cf,
        estimated_diameter_mm=d_est,
        actual_diameter_mm=float(actual_diameter_mm),
        arc_centres_mm=centres,
        arc_radii_mm=radii,
        warnings=tuple(_warnings(cf, d_est, actual_diameter_mm, radii)),
        method="centroid",
    )


def _rotate(points: np.ndarray, angle_rad: np.ndarray) -> np.ndarray:
    """Rotate (N, 2) points by per-point angles (counter-clockwise)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    x, y = points[:, 0], points[:, 1]
    return np.stack([c * x - s * y, s * x + c * y], axis=1)


def find_axis_joint(
    arcs: list[np.ndarray],
    angles_deg: list[float],
    actual_diameter_mm: float,
    fit_offset: bool = True,
    fit_angle_scale: bool = False,
    per_view: bool = False,
    fit_radius: bool = True,
) -> AxisCalibration:
    """Fit one circle to all cylinder arcs jointly in the object frame.

    Unknowns: the axis ``a``, the radius ``r``, the cylinder's offset ``c`` from the axis
    (unless ``fit_offset`` is off, i.e. the cylinder is known to be centred) and, with
    ``fit_angle_scale``, a turntable scale ``k`` (true angle = k x commanded). The
    residual of a point ``p`` seen at commanded angle ``theta`` is
    ``|Rz(-k theta)(p - a) - c| - r``, minimised by Levenberg-Marquardt from the thesis'
    estimate (per-arc circles, centroid of centres). ``C_f = D_a / 2r``; with
    ``fit_radius`` off, ``r`` is held at ``D_a / 2`` and ``C_f`` is 1 (the module docstring
    says why), while ``estimated_diameter_mm`` still reports the free fit's ``2r``.

    Args:
        arcs: world-frame (K, 2) arcs in mm, one per view, already trimmed.
        angles_deg: the commanded turntable angle of each arc.
        actual_diameter_mm: the cylinder's true diameter.
        fit_offset: estimate the cylinder's offset from the axis.
        fit_angle_scale: estimate the turntable's angle scale too (needs an off-centre
            cylinder: a centred one looks the same at every angle).
        per_view: with ``fit_angle_scale``, also estimate each view's own angle offset
            (:func:`fit_view_offsets`), so a repeatable gear error is absorbed.
        fit_radius: estimate the radius (and ``C_f`` from it) rather than hold it at the
            known ``D_a / 2``.

    Returns:
        AxisCalibration with method "joint".
    """
    _check_inputs(arcs, actual_diameter_mm)
    if len(angles_deg) != len(arcs):
        raise CalibrationError("give one turntable angle per cylinder arc")
    if not fit_radius:
        free = find_axis_joint(arcs, angles_deg, actual_diameter_mm, fit_offset, fit_angle_scale)
        held = _hold_radius(free, arcs, angles_deg, actual_diameter_mm, fit_offset)
        if fit_angle_scale and per_view and fit_offset:
            return fit_view_offsets(held, arcs, angles_deg, radius_mm=actual_diameter_mm / 2.0)
        return held
    start = find_axis(arcs, actual_diameter_mm)
    pts = np.concatenate([np.asarray(a, dtype=float) for a in arcs])
    theta = np.deg2rad(np.repeat(np.asarray(angles_deg, float), [len(a) for a in arcs]))
    a0 = np.asarray(start.axis_xy_mm)
    offsets = _rotate(start.arc_centres_mm - a0, -np.deg2rad(np.asarray(angles_deg, float)))
    x0 = [*a0, float(start.arc_radii_mm.mean())]
    if fit_offset:
        x0 += list(offsets.mean(axis=0))
    if fit_angle_scale:
        x0 += [1.0, 0.0, 0.0]
    n_offset = 2 if fit_offset else 0

    def unpack(p: np.ndarray) -> tuple[np.ndarray, float, np.ndarray, np.ndarray]:
        offset = p[3:5] if fit_offset else np.zeros(2)
        gear = p[3 + n_offset :] if fit_angle_scale else np.array([1.0, 0.0, 0.0])
        return p[:2], float(p[2]), offset, gear

    def residuals(p: np.ndarray) -> np.ndarray:
        axis, r, offset, gear = unpack(p)
        q = _rotate(pts - axis, -_gear_rad(theta, gear)) - offset
        return np.hypot(q[:, 0], q[:, 1]) - r

    sol = least_squares(residuals, np.array(x0), method="lm", xtol=1e-12, ftol=1e-12)
    axis, r, offset, gear = unpack(sol.x)
    scale = float(gear[0])
    if fit_angle_scale and np.hypot(*offset) < MIN_OFFSET_FOR_SCALE_MM:
        # A (nearly) centred cylinder looks the same at every angle: the scale is noise.
        calibration = find_axis_joint(arcs, angles_deg, actual_diameter_mm, fit_offset, False)
        note = (
            f"the calibration cylinder is within {MIN_OFFSET_FOR_SCALE_MM} mm of the axis, so "
            "the turntable angle scale was not estimated; place the cylinder off-centre"
        )
        return replace(calibration, warnings=(*calibration.warnings, note))
    d_est = float(2.0 * abs(r))
    cf = float(actual_diameter_mm / d_est)
    warnings = _warnings(cf, d_est, actual_diameter_mm, start.arc_radii_mm)
    calibration = AxisCalibration(
        axis_xy_mm=(float(axis[0]), float(axis[1])),
        correction_factor=cf,
        estimated_diameter_mm=d_est,
        actual_diameter_mm=float(actual_diameter_mm),
        arc_centres_mm=start.arc_centres_mm,
        arc_radii_mm=start.arc_radii_mm,
        warnings=tuple(warnings),
        method="joint",
        angle_scale=scale,
        angle_wave_deg=(float(np.rad2deg(gear[1])), float(np.rad2deg(gear[2]))),
        cylinder_offset_mm=(float(offset[0]), float(offset[1])) if fit_offset else None,
        rms_mm=float(np.sqrt(np.mean(sol.fun**2))),
    )
    if fit_angle_scale and per_view and fit_offset:
        return fit_view_offsets(calibration, arcs, angles_deg)
    return calibration


def turn_miss_deg(axis: AxisCalibration) -> float:
    """Return how far the table turns short of one turn of its step count (degrees;
    negative: beyond it), from the calibration's angle scale."""
    return 360.0 * (1.0 - axis.angle_scale)


def gear_ratio_factor(axis: AxisCalibration) -> float | None:
    """Return what the box's ``[turntable] gear_ratio`` should be multiplied by, or None.

    The calibration's angle scale is the table's true turn per turn of its count; a box
    configured with its ratio times ``1 / scale`` counts true degrees. None where the
    scale was held at 1, or where its turn's miss is within the next-turn tolerance
    (:data:`~lamina_shared.types.NEXT_TURN_MISMATCH_DEG`) once :data:`SCALE_SIGMAS` of
    the scale's standard error are taken off it: a box mended to its whole steps must
    not be told to change again by the cylinder's noise.

    Args:
        axis: the cylinder's calibration.

    Returns:
        The factor, or None when the configured ratio needs no change.
    """
    scale, sd = axis.angle_scale, axis.angle_scale_sd
    if not np.isfinite(scale) or scale <= 0.0:
        return None
    surely = abs(turn_miss_deg(axis)) - 360.0 * SCALE_SIGMAS * (sd if np.isfinite(sd) else 0.0)
    if surely <= NEXT_TURN_MISMATCH_DEG:
        return None
    return 1.0 / scale


def gear_advice(axis: AxisCalibration) -> str | None:
    """Return a line for the technician when the table turns short of (or past) its count.

    The host corrects every view at its step count either way; what the count's miss
    spoils is a continuous scan's laser-off frame taken a turn later (``next-turn``),
    which the box takes a turn of its count after the laser-on frame.

    Args:
        axis: the cylinder's calibration.

    Returns:
        The line, or None when the configured ``gear_ratio`` needs no change.
    """
    factor = gear_ratio_factor(axis)
    if factor is None:
        return None
    miss_deg = turn_miss_deg(axis)
    way = "short of" if miss_deg > 0 else "beyond"
    return (
        f"the turntable turns {abs(miss_deg):.2f} degrees {way} its step count each turn "
        f"(scale {axis.angle_scale:.5f}); the views are corrected for it, but laser-off "
        f"frames taken a turn later miss their angle: multiply [turntable] gear_ratio in the "
        f"box's configuration by {factor:.5f} and scan the calibration cylinder again"
    )


def next_turn_warning(axis: AxisCalibration) -> str | None:
    """Return the warning of a scan whose laser-off frames were taken a turn later, or None.

    The box takes each such frame a turn of its step count after the laser-on frame; a
    table that turns short of its count (:func:`gear_ratio_factor`) has not come round
    by then, so the frame sees the subject turned by the turn's miss and room light on
    fine relief can pass for stripe (random limb shapes with 1 mm relief measured 0.23-0.29
    mm instead of 0.09 mm at 1.6 degrees).

    Args:
        axis: the calibration the scan was processed with.

    Returns:
        The warning, or None when the table comes round within the tolerance.
    """
    factor = gear_ratio_factor(axis)
    if factor is None:
        return None
    miss_deg = abs(turn_miss_deg(axis))
    return (
        f"the laser-off frames taken a turn later stood {miss_deg:.2f} degrees from their "
        "laser-on frames (the turntable does not turn once per turn of its step count), so "
        f"room light on fine relief may have been taken for stripe: multiply [turntable] "
        f"gear_ratio in the box's configuration by {factor:.5f}, scan the calibration "
        "cylinder again, and scan again"
    )


def _gear_rad(count_rad: np.ndarray, gear: np.ndarray) -> np.ndarray:
    """Return the true angles (rad) of step counts ``count_rad`` for a gear ``(scale, sin,
    cos)``: the scale's shortfall over the whole count plus a once-per-turn error (an
    off-centre gear's, a bearing's runout), zero at count 0 so the frame starts there."""
    scale, a, b = gear
    return scale * count_rad + a * np.sin(count_rad) + b * (np.cos(count_rad) - 1.0)


def fit_view_offsets(
    calibration: AxisCalibration,
    arcs: list[np.ndarray],
    angles_deg: list[float],
    radius_mm: float | None = None,
) -> AxisCalibration:
    """Refine a joint fit with one turntable angle offset per distinct angle within the turn.

    The cylinder is scanned at the object's view angles, so the error of each view's
    angle (a gear's once-per-turn runout, an eccentric gear) is measured where it is
    used. Unknowns: axis, the cylinder's offset, the radius unless ``radius_mm`` holds it
    at the known value, and the offset of every view but the first, whose offset stays
    at the scale fit's value (a common rotation of all views is the same as a rotation of
    the cylinder's offset, so one must be fixed). Started from the scale fit, whose
    scale is kept; with a free radius ``C_f`` follows the refined radius.
    """
    commanded = np.asarray(angles_deg, dtype=float)
    distinct, view = np.unique(np.round(commanded % 360.0, 6), return_inverse=True)
    if len(distinct) < 3 or calibration.cylinder_offset_mm is None:
        return calibration
    pts = np.concatenate([np.asarray(a, dtype=float) for a in arcs])
    counts = [len(a) for a in arcs]
    point_count = np.repeat(commanded, counts)
    theta = np.deg2rad(point_count)
    point_view = np.repeat(view, counts)
    scale = calibration.angle_scale
    first = np.array([commanded[view == k][0] for k in range(len(distinct))])
    start = calibration._geared_deg(first) - first
    # A view's angle seen again turns later stands the gear's shortfall over those turns
    # further: its offset is the first sighting's plus the scale's share of the turns.
    theta += np.deg2rad((scale - 1.0) * (point_count - first[point_view]))
    free_radius = () if radius_mm is not None else (calibration.estimated_diameter_mm / 2.0,)
    first_offset = 4 + len(free_radius)  # parameters: axis, cylinder offset, [radius], views
    x0 = np.array(
        [*calibration.axis_xy_mm, *calibration.cylinder_offset_mm, *free_radius, *start[1:]]
    )

    def residuals(p: np.ndarray) -> np.ndarray:
        offsets = np.deg2rad(np.concatenate([start[:1], p[first_offset:]]))
        q = _rotate(pts - p[:2], -(theta + offsets[point_view])) - p[2:4]
        return np.hypot(q[:, 0], q[:, 1]) - (p[4] if radius_mm is None else radius_mm)

    sol = least_squares(residuals, x0, method="lm", xtol=1e-12, ftol=1e-12)
    offsets = np.concatenate([start[:1], sol.x[first_offset:]])
    sd_deg = _standard_errors(sol.jac, sol.fun)[first_offset:]
    if not np.median(sd_deg) <= MAX_VIEW_OFFSET_SD_DEG:
        note = (
            f"per-view turntable angles not used: the calibration cylinder measures them only "
            f"to +-{np.median(sd_deg):.3f} deg (needs {MAX_VIEW_OFFSET_SD_DEG} deg); place it "
            "further off-centre"
        )
        return replace(calibration, view_offsets_note=note)
    if radius_mm is None:
        d_est = float(2.0 * abs(sol.x[4]))
        calibration = replace(
            calibration,
            correction_factor=calibration.actual_diameter_mm / d_est,
            estimated_diameter_mm=d_est,
        )
    return replace(
        calibration,
        axis_xy_mm=(float(sol.x[0]), float(sol.x[1])),
        cylinder_offset_mm=(float(sol.x[2]), float(sol.x[3])),
        rms_mm=float(np.sqrt(np.mean(sol.fun**2))),
        view_offsets_deg=np.stack([first, offsets], axis=1),
        view_offset_sd_deg=float(np.median(sd_deg)),
    )


def _standard_errors(jac: np.ndarray, residuals: np.ndarray) -> np.ndarray:
    """Return the least-squares parameters' standard errors, in the parameters' units."""
    dof = max(len(residuals) - jac.shape[1], 1)
    sigma2 = float(residuals @ residuals) / dof
    try:
        cov = np.linalg.inv(jac.T @ jac) * sigma2
    except np.linalg.LinAlgError:
        return np.full(jac.shape[1], np.inf)
    return np.sqrt(np.maximum(np.diag(cov), 0.0))


def _hold_radius(
    free: AxisCalibration,
    arcs: list[np.ndarray],
    angles_deg: list[float],
    actual_diameter_mm: float,
    fit_offset: bool,
) -> AxisCalibration:
    """Refit the axis, offset and angle scale of a free joint fit with ``r = D_a / 2``.

    The free fit is the starting point and keeps its role as a check: its diameter is
    reported as ``estimated_diameter_mm`` and drives the 5 % warning. A scale the
    cylinder cannot tell from 1 (within :data:`SCALE_SIGMAS` of its standard error) is
    held at exactly 1: a tooth-exact belt has none, and a scale's noise, multiplied by
    every turn of a long scan, would twist its upper sections.
    """
    pts = np.concatenate([np.asarray(a, dtype=float) for a in arcs])
    theta = np.deg2rad(np.repeat(np.asarray(angles_deg, float), [len(a) for a in arcs]))
    radius = actual_diameter_mm / 2.0
    offset0 = free.cylinder_offset_mm if free.cylinder_offset_mm is not None else (0.0, 0.0)
    fit_gear = free.angle_scale != 1.0
    n_offset = 2 if fit_offset else 0

    def solve(scale_free: bool) -> Any:
        x0 = [*free.axis_xy_mm, *(offset0 if fit_offset else ())]
        if fit_gear:
            x0 += [*([free.angle_scale] if scale_free else []), *np.deg2rad(free.angle_wave_deg)]

        def unpack(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            offset = p[2:4] if fit_offset else np.zeros(2)
            gear = p[2 + n_offset :] if scale_free else np.concatenate([[1.0], p[2 + n_offset :]])
            return p[:2], offset, gear if fit_gear else np.array([1.0, 0.0, 0.0])

        def residuals(p: np.ndarray) -> np.ndarray:
            axis, offset, gear = unpack(p)
            q = _rotate(pts - axis, -_gear_rad(theta, gear)) - offset
            return np.hypot(q[:, 0], q[:, 1]) - radius

        sol = least_squares(residuals, np.array(x0), method="lm", xtol=1e-12, ftol=1e-12)
        return sol, unpack(sol.x)

    sol, (axis, offset, gear) = solve(scale_free=True)
    scale_sd = float("nan")
    if fit_gear:
        scale_sd = float(_standard_errors(sol.jac, sol.fun)[2 + n_offset])
        if abs(gear[0] - 1.0) < SCALE_SIGMAS * scale_sd:
            sol, (axis, offset, gear) = solve(scale_free=False)
    return replace(
        free,
        axis_xy_mm=(float(axis[0]), float(axis[1])),
        correction_factor=1.0,
        angle_scale=float(gear[0]),
        angle_scale_sd=scale_sd,
        angle_wave_deg=(float(np.rad2deg(gear[1])), float(np.rad2deg(gear[2]))),
        cylinder_offset_mm=(float(offset[0]), float(offset[1])) if fit_offset else None,
        rms_mm=float(np.sqrt(np.mean(sol.fun**2))),
    )
