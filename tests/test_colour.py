"""Colour per point (issue 14 part 3): wire field, negotiation, device sampling, host output.

The simulated ``patches`` cylinder is skin-tone with four bands of known reflectance;
its truth is :class:`lamina_device.sim.texture.Texture`. Measured colours are compared
with the patches' reflectances after one white balance taken on the skin (a colour
camera has an unknown gain per channel: the room light, the exposure).
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from lamina_device.acquisition import acquire
from lamina_device.extract import sample_colour
from lamina_device.server import DeviceServer
from lamina_device.sim import open_sim
from lamina_device.sim.texture import Texture, colour_errors
from lamina_host.link.errors import DeviceError
from lamina_host.link.handshake import read_welcome
from lamina_host.reconstruct.assembly import average_overlap_colours, average_overlaps
from lamina_host.reconstruct.mesh import load_coloured_ply, load_obj, obj_bytes, save_ply
from lamina_host.store.library import Library
from lamina_shared.limits import DeviceLimits
from lamina_shared.ops import OPS, ArgsError, ScanArgs, parse_args, request_args
from lamina_shared.protocol import (
    COLOUR_FLAG,
    PROTOCOL_VERSION,
    ProtocolError,
    confidence_bytes,
    decode_segment_body,
    encode_segment_body,
    quantise_rows,
    segment_bytes_per_point,
)
from lamina_shared.types import ScanPlan, Segment
from tests.helpers.served import link

PATCH_OBJECT = "patches:d=30"


def stripe(n: int, colour: bool, seed: int = 0) -> Segment:
    """A plausible stripe of ``n`` neighbouring columns, coloured skin-like if asked."""
    rng = np.random.default_rng(seed)
    peak = rng.integers(20, 200, n).astype(np.uint8)
    rgb = np.clip(np.array([180.0, 130.0, 105.0]) + rng.normal(0, 6, (n, 3)), 0, 255)
    return Segment(
        "object", 1, 2, 3.0, 45.0,
        np.arange(100, 100 + n, dtype=np.uint16),
        quantise_rows(200 + np.cumsum(rng.normal(0, 0.3, n))),
        peak,
        rng.integers(3, 9, n).astype(np.uint8),
        confidence_bytes(peak, 5.0),
        rgb.astype(np.uint8) if colour else np.zeros((0, 3), np.uint8),
    )  # fmt: skip


# --- the wire ----------------------------------------------------------------------------


@pytest.mark.parametrize("n", [1, 2, 33, 639])
def test_segments_round_trip_with_and_without_colour(n):
    for colour in (False, True):
        segment = stripe(n, colour)
        body = encode_segment_body(7, 3, segment)
        decoded = decode_segment_body(body).segment
        assert decoded.same_as(segment)
        assert decoded.has_colour is colour
        assert bool(body[8] & COLOUR_FLAG) is colour  # the target byte carries the flag


def test_colour_off_costs_nothing_and_colour_on_costs_under_three_bytes():
    plain, coloured = stripe(639, False), stripe(639, True)
    # Without colour the body is exactly the protocol-3 body: no flag, no extra byte.
    assert encode_segment_body(1, 1, plain) == encode_segment_body(
        1, 1, Segment(*[getattr(plain, f) for f in ("target", "section", "view", "z_mm")],
                      plain.angle_deg, plain.cols, plain.rows, plain.peak, plain.width,
                      plain.confidence)
    )  # fmt: skip
    extra = segment_bytes_per_point(coloured) - segment_bytes_per_point(plain)
    assert 0.5 < extra < 3.0  # Rice-coded colour differences, below 3 raw bytes


def test_malformed_colour_is_a_protocol_error():
    body = bytearray(encode_segment_body(1, 1, stripe(40, True)))
    with pytest.raises(ProtocolError):
        decode_segment_body(bytes(body[:-3]))
    empty = bytearray(encode_segment_body(1, 1, stripe(0, False)))
    empty[8] |= COLOUR_FLAG
    with pytest.raises(ProtocolError, match="empty segment"):
        decode_segment_body(bytes(empty))


def test_the_colour_flag_is_only_sent_when_asked():
    plan = ScanPlan.regular(1, 1.0, 4)
    assert "colour" not in request_args(ScanArgs("object", plan))  # an older device refuses it
    assert request_args(ScanArgs("object", plan, colour=True))["colour"] is True
    limits = DeviceLimits()
    assert parse_args("scan", {"target": "object", "colour": True}, limits).colour is True
    with pytest.raises(ArgsError, match=r"scan\.colour"):
        parse_args("scan", {"target": "object", "colour": 1}, limits)
    assert "scan" in OPS


def test_an_older_device_welcome_offers_no_colour():
    welcome: dict[str, Any] = {
        "protocol": PROTOCOL_VERSION, "hardware": "pi", "image_size": [640, 480],
        "segment_encoding": {"row_scale": 64},
    }  # fmt: skip
    assert read_welcome(welcome).colour is False
    assert read_welcome({**welcome, "colour": True}).colour is True
    assert read_welcome({**welcome, "colour": "yes"}).colour is False


# --- the device ---------------------------------------------------------------------------


def test_bilinear_sampling_of_a_linear_ramp_is_exact():
    rows, cols = np.mgrid[0:20, 0:30].astype(float)
    image = np.stack([3 * cols + 2, 4 * rows + 5, cols + rows], axis=2).astype(np.uint8)
    u = np.array([0.0, 3.0, 7.0, 29.0])
    v = np.array([0.0, 2.25, 11.5, 18.75])
    truth = np.stack([3 * u + 2, 4 * v + 5, u + v], axis=1)
    np.testing.assert_allclose(sample_colour(image, u, v), np.rint(truth), atol=0.5)
    # Beyond the last pixel centre a point takes the border colour.
    assert tuple(sample_colour(image, np.array([29.0]), np.array([19.7]))[0]) == tuple(
        image[19, 29]
    )


def test_colour_does_not_change_the_stripe():
    plan = ScanPlan.regular(1, 1.0, 2)
    runs: list[list[Segment]] = []
    for colour in (False, True):
        hardware = open_sim(PATCH_OBJECT, noise="harsh")
        segments: list[Segment] = []
        try:
            acquire(hardware, "object", plan, segments.append, colour=colour)
        finally:
            hardware.close()
        runs.append(segments)
    for plain, coloured in zip(*runs, strict=True):
        assert not plain.has_colour and coloured.has_colour
        for name in ("cols", "rows", "peak", "width", "confidence"):
            assert np.array_equal(getattr(plain, name), getattr(coloured, name)), name


def test_a_monochrome_device_refuses_colour():
    hardware = open_sim(PATCH_OBJECT)  # thesis noise: one grey channel
    try:
        assert not hardware.camera.has_colour  # type: ignore[attr-defined]
        with pytest.raises(Exception, match="monochrome"):
            acquire(hardware, "object", ScanPlan.regular(1, 1.0, 1), print, colour=True)
    finally:
        hardware.close()


# --- negotiation over a real link ---------------------------------------------------------


class OlderServer(DeviceServer):
    """A device from before colour: its WELCOME says nothing about it."""

    def welcome(self) -> dict[str, Any]:
        welcome = super().welcome()
        welcome.pop("colour")
        return welcome


def test_colour_is_negotiated_and_an_older_device_still_scans():
    plan = ScanPlan.regular(1, 1.0, 2)
    with link(object_spec=PATCH_OBJECT, noise="harsh") as ends:
        client = ends.client
        assert client.info is not None and client.info.colour
        coloured = client.scan("object", plan, colour=True)
        assert all(s.has_colour for s in coloured)
    with link(object_spec=PATCH_OBJECT, noise="harsh", server_class=OlderServer) as ends:
        client = ends.client
        assert client.info is not None and not client.info.colour
        plain = client.scan("object", plan)  # no colour asked: works as before
        assert not any(s.has_colour for s in plain)
        with pytest.raises(DeviceError, match="cannot sample colour"):
            client.scan("object", plan, colour=True)
    for a, b in zip(coloured, plain, strict=True):
        assert np.array_equal(a.rows, b.rows)  # the same stripe, with and without colour


# --- the host --------------------------------------------------------------------------


def test_overlapping_views_get_the_mean_colour():
    angles = [np.radians(np.arange(0, 181, 2.0)), np.radians(np.arange(90, 271, 2.0))]
    arcs = [10.0 * np.stack([np.cos(a), np.sin(a)], axis=1) for a in angles]
    paint = ([200.0, 0.0, 0.0], [0.0, 0.0, 100.0])
    colours = [np.tile(c, (len(a), 1)) for c, a in zip(paint, angles, strict=True)]
    points, mean = average_overlap_colours(arcs, colours)
    azimuth = np.degrees(np.arctan2(points[:, 1], points[:, 0])) % 360
    # In the overlap the colour blends from one view's to the other's without a step
    # (weights falling to zero at each view's end): a convex mix, red falling steadily.
    both = (azimuth > 91) & (azimuth < 179)
    mix = mean[both][np.argsort(azimuth[both])]
    np.testing.assert_allclose(mix[:, 0] / 200.0 + mix[:, 2] / 100.0, 1.0)
    assert np.all(np.diff(mix[:, 0]) <= 1e-9) and mix[0, 0] > 190.0 and mix[-1, 0] < 10.0
    assert np.abs(np.diff(mix[:, 0])).max() < 20.0
    np.testing.assert_allclose(mean[azimuth < 89], [[200.0, 0.0, 0.0]] * int((azimuth < 89).sum()))
    # The geometry's overlap averaging is unchanged by sharing its core with colour.
    contour = average_overlaps(arcs)
    np.testing.assert_allclose(np.hypot(*contour.T), 10.0, atol=1e-9)


def test_ply_and_obj_carry_vertex_colours(tmp_path):
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    faces = np.array([[0, 1, 2], [0, 1, 3]])
    rgb = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255], [12, 34, 56]], np.uint8)
    save_ply(tmp_path / "m.ply", vertices, faces, colours=rgb)
    v, f, c = load_coloured_ply((tmp_path / "m.ply").read_bytes())
    assert np.array_equal(v, vertices) and np.array_equal(f, faces) and np.array_equal(c, rgb)
    v, f, c = load_obj(obj_bytes(vertices, faces, rgb))
    assert np.allclose(v, vertices) and np.array_equal(f, faces) and np.array_equal(c, rgb)
    assert load_obj(obj_bytes(vertices, faces))[2] is None


def test_the_library_keeps_colour(tmp_path):
    library = Library(tmp_path / "lib.db")
    plan = ScanPlan.regular(1, 1.0, 1)
    segment = stripe(50, True, seed=4)
    segment = Segment("object", 0, 0, 0.0, 0.0, segment.cols, segment.rows, segment.peak,
                      segment.width, segment.confidence, segment.colour)  # fmt: skip
    scan_id = library.create_scan("s1", {"cylinder": plan, "object": plan}, {}, {})
    assert library.add_segment(scan_id, 0, segment)
    assert library.segments(scan_id, "object")[0].same_as(segment)


# --- a whole scan -------------------------------------------------------------------------


def test_a_colour_scan_writes_ply_and_obj_coloured_like_the_patches(tmp_path):
    out = tmp_path / "out"
    done = subprocess.run(
        [sys.executable, "-m", "lamina_host", "scan", "--device", "sim", "--object",
         PATCH_OBJECT, "--noise", "harsh", "--colour", "--sections", "2", "--views", "8",
         "--out", str(out), "--library", str(tmp_path / "lib.db")],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    points, _, colours = load_coloured_ply((out / "colour_points.ply").read_bytes())
    assert colours is not None
    gain, errors = colour_errors(points, colours)
    for error in errors:
        assert error.points > 200, error  # every patch is seen in both sections
        assert np.all(np.abs(error.bias) < 3.0), error
        assert np.all(np.array(error.rms) < 6.0), error
        assert error.mean_delta_e < 6.0, error
    # The mesh's vertices take the nearby points' colours; the OBJ holds the same.
    vertices, faces, vertex_rgb = load_coloured_ply((out / "mesh.ply").read_bytes())
    assert vertex_rgb is not None
    texture = Texture()
    on_patch = texture.patch_index(vertices, margin_deg=8.0)
    for k, patch in enumerate(texture.patches):
        truth = gain * np.array(patch.reflectance)
        assert np.all(np.abs(vertex_rgb[on_patch == k].mean(axis=0) - truth) < 4.0), patch.name
    obj_v, obj_f, obj_rgb = load_obj((out / "mesh.obj").read_bytes())
    assert np.allclose(obj_v, vertices, atol=1e-5) and np.array_equal(obj_f, faces)
    assert obj_rgb is not None and np.array_equal(obj_rgb, vertex_rgb)


def test_colour_from_a_monochrome_device_is_one_line(tmp_path):
    done = subprocess.run(
        [sys.executable, "-m", "lamina_host", "scan", "--device", "sim", "--object",
         PATCH_OBJECT, "--colour", "--sections", "1", "--views", "4",
         "--out", str(tmp_path / "out"), "--library", str(tmp_path / "lib.db")],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert done.returncode != 0
    lines = done.stderr.strip().splitlines()
    assert lines and "cannot sample colour" in lines[-1] and "Traceback" not in done.stderr
    assert not Path(tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


# --- replay ---------------------------------------------------------------------------------


def test_replay_samples_colour_from_the_capture_frames(tmp_path):
    import cv2

    from lamina_device.replay import open_replay
    from lamina_shared.capture import load_capture

    out = tmp_path / "capture"
    done = subprocess.run(
        [sys.executable, "-m", "lamina_device", "record", "--hardware", "sim", "--out", str(out),
         "--object", "cylinder:d=19.05", "--sections", "1", "--pitch", "2", "--views", "2"],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    capture = load_capture(out)
    grey_frames = {}
    for view in capture.views("object"):
        assert view.laser_off is not None
        grey = cv2.imread(str(view.laser_off), cv2.IMREAD_UNCHANGED)
        grey_frames[view.spec.angle_deg] = grey
        # The laser's (red) channel keeps the recorded frame; green is half of it, blue 50.
        bgr = np.stack([np.full_like(grey, 50), grey // 2, grey], axis=2)
        assert cv2.imwrite(str(view.laser_off), bgr)
    hardware = open_replay(out)
    segments: list[Segment] = []
    try:
        assert hardware.camera.has_colour  # type: ignore[attr-defined]
        plan = capture.plan("object")
        assert plan is not None
        acquire(hardware, "object", plan, segments.append, colour=True)
    finally:
        hardware.close()
    assert segments and all(s.has_colour for s in segments)
    for segment in segments:
        grey = grey_frames[segment.angle_deg].astype(float)
        red = sample_colour(np.stack([grey] * 3, axis=2), segment.cols, segment.rows)[:, 0]
        assert np.array_equal(segment.colour[:, 0], red)  # red is the recorded frame
        assert np.all(segment.colour[:, 2] == 50)  # blue: the constant, so RGB is not BGR
        assert np.all(np.abs(segment.colour[:, 1].astype(int) - red.astype(int) // 2) <= 1)
