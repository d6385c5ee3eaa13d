"""RealSense recordings without a camera: pyrealsense2 software_device + recorder write .db3 files.

Device errors are tested by replacing ``rs.context`` (the pyrealsense2 boundary) with fakes.
"""

import os

import cv2
import numpy as np
import pyrealsense2 as rs
import pytest

from o3d_mvps.capture import default_depth_intrinsic
from o3d_mvps.cli import main as cli_main
from o3d_mvps.colour import srgb_to_linear
from o3d_mvps.errors import RecordingError
from o3d_mvps.realsense import (
    check_modes,
    extrinsics_to_matrix,
    find_device,
    read_recording,
    record_capture,
    select_frames,
)
from o3d_mvps.depth_to_colour import register_depth

CW, CH, DW, DH = 128, 72, 64, 36
COLOR_K = np.array([[110.0, 0.0, 63.2], [0.0, 111.0, 36.1], [0.0, 0.0, 1.0]])
UNITS = 0.001


# --------------------------------------------------------------------------------------------
# Writing recordings with a software device
# --------------------------------------------------------------------------------------------
def _rs_intrinsics(K, size):
    intr = rs.intrinsics()
    intr.width, intr.height = size
    intr.fx, intr.fy, intr.ppx, intr.ppy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    intr.model, intr.coeffs = rs.distortion.brown_conrady, [0.0] * 5
    return intr


def _rs_extrinsics(T):
    ext = rs.extrinsics()
    ext.rotation = T[:3, :3].T.ravel().tolist()  # column-major
    ext.translation = T[:3, 3].tolist()
    return ext


def write_recording(path, colors=None, depths=None, depth_K=None, depth_to_color=None, color_format=rs.format.rgb8):
    """Record colour (n, H, W, 3) uint8 and depth (n, h, w) uint16 frames to a .db3 file."""
    dev = rs.software_device()
    dev.register_info(rs.camera_info.name, "Intel RealSense D415")
    dev.register_info(rs.camera_info.serial_number, "000123")
    streams = []  # (software sensor, profile, bytes per pixel, frames)
    if depths is not None:
        sensor = dev.add_sensor("Stereo Module")
        vs = rs.video_stream()
        vs.type, vs.index, vs.uid, vs.fps, vs.bpp, vs.fmt = rs.stream.depth, 0, 0, 30, 2, rs.format.z16
        vs.height, vs.width = depths.shape[1:3]
        vs.intrinsics = _rs_intrinsics(depth_K, (vs.width, vs.height))
        streams.append((sensor, sensor.add_video_stream(vs, True), 2, depths))
        sensor.add_read_only_option(rs.option.depth_units, UNITS)
    if colors is not None:
        sensor = dev.add_sensor("RGB Camera")
        vs = rs.video_stream()
        vs.type, vs.index, vs.uid, vs.fps, vs.bpp, vs.fmt = rs.stream.color, 0, 1, 30, 3, color_format
        vs.height, vs.width = colors.shape[1:3]
        vs.intrinsics = _rs_intrinsics(COLOR_K, (vs.width, vs.height))
        streams.append((sensor, sensor.add_video_stream(vs, True), 3, colors))
    if len(streams) == 2 and depth_to_color is not None:
        streams[0][1].register_extrinsics_to(streams[1][1], _rs_extrinsics(depth_to_color))
    recorder = rs.recorder(str(path), dev)
    sensors = recorder.query_sensors()
    for s in sensors:
        s.open(s.get_stream_profiles()[0])
        s.start(lambda frame: None)
    n = len(streams[0][3]) if streams else 0
    for k in range(n):
        for sensor, profile, bpp, data in streams:
            f = rs.software_video_frame()
            f.pixels = np.ascontiguousarray(data[k]).tobytes()
            f.stride, f.bpp = data[k].shape[1] * bpp, bpp
            f.timestamp, f.domain, f.frame_number = k * 33.3, rs.timestamp_domain.hardware_clock, k
            f.profile = profile.as_video_stream_profile()
            if bpp == 2:
                f.depth_units = UNITS
            sensor.on_video_frame(f)
    for s in sensors:
        s.stop()
        s.close()
    del recorder, sensors


def _canvas(seed, width=CW + 128):
    """A smooth random colour texture (CH, width, 3) uint8 to crop frames from."""
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 256, size=(CH // 4, width // 4, 3), dtype=np.uint8)
    return cv2.resize(small, (width, CH), interpolation=cv2.INTER_LINEAR)


def _crop(canvas, offset):
    return np.ascontiguousarray(canvas[:, offset : offset + CW])


def _texture(n, seed=0, shift=2):
    """n textured uint8 frames (n, CH, CW, 3), each ``shift`` pixels further to the right."""
    canvas = _canvas(seed)
    return np.stack([_crop(canvas, k * shift) for k in range(n)]) if n else np.zeros((0, CH, CW, 3), np.uint8)


def _depth_frames(n):
    v, u = np.mgrid[0:DH, 0:DW]
    base = 600 + 2 * u + v  # mm: a slanted plane
    base[10:20, 20:40] = 450  # a box in front of it
    frames = (base[None] + np.arange(n)[:, None, None]).astype(np.uint16)
    frames[:, 0:3, 0:5] = 0  # a missing patch
    return frames


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """Six frames, identity extrinsic and depth intrinsics = colour / 2: depth reads back as written."""
    path = tmp_path_factory.mktemp("rec") / "identity.db3"
    colors, depths = _texture(6), _depth_frames(6)
    write_recording(path, colors, depths, default_depth_intrinsic(COLOR_K, 2), np.eye(4))
    return path, colors, depths


# --------------------------------------------------------------------------------------------
# Reading recordings
# --------------------------------------------------------------------------------------------
def test_read_recording_round_trip(recorded):
    path, colors, depths = recorded
    capture = read_recording(path, frames=4)
    meta = capture.metadata["realsense"]
    numbers = meta["frame_numbers"]
    assert numbers == [0, 2, 3, 5]  # all 6 frames played back, 4 spread evenly
    assert meta["selection"]["candidates"] == 6 and capture.n_frames == 4
    assert capture.color_size == (CH, CW) and capture.depth_size == (DH, DW) and capture.scale_factor == 2
    assert capture.sensor == "Intel RealSense D415 (serial 000123)"
    assert capture.depth_scale == 1000 and capture.color_encoding == "srgb"
    np.testing.assert_allclose(capture.color_K(), COLOR_K, atol=1e-4)
    np.testing.assert_allclose(capture.depth_K(), default_depth_intrinsic(COLOR_K, 2), atol=1e-4)
    np.testing.assert_allclose(meta["depth_to_color"], np.eye(4), atol=1e-7)
    assert meta["serial"] == "000123" and abs(meta["depth_units_m"] - UNITS) < 1e-9
    for i, k in enumerate(numbers):
        np.testing.assert_array_equal(capture.color_array(i), srgb_to_linear(colors[k] / np.float32(255)))
        np.testing.assert_allclose(capture.depth_array(i), depths[k] * UNITS, atol=1e-6)


def test_read_recording_registers_with_the_recorded_extrinsic(tmp_path):
    depth_K = np.array([[52.0, 0.0, 32.4], [0.0, 52.5, 17.8], [0.0, 0.0, 1.0]])
    a = np.deg2rad(1.0)
    T = np.eye(4)
    T[:3, :3] = [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]  # about z: not symmetric
    T[:3, 3] = [0.015, 0.0, 0.0]
    colors, depths = _texture(3), _depth_frames(3)
    write_recording(tmp_path / "ext.db3", colors, depths, depth_K, T)
    capture = read_recording(tmp_path / "ext.db3", frames=2)
    np.testing.assert_allclose(capture.metadata["realsense"]["depth_to_color"], T, atol=1e-6)
    k = capture.metadata["realsense"]["frame_numbers"][0]
    expected = register_depth(depths[k] * UNITS, depth_K, COLOR_K, T, (DW, DH), scale_factor=2)
    np.testing.assert_allclose(capture.depth_array(0), expected, atol=1e-6)
    # Colour camera 15 mm along +x of the depth camera sees the box (z = 0.45 m, depth columns 20..39)
    # shifted by f * x / z: columns 20..39 -> about (20 - 32.4) * 55 / 52 + 31.6 + 55 * 0.015 / 0.45.
    z = capture.depth_array(0)
    cols = np.flatnonzero(((z > 0) & (z < 0.5)).any(axis=0))
    shift = 55.0 * 0.015 / 0.45  # ~1.8 px
    assert abs(cols.mean() - ((29.5 - 32.4) * 55 / 52 + COLOR_K[0, 2] / 2 - 0.25 + shift)) < 1.5


def test_extrinsics_convention_matches_librealsense():
    T = np.eye(4)
    a = 0.3
    T[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    T[:3, :3] = T[:3, :3] @ [[1, 0, 0], [0, np.cos(0.2), -np.sin(0.2)], [0, np.sin(0.2), np.cos(0.2)]]
    T[:3, 3] = [0.1, -0.02, 0.03]
    ext = _rs_extrinsics(T)
    p = [0.2, -0.1, 0.7]
    expected = rs.rs2_transform_point_to_point(ext, p)
    np.testing.assert_allclose(extrinsics_to_matrix(ext)[:3, :3] @ p + T[:3, 3], expected, atol=1e-6)


def test_read_recording_bgr_and_stride(tmp_path):
    colors, depths = _texture(8, seed=3), _depth_frames(8)
    write_recording(tmp_path / "bgr.db3", colors[..., ::-1], depths, default_depth_intrinsic(COLOR_K, 2), np.eye(4),
                    color_format=rs.format.bgr8)  # fmt: skip
    with pytest.warns(UserWarning, match="kept 4 of 20 frames"):
        capture = read_recording(tmp_path / "bgr.db3", frames=20, stride=2, scale_factor=4)
    numbers = capture.metadata["realsense"]["frame_numbers"]
    assert numbers == [0, 2, 4, 6] and capture.metadata["realsense"]["selection"]["stride"] == 2
    assert capture.depth_size == (CH // 4, CW // 4)
    np.testing.assert_array_equal(capture.color_array(0), srgb_to_linear(colors[numbers[0]] / np.float32(255)))


def test_read_recording_skips_blurred_and_non_overlapping_frames(tmp_path):
    colors, depths = _texture(8, seed=5), _depth_frames(8)
    colors[3] = cv2.GaussianBlur(colors[3], (0, 0), 3)
    colors[6] = _crop(_canvas(5), 80)  # 80 of 128 pixels away from the reference
    write_recording(tmp_path / "sel.db3", colors, depths, default_depth_intrinsic(COLOR_K, 2), np.eye(4))
    with pytest.warns(UserWarning, match="1 blurred, 1 with little overlap"):
        capture = read_recording(tmp_path / "sel.db3", frames=20)
    assert capture.metadata["realsense"]["frame_numbers"] == [0, 1, 2, 4, 5, 7]


# --------------------------------------------------------------------------------------------
# Frame selection on its own
# --------------------------------------------------------------------------------------------
def test_select_frames_spreads_sharp_overlapping_frames():
    frames = _texture(12, seed=7, shift=3)
    greys = [cv2.cvtColor(f, cv2.COLOR_RGB2GRAY).astype(np.float32) / 255 for f in frames]
    greys[0] = cv2.GaussianBlur(greys[0], (0, 0), 3)  # blurred: the reference becomes frame 1
    greys[5] = cv2.GaussianBlur(greys[5], (0, 0), 3)
    far = _crop(_canvas(7), 3 + 75)  # 75 px from the reference (frame 1): overlap 0.41
    greys[9] = cv2.cvtColor(far, cv2.COLOR_RGB2GRAY).astype(np.float32) / 255
    choice = select_frames(greys, 5)
    assert choice.indices[0] == 1
    assert set(choice.blurred) == {0, 5} and 9 in choice.low_overlap
    assert len(choice.indices) == 5 and not {0, 5, 9} & set(choice.indices)
    assert choice.indices == sorted(choice.indices) and choice.indices[-1] == 11
    assert choice.overlap[4] == pytest.approx(1 - 9 / CW, abs=0.03)  # 9 px of 128


# --------------------------------------------------------------------------------------------
# Errors
# --------------------------------------------------------------------------------------------
def test_recording_errors_name_the_problem_and_the_formats(tmp_path, recorded):
    with pytest.raises(RecordingError, match=r"does not exist.*\.bag.*\.db3"):
        read_recording(tmp_path / "missing.db3")
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(RecordingError, match=r"not a RealSense recording \(\.bag or \.db3\)"):
        read_recording(tmp_path / "notes.txt")
    (tmp_path / "empty.bag").write_bytes(b"")
    with pytest.raises(RecordingError, match="empty.*truncated"):
        read_recording(tmp_path / "empty.bag")
    for name in ["junk.db3", "junk.bag"]:
        (tmp_path / name).write_text("not a recording")
        with pytest.raises(RecordingError, match=r"corrupt, truncated or not a RealSense recording.*\.bag.*\.db3"):
            read_recording(tmp_path / name)
    data = recorded[0].read_bytes()
    (tmp_path / "cut.db3").write_bytes(data[: len(data) // 2])
    with pytest.raises(RecordingError, match="corrupt, truncated"):
        read_recording(tmp_path / "cut.db3")


def test_recording_without_frames_or_streams(tmp_path):
    K = default_depth_intrinsic(COLOR_K, 2)
    write_recording(tmp_path / "zero.db3", _texture(0), _depth_frames(0), K, np.eye(4))
    with pytest.raises(RecordingError, match="no streams or no frames"):
        read_recording(tmp_path / "zero.db3")
    write_recording(tmp_path / "depth_only.db3", None, _depth_frames(3), K)
    with pytest.raises(RecordingError, match="no colour stream.*both the colour and the depth"):
        read_recording(tmp_path / "depth_only.db3")
    write_recording(tmp_path / "colour_only.db3", _texture(3), None)
    with pytest.raises(RecordingError, match="no depth stream"):
        read_recording(tmp_path / "colour_only.db3")


class FakeProfile:
    def __init__(self, kind, fmt, w, h, fps):
        self._kind, self._fmt, self._w, self._h, self._fps = kind, fmt, w, h, fps

    def stream_type(self):
        return self._kind

    def format(self):
        return self._fmt

    def fps(self):
        return self._fps

    def is_video_stream_profile(self):
        return True

    def as_video_stream_profile(self):
        return self

    def width(self):
        return self._w

    def height(self):
        return self._h


class FakeSensor:
    def __init__(self, profiles):
        self._profiles = profiles

    def get_stream_profiles(self):
        return self._profiles


class FakeDevice:
    def __init__(self, usb, color_modes, depth_modes):
        self.info = {rs.camera_info.name: "Intel RealSense D415", rs.camera_info.serial_number: "42",
                     rs.camera_info.usb_type_descriptor: usb}  # fmt: skip
        self.sensors = [
            FakeSensor([FakeProfile(rs.stream.depth, rs.format.z16, *m) for m in depth_modes]),
            FakeSensor([FakeProfile(rs.stream.color, rs.format.rgb8, *m) for m in color_modes]),
        ]

    def supports(self, info):
        return info in self.info

    def get_info(self, info):
        return self.info[info]

    def query_sensors(self):
        return self.sensors


def _fake_context(monkeypatch, devices):
    class FakeContext:
        def query_devices(self):
            return devices

    monkeypatch.setattr(rs, "context", FakeContext)


D415_COLOR = [(1920, 1080, 30), (1280, 720, 30), (1280, 720, 15), (640, 480, 30)]
D415_DEPTH = [(1280, 720, 30), (848, 480, 30), (640, 360, 30)]


def test_no_camera(monkeypatch, capsys):
    _fake_context(monkeypatch, [])
    with pytest.raises(RecordingError, match="no RealSense camera found.*USB 3.*o3d-mvps convert"):
        record_capture(frames=2, progress=False)
    assert cli_main(["record", str(os.devnull + "_out")]) == 1
    assert "no RealSense camera found" in capsys.readouterr().err


def test_wrong_serial(monkeypatch):
    _fake_context(monkeypatch, [FakeDevice("3.2", D415_COLOR, D415_DEPTH)])
    assert find_device("42").get_info(rs.camera_info.serial_number) == "42"
    with pytest.raises(RecordingError, match="serial 7.*connected: 42"):
        find_device("7")


def test_usb2_too_slow(monkeypatch):
    _fake_context(monkeypatch, [FakeDevice("2.1", D415_COLOR, D415_DEPTH)])
    with pytest.raises(RecordingError, match=r"USB 2\.1, too slow.*USB 3 port"):
        record_capture(frames=2, progress=False)
    with pytest.raises(RecordingError, match="USB 2 link offers fewer modes"):  # slow enough, but not offered
        check_modes(find_device(), (640, 480), (640, 360), 6)


def test_unsupported_resolution_lists_supported_modes(monkeypatch):
    device = FakeDevice("3.2", D415_COLOR, D415_DEPTH)
    check_modes(device, (1280, 720), (640, 360), 30)
    with pytest.raises(RecordingError, match=r"colour at 1024x768.*1920x1080 @ 30 fps, 1280x720 @ 15/30 fps"):
        check_modes(device, (1024, 768), (640, 360), 30)
    with pytest.raises(RecordingError, match=r"depth at 320x240 and 30 fps.*848x480 @ 30 fps"):
        check_modes(device, (1280, 720), (320, 240), 30)
    _fake_context(monkeypatch, [device])
    with pytest.raises(RecordingError, match="does not stream colour at 1280x720 and 60 fps"):
        record_capture(frames=2, fps=60, progress=False)


# --------------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------------
def test_cli_convert(recorded, tmp_path, monkeypatch):
    from o3d_mvps.cli import record as cli_record

    written = {}
    def fake_write(capture, path, overwrite=False):
        written.update(c=capture, p=path, o=overwrite)

    monkeypatch.setattr(cli_record, "write_capture", fake_write)
    out = tmp_path / "capture"
    assert cli_main(["--quiet", "convert", str(recorded[0]), str(out), "--frames", "3", "--overwrite"]) == 0
    assert written["c"].n_frames == 3 and str(written["p"]) == str(out) and written["o"] is True
    assert cli_main(["convert", str(tmp_path / "nope.db3"), str(out)]) == 1


def test_cli_parsers():
    from o3d_mvps.cli import build_parser

    parser = build_parser()
    args = parser.parse_args(["record", "out", "--frames", "5", "--color", "1280x720", "--depth", "848x480",
                              "--on-key", "--emitter", "off", "--exposure", "8000"])  # fmt: skip
    assert args.color == (1280, 720) and args.depth == (848, 480) and args.on_key and args.emitter == "off"
    assert args.light == "led"  # the product's camera carries an LED
    assert parser.parse_args(["convert", "in.bag", "out"]).light is None
    with pytest.raises(SystemExit):
        parser.parse_args(["record", "out", "--interval", "1", "--on-key"])
    with pytest.raises(SystemExit):
        parser.parse_args(["record", "out", "--color", "big"])
    args = parser.parse_args(["convert", "in.bag", "out", "--stride", "3", "--scale-factor", "4"])
    assert args.stride == 3 and args.scale_factor == 4


def test_convert_writes_a_readable_capture(recorded, tmp_path):
    from o3d_mvps.capture import read_capture

    out = tmp_path / "capture"
    assert cli_main(["--quiet", "convert", str(recorded[0]), str(out), "--frames", "3"]) == 0
    capture = read_capture(out)
    meta = capture.metadata["realsense"]
    assert capture.n_frames == 3 and capture.depth_size == (DH, DW) and meta["serial"] == "000123"
    assert capture.sensor == "Intel RealSense D415 (serial 000123)"
    k = meta["frame_numbers"][0]
    np.testing.assert_allclose(capture.depth_array(0), recorded[2][k] * UNITS, atol=1e-6)  # whole mm survive PNG
    assert cli_main(["--quiet", "convert", str(recorded[0]), str(out)]) == 1  # exists, no --overwrite
    assert capture.light is None  # not said: refine assumes the LED and warns
    assert cli_main(["--quiet", "convert", str(recorded[0]), str(out), "--frames", "3", "--light", "room",
                     "--overwrite"]) == 0  # fmt: skip
    assert read_capture(out).light == "room"


@pytest.mark.parametrize("light, model", [("room", "room"), ("led", "led")])
def test_convert_light_reaches_refines_light_model(recorded, tmp_path, light, model):
    """End to end: convert --light writes capture.json's "light", read_capture returns it, and
    refine's front end (problem_from_capture, which hands the solver its options) picks the light
    model from it without the "does not say what lit it" warning (a dropped light gives "led" and warns)."""
    import json
    import warnings

    from o3d_mvps import RefineOptions
    from o3d_mvps.capture import read_capture
    from o3d_mvps.solving import problem_from_capture

    out = tmp_path / "capture"
    assert cli_main(["--quiet", "convert", str(recorded[0]), str(out), "--frames", "3", "--light", light]) == 0
    assert json.loads((out / "capture.json").read_text())["light"] == light
    capture = read_capture(out)
    assert capture.light == light
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        problem, _ = problem_from_capture(capture, RefineOptions(progress=False),
                                          initial_poses=np.tile(np.eye(4), (capture.n_frames, 1, 1)))
    assert problem.options.light_model == model
    assert not [w for w in caught if "what lit it" in str(w.message)]


def test_light_is_checked_before_reading(tmp_path):
    from o3d_mvps.errors import CaptureError

    with pytest.raises(CaptureError, match="light must be one of 'led', 'room'.*got 'flash'"):
        read_recording(tmp_path / "missing.db3", light="flash")  # the light is refused, not the missing file
    with pytest.raises(CaptureError, match="light must be one of"):
        record_capture(frames=2, light="sun", progress=False)  # before looking for a camera
