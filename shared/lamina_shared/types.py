"""Data that crosses module and process boundaries: scan plans, boards, segments.

Image coordinates follow one convention everywhere in Lamina: ``(u, v)`` is
(column, row), ``v`` grows downwards, and the centre of pixel ``(i, j)`` sits at
exactly ``u = i, v = j`` (the same convention as OpenCV's corner detectors).
World and object coordinates follow ``docs/capture-format.md`` (in the repository).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

MAX_DECODED_VIEWS = 2**20
"""Most views any plan form decodes to; devices advertise their own, lower limit."""

TARGETS = ("grid", "cylinder", "object")
"""What can sit on the turntable: the calibration board, the calibration cylinder, the subject."""

CONFIDENCE_SCALE = 4
"""A point's confidence byte is its stripe peak over the noise sigma times this (0.25 steps)."""

SCAN_MODES = ("stop-and-go", "continuous")
"""How a plan's views are taken: the turntable stopping at each view (the default), or
turning at constant speed through each section while the camera streams (issue 22)."""

OFF_FRAMES = ("interleaved", "next-turn")
"""Where a continuous view's laser-off frames come from (the box's ``[turntable]
continuous_off_frames``): the frames just before and after its laser-on frame, or one
frame a turn of the table's step count later, at the same count."""

NEXT_TURN_MISMATCH_DEG = 0.05
"""Most a next-turn laser-off frame may stand from its laser-on frame's angle: the box's
frame period must divide its turn to within this, and the host names the gear ratio that
mends a table whose turn misses its count by more."""


@dataclass(frozen=True)
class ViewSpec:
    """One turntable position of a scan: which section, how high, which angle."""

    section: int
    z_mm: float
    angle_deg: float

    def to_dict(self) -> dict[str, Any]:
        """Return the JSON form used by the wire protocol and capture files."""
        return {"section": self.section, "z_mm": self.z_mm, "angle_deg": self.angle_deg}


@dataclass(frozen=True)
class ScanPlan:
    """The ordered views a scan visits; sections may hold different view counts.

    ``mode`` (one of :data:`SCAN_MODES`) says how the device takes them: in
    ``continuous`` mode the turntable does not stop, so each view's segment carries the
    angle the table was really at (its step count at the exposure), near the planned one.
    """

    views: tuple[ViewSpec, ...]
    mode: str = SCAN_MODES[0]

    def __post_init__(self) -> None:
        if self.mode not in SCAN_MODES:
            raise ValueError(f"scan mode {self.mode!r} is not one of {', '.join(SCAN_MODES)}")

    @property
    def continuous(self) -> bool:
        """Return True when the turntable turns through each section without stopping."""
        return self.mode == "continuous"

    def with_mode(self, mode: str) -> ScanPlan:
        """Return the same views taken in ``mode`` (ValueError for an unknown mode)."""
        return ScanPlan(self.views, mode)

    def with_views(self, views: tuple[ViewSpec, ...]) -> ScanPlan:
        """Return ``views`` (a part of this plan, say) taken in this plan's mode."""
        return ScanPlan(views, self.mode)

    def labels(self, seq: int, section: int, z_mm: float, angle_deg: float) -> bool:
        """Return True when a segment so labelled can be view ``seq`` of this plan.

        Section and height must be the plan's; so must the angle of a stop-and-go view,
        while a continuous view carries the angle the table was really at (in [0, 360)).
        """
        if not 0 <= seq < len(self.views):
            return False
        view = self.views[seq]
        if (view.section, view.z_mm) != (section, z_mm):
            return False
        if self.continuous:
            return math.isfinite(angle_deg) and 0.0 <= angle_deg < 360.0
        return view.angle_deg == angle_deg

    @classmethod
    def regular(
        cls, sections: int, pitch_mm: float, views: int, mode: str = SCAN_MODES[0]
    ) -> ScanPlan:
        """Return ``sections`` sections ``pitch_mm`` apart with ``views`` evenly spaced angles."""
        if sections < 1 or views < 1:
            raise ValueError("a scan needs at least one section and one view per section")
        if not math.isfinite(pitch_mm) or pitch_mm <= 0:
            raise ValueError(f"section pitch must be a positive number of mm, not {pitch_mm}")
        step = 360.0 / views
        # The pitch on the 1e-9 mm grid first, so the plan's second height is its pitch
        # exactly and the compact wire form (regular_form) reproduces every height.
        pitch_mm = round(pitch_mm, 9)
        if pitch_mm <= 0:
            raise ValueError("section pitch must be at least 1e-9 mm")
        return cls(
            tuple(
                ViewSpec(s, round(s * pitch_mm, 9), round(v * step, 9))
                for s in range(sections)
                for v in range(views)
            ),
            mode,
        )

    @property
    def sections(self) -> list[int]:
        """Return the distinct section indices in scan order."""
        return list(dict.fromkeys(v.section for v in self.views))

    def to_dict(self) -> dict[str, Any]:
        """Return the explicit JSON form: every view listed (stored plans, fingerprints).

        ``mode`` is there only when it is not the default, so stop-and-go plans keep the
        form (and the fingerprints) they had before modes existed.
        """
        return {"views": [v.to_dict() for v in self.views], **self._mode_form()}

    def _mode_form(self) -> dict[str, Any]:
        return {} if self.mode == SCAN_MODES[0] else {"mode": self.mode}

    def regular_form(self) -> dict[str, Any] | None:
        """Return ``{"sections", "pitch_mm", "views"}`` if :meth:`regular` of them is this plan."""
        sections = len(self.sections)
        if not self.views or len(self.views) % sections:
            return None
        per_section = len(self.views) // sections
        pitch_mm = self.views[per_section].z_mm if sections > 1 else 1.0
        try:
            candidate = ScanPlan.regular(sections, pitch_mm, per_section, self.mode)
        except ValueError:
            return None
        if candidate != self:
            return None
        return {"sections": sections, "pitch_mm": pitch_mm, "views": per_section}

    def to_wire(self) -> dict[str, Any]:
        """Return the form a REQUEST or WELCOME carries: compact when the plan is regular.

        A regular plan of any size travels in a few bytes (``{"regular": {...}}``); any
        other plan lists its views and must fit one message (``shared/PROTOCOL.md``).
        """
        regular = self.regular_form()
        if regular is None:
            return self.to_dict()
        return {"regular": regular, **self._mode_form()}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> ScanPlan:
        """Build a plan from its explicit or regular JSON form, checking every number is finite.

        Whatever the data claim, at most :data:`MAX_DECODED_VIEWS` views are built.
        """
        mode = data.get("mode", SCAN_MODES[0])
        if mode not in SCAN_MODES:
            raise ValueError(f"scan mode {mode!r} is not one of {', '.join(SCAN_MODES)}")
        if "regular" in data:
            form = data["regular"]
            sections, views_per_section = int(form["sections"]), int(form["views"])
            if sections * views_per_section > MAX_DECODED_VIEWS:
                raise ValueError(f"a plan of more than {MAX_DECODED_VIEWS} views")
            return cls.regular(sections, float(form["pitch_mm"]), views_per_section, mode)
        if len(data["views"]) > MAX_DECODED_VIEWS:
            raise ValueError(f"a plan of more than {MAX_DECODED_VIEWS} views")
        views = []
        for item in data["views"]:
            view = ViewSpec(int(item["section"]), float(item["z_mm"]), float(item["angle_deg"]))
            if not (math.isfinite(view.z_mm) and math.isfinite(view.angle_deg)):
                raise ValueError(f"non-finite number in scan plan view {item}")
            views.append(view)
        if not views:
            raise ValueError("a scan plan needs at least one view")
        return cls(tuple(views), mode)


@dataclass(frozen=True)
class BoardSpec:
    """A chessboard lying in the laser plane (capture spec, ``calibration_grid``)."""

    inner_corners: tuple[int, int]
    square_mm: float
    origin_mm: tuple[float, float]

    @property
    def corner_count(self) -> int:
        """Return how many inner corners the board has."""
        return self.inner_corners[0] * self.inner_corners[1]

    def world_corners(self) -> np.ndarray:
        """Return the (N, 2) world positions in mm, ``i`` fastest: index = j * nx + i."""
        nx, ny = self.inner_corners
        jj, ii = np.mgrid[0:ny, 0:nx]
        xy = np.stack([ii.ravel(), jj.ravel()], axis=1).astype(float) * self.square_mm
        return xy + np.asarray(self.origin_mm, dtype=float)

    def to_dict(self) -> dict[str, Any]:
        """Return the capture-spec JSON form."""
        return {
            "pattern": "chessboard",
            "inner_corners": list(self.inner_corners),
            "square_mm": self.square_mm,
            "origin_mm": list(self.origin_mm),
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> BoardSpec:
        """Build a board from its capture-spec JSON form."""
        nx, ny = (int(n) for n in data["inner_corners"])
        ox, oy = (float(o) for o in data["origin_mm"])
        return cls((nx, ny), float(data["square_mm"]), (ox, oy))


LIFT_REFERENCE_VIEWS = 8
"""Views of each lift reference section, evenly round the turn: a cylinder that stands a
little off upright reads the flank's mean height (its lean cancels round a turn), and the
stripe on a 45 degree flank is wide and noisy (0.5 mm per point on the limb rig, harsh):
eight views measure its radius to about 0.015 mm, four to about 0.03 mm."""


@dataclass(frozen=True)
class LiftReference:
    """Two marks on the calibration cylinder a known distance apart: the lift's length standard.

    Each mark is a V-groove turned round the cylinder; the lift sections meet the middle of
    each groove's lower flank, a cone on which the measured radius says how high the laser
    sheet really is. Both grooves are cut alike, so a bias in the measured radius cancels
    between them. ``marks_mm`` are the lift heights (as commanded) that meet the middle of
    each lower flank, from the box's drawings; ``spacing_mm`` is the certified distance
    between the two grooves; ``flank_slope`` the radius the flank loses per mm of height (1
    for a 90 degree V); ``depth_mm`` the groove's depth (for the check that the sheet met
    the flank's straight middle).
    """

    marks_mm: tuple[float, float]
    spacing_mm: float
    flank_slope: float = 1.0
    depth_mm: float = 5.0

    def __post_init__(self) -> None:
        numbers = (*self.marks_mm, self.spacing_mm, self.flank_slope, self.depth_mm)
        if len(self.marks_mm) != 2 or not all(math.isfinite(v) for v in numbers):
            raise ValueError("a lift reference needs two mark heights and finite numbers")
        low, high = self.marks_mm
        if not (high > low and self.spacing_mm > 0 and self.flank_slope > 0 and self.depth_mm > 0):
            raise ValueError(
                "a lift reference needs its upper mark above the lower one and a positive "
                "spacing, flank slope and groove depth"
            )

    def to_dict(self) -> dict[str, Any]:
        """Return the JSON form (WELCOME ``lift_reference``, the library's calibration)."""
        return {
            "marks_mm": list(self.marks_mm),
            "spacing_mm": self.spacing_mm,
            "flank_slope": self.flank_slope,
            "depth_mm": self.depth_mm,
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> LiftReference:
        """Build a reference from its JSON form.

        Raises:
            ValueError, KeyError, TypeError: the data are not a usable reference.
        """
        low, high = (float(v) for v in data["marks_mm"])
        return cls(
            (low, high),
            float(data["spacing_mm"]),
            float(data.get("flank_slope", 1.0)),
            float(data.get("depth_mm", 5.0)),
        )

    def plan(self, cylinder: ScanPlan) -> ScanPlan:
        """Return ``cylinder``'s plan with one section at each mark, ``LIFT_REFERENCE_VIEWS``
        views evenly round the turn, after its own sections."""
        first = max(v.section for v in cylinder.views) + 1
        step = 360.0 / LIFT_REFERENCE_VIEWS
        extra = tuple(
            ViewSpec(first + k, z, round(v * step, 9))
            for k, z in enumerate(self.marks_mm)
            for v in range(LIFT_REFERENCE_VIEWS)
        )
        return ScanPlan(cylinder.views + extra)


def _unknown_confidence() -> np.ndarray:
    return np.zeros(0, np.uint8)


def _no_colour() -> np.ndarray:
    return np.zeros((0, 3), np.uint8)


@dataclass(frozen=True, eq=False)
class Segment:
    """The stripe points the device extracted from one laser-on/laser-off view.

    ``cols`` are image columns (integers), ``rows`` the sub-pixel stripe centre in
    each column, ``peak`` the highest difference intensity of the run used and
    ``width`` its length in pixels: per-point quality for the host to judge.
    ``confidence`` (uint8) is the peak over the noise sigma of the view's difference
    image, times :data:`CONFIDENCE_SCALE` and capped at 255; 0 means unknown (segments
    recorded before the device measured its noise). ``colour`` is either empty (0, 3)
    (the scan did not ask for colour) or (N, 3) uint8 sRGB sampled from the view's
    laser-off frame at each stripe centre. ``turns`` is how many whole turns the
    table's step count had made since the device powered up when the view was taken:
    the count is ``angle_deg + 360 * turns``. A gear that turns short of its count falls
    further behind with every turn, so the host scales its calibrated error over the
    whole count, not the angle within the turn (0 in segments recorded before the
    device sent it).
    """

    target: str
    section: int
    view: int
    z_mm: float
    angle_deg: float
    cols: np.ndarray = field(repr=False)
    rows: np.ndarray = field(repr=False)
    peak: np.ndarray = field(repr=False)
    width: np.ndarray = field(repr=False)
    confidence: np.ndarray = field(default_factory=_unknown_confidence, repr=False)
    colour: np.ndarray = field(default_factory=_no_colour, repr=False)
    turns: int = 0

    def __post_init__(self) -> None:
        n = len(self.cols)
        if len(self.confidence) == 0 and n:
            object.__setattr__(self, "confidence", np.zeros(n, np.uint8))
        if not (len(self.rows) == len(self.peak) == len(self.width) == len(self.confidence) == n):
            raise ValueError("segment arrays differ in length")
        colour = np.asarray(self.colour)
        if colour.ndim != 2 or colour.shape[1] != 3 or len(colour) not in (0, n):
            raise ValueError("segment colour must be (0, 3) or one (r, g, b) row per point")

    @property
    def has_colour(self) -> bool:
        """Return True when every point carries an sRGB colour."""
        return len(self.colour) == len(self.cols) and len(self.cols) > 0

    def __len__(self) -> int:
        return len(self.cols)

    @property
    def count_deg(self) -> float:
        """Return the view's step count in degrees, ``angle_deg + 360 * turns``: the
        angle the gear's calibrated error is taken at."""
        return self.angle_deg + 360.0 * self.turns

    @property
    def uv(self) -> np.ndarray:
        """Return the (N, 2) image points ``(u, v)`` as float64."""
        return np.stack([self.cols.astype(float), self.rows.astype(float)], axis=1)

    def same_as(self, other: Segment) -> bool:
        """Return True when both segments are identical bit for bit."""
        return (self.target, self.section, self.view, self.z_mm, self.angle_deg, self.turns) == (
            other.target,
            other.section,
            other.view,
            other.z_mm,
            other.angle_deg,
            other.turns,
        ) and all(
            a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()
            for a, b in zip(  # noqa: B905 - two tuples of six arrays
                (self.cols, self.rows, self.peak, self.width, self.confidence, self.colour),
                (other.cols, other.rows, other.peak, other.width, other.confidence, other.colour),
            )
        )


def from_first_turn(segments: list[Segment], among: list[Segment] | None = None) -> list[Segment]:
    """Return ``segments`` with their turns counted from the first turn among them.

    A segment's turns are the device's since it powered up, so a scan's first view may
    stand hundreds of turns on. Counted from the scan's own first turn, a gear's
    calibrated shortfall (scaled over the count) turns the whole object by at most a
    turn's shortfall however long the device has run, and the fits stay well
    conditioned. Give it every segment of one target of one scan, or a part of them with
    the whole as ``among`` (whose first turn is then the one counted from).
    """
    first = min((s.turns for s in (segments if among is None else among)), default=0)
    return [replace(s, turns=s.turns - first) for s in segments] if first else list(segments)
