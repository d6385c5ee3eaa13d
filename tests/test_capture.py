"""Capture folder reading/writing and validation (o3d_mvps.capture)."""

import json
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pytest

from helpers import snapshot

from o3d_mvps.capture import writing as capture_writing
from o3d_mvps import fileio
from o3d_mvps.capture import (
    Capture,
    GroundTruth,
    default_depth_intrinsic,
    image_from_array,
    read_capture,
    validate_capture,
    write_capture,
)
from o3d_mvps.colour import srgb_to_linear
from o3d_mvps.errors import CaptureError, OutputExistsError

H, W, SF, N = 24, 32, 2, 3
K = np.array([[30.7, 0.0, 15.3], [0.0, 31.1, 11.9], [0.0, 0.0, 1.0]])


def make_capture(encoding="srgb", bits=8, seed=0) -> Capture:
    """A 3-frame 32x24 capture (depth 16x12) with masks and ground truth, exactly representable."""
    rng = np.random.default_rng(seed)
    top = 2**bits - 1
    color = []
    for _ in range(N):
        levels = rng.integers(0, top + 1, size=(H, W, 3)) / top
        color.append(image_from_array(srgb_to_linear(levels) if encoding == "srgb" else levels.astype(np.float32)))
    depth = []
    for _ in range(N):
        mm = rng.integers(550, 650, size=(H // SF, W // SF, 1))
        mm[0, :3] = 0  # missing measurements
        depth.append(image_from_array((mm / 1000.0).astype(np.float32)))
    mask = np.zeros((H, W, 1), np.uint8)
    mask[5:15, 8:20] = 255
    gt = GroundTruth(
        depth=rng.uniform(0.5, 0.7, (H, W)).astype(np.float32),
        normals=rng.normal(size=(H, W, 3)).astype(np.float32),
        albedo=rng.uniform(0, 1, (H, W, 3)).astype(np.float32),
        poses=np.tile(np.eye(4), (N, 1, 1)) + rng.normal(scale=1e-3, size=(N, 4, 4)),
        light={"model": "directional", "sh": rng.normal(size=(N, 4)).tolist()},
        mesh_to_reference=np.eye(4) + rng.normal(scale=0.1, size=(4, 4)),
    )
    depth_K = default_depth_intrinsic(K, SF) + np.array([[0.01, 0, 0.02], [0, 0.03, 0.04], [0, 0, 0]])
    return Capture(
        color=color,
        depth=depth,
        color_intrinsic=o3d.core.Tensor(K),
        depth_intrinsic=o3d.core.Tensor(depth_K),
        masks=[image_from_array(mask), None, image_from_array(mask[::-1].copy())],
        depth_scale=1000.0,
        depth_trunc=2.5,
        color_encoding=encoding,
        sensor="D415 test",
        groundtruth=gt,
        metadata={"color_bit_depth": bits, "led_offset_m": [0.03, 0.0, 0.0], "note": "synthetic"},
    )


@pytest.fixture
def folder(tmp_path) -> Path:
    """A written capture folder."""
    path = tmp_path / "capture"
    write_capture(make_capture(), path)
    return path


def siblings(path: Path) -> list:
    return sorted(p.name for p in path.parent.iterdir())


def edit_json(path: Path, **fields) -> None:
    data = json.loads(path.read_text())
    data.update(fields)
    path.write_text(json.dumps(data))


# --- round trip --------------------------------------------------------------------------


@pytest.mark.parametrize("encoding, bits", [("srgb", 8), ("linear", 8), ("srgb", 16), ("linear", 16)])
def test_round_trip_reproduces_every_array(tmp_path, encoding, bits):
    original = make_capture(encoding, bits)
    write_capture(original, str(tmp_path / "out"))
    back = read_capture(str(tmp_path / "out"))

    assert back.n_frames == N and back.color_size == (H, W) and back.depth_size == (H // SF, W // SF)
    for i in range(N):
        np.testing.assert_array_equal(back.color_array(i), original.color_array(i))
        np.testing.assert_allclose(back.depth_array(i), original.depth_array(i), rtol=0, atol=1e-3)
        # kept as the files' codes (a quarter of float32's memory at 8 bits), written back as they were
        assert back.color[i].as_tensor().numpy().dtype == (np.uint8 if bits == 8 else np.uint16)
        np.testing.assert_array_equal(back.color_codes(i), capture_writing._encode_color(
            original.color_array(i), encoding, bits))
    assert back.mask_array(1) is None
    for i in (0, 2):
        np.testing.assert_array_equal(back.masks[i].as_tensor().numpy(), original.masks[i].as_tensor().numpy())
    np.testing.assert_allclose(back.color_K(), original.color_K(), rtol=0, atol=1e-9)
    np.testing.assert_allclose(back.depth_K(), original.depth_K(), rtol=0, atol=1e-9)
    gt, gt0 = back.groundtruth, original.groundtruth
    for name in ("depth", "normals", "albedo", "poses", "mesh_to_reference"):
        np.testing.assert_array_equal(getattr(gt, name), getattr(gt0, name))
        assert getattr(gt, name).dtype == getattr(gt0, name).dtype
    assert gt.light == gt0.light
    settings = (back.depth_scale, back.depth_trunc, back.color_encoding, back.sensor)
    assert settings == (1000.0, 2.5, encoding, "D415 test")
    assert back.metadata == original.metadata


def test_written_files_follow_the_folder_format(folder):
    assert sorted(p.name for p in (folder / "color").iterdir()) == ["000000.png", "000001.png", "000002.png"]
    assert sorted(p.name for p in (folder / "mask").iterdir()) == ["000000.png", "000002.png"]
    depth = cv2.imread(str(folder / "depth" / "000000.png"), cv2.IMREAD_UNCHANGED)
    assert depth.dtype == np.uint16 and depth.shape == (H // SF, W // SF)
    color = cv2.imread(str(folder / "color" / "000000.png"), cv2.IMREAD_UNCHANGED)
    assert color.dtype == np.uint8 and color.shape == (H, W, 3)
    intrinsic = o3d.io.read_pinhole_camera_intrinsic(str(folder / "intrinsic.json"))
    assert (intrinsic.width, intrinsic.height) == (W, H)
    np.testing.assert_allclose(intrinsic.intrinsic_matrix, K, rtol=0, atol=1e-12)
    settings = json.loads((folder / "capture.json").read_text())
    assert settings["frames"] == N and settings["depth_scale"] == 1000 and settings["color_encoding"] == "srgb"


def test_reads_open3d_written_folder_with_defaults(tmp_path):
    """No capture.json, no depth_intrinsic.json, no masks, colour in BGR-stored PNGs written by Open3D."""
    root = tmp_path / "o3d"
    (root / "color").mkdir(parents=True)
    (root / "depth").mkdir()
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[..., 0] = 255  # pure red
    for i in range(2):
        o3d.t.io.write_image(str(root / "color" / f"{i:06d}.png"), image_from_array(rgb))
        depth = np.full((H // 4, W // 4), 600, np.uint16)
        o3d.t.io.write_image(str(root / "depth" / f"{i:06d}.png"), image_from_array(depth))
    o3d.io.write_pinhole_camera_intrinsic(str(root / "intrinsic.json"), o3d.camera.PinholeCameraIntrinsic(W, H, K))

    with pytest.raises(CaptureError, match="automatic object mask of frame 0 is empty"):
        read_capture(root)  # no mask/: automatic masks, and a flat depth holds nothing but a wall
    capture = read_capture(root, mask="none")

    np.testing.assert_array_equal(capture.color_array(1)[0, 0], [1.0, 0.0, 0.0])
    np.testing.assert_allclose(capture.depth_array(0), 0.6, rtol=1e-6)
    assert capture.scale_factor == 4 and capture.masks is None
    assert (capture.depth_scale, capture.color_encoding, capture.metadata["color_bit_depth"]) == (1000.0, "srgb", 8)
    np.testing.assert_allclose(capture.depth_K(), default_depth_intrinsic(K, 4), rtol=0, atol=1e-12)


def test_single_frame_capture_round_trips(tmp_path):
    one = make_capture().select([0])
    write_capture(one, tmp_path / "one")
    assert read_capture(tmp_path / "one").n_frames == 1


def test_coded_capture_writes_its_codes_and_refuses_mixed_frames(tmp_path, folder):
    """A capture read from files writes its codes back unchanged (a second round trip changes no
    file); integer colour other than uint8/uint16 codes, or codes mixed with float frames, is refused."""
    back = read_capture(folder)
    assert back.color_codes(0).dtype == np.uint8 and back.color_codes(0).shape == (H, W, 3)
    write_capture(back, tmp_path / "again")
    for i in range(N):
        again = cv2.imread(str(tmp_path / "again" / "color" / f"{i:06d}.png"), cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(again[..., ::-1], back.color_codes(i))
    float_frame = image_from_array(back.color_array(1))
    with pytest.raises(CaptureError, match=r"mix float32 \(first: frame 1 \(000001.png\)\) and uint8 \(first: frame 0 "
                                           r"\(000000.png\)\); give every frame as codes of one bit depth"):
        validate_capture(replace(back, color=[back.color[0], float_frame, back.color[2]]),
                         frame_names=back.frame_names)
    with pytest.raises(CaptureError, match="integer colour must be uint8 or uint16 codes"):
        validate_capture(replace(back, color=[image_from_array(back.color_codes(i).astype(np.int32))
                                              for i in range(N)]))
    assert make_capture().color_codes(0) is None  # float frames
    # a folder whose frame 2 was saved as 16-bit: named by its file before any work
    frame = cv2.imread(str(folder / "color" / "000002.png"), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(folder / "color" / "000002.png"), frame.astype(np.uint16) * 257)
    with pytest.raises(CaptureError, match=r"color mixes 8-bit frames \(first: 000000.png\) and 16-bit frames "
                                           r"\(first: 000002.png\); save every colour frame at one bit depth"):
        read_capture(folder)


def test_reference_only_keeps_frame_0_and_the_whole_ground_truth(capture_dir):
    """Capture.reference_only: frame 0's images (the same objects, not copies), names and ids,
    and the ground truth untouched (its poses still index every frame); read_groundtruth reads
    the same ground truth as read_capture, and None from a folder without one."""
    from o3d_mvps.capture.reading import read_groundtruth

    capture = read_capture(capture_dir)
    one = capture.reference_only()
    assert capture.n_frames > 1 and one.n_frames == 1
    assert one.color[0] is capture.color[0] and one.depth[0] is capture.depth[0] and one.masks[0] is capture.masks[0]
    assert one.frame_names == capture.frame_names[:1] and one.groundtruth is capture.groundtruth
    assert len(one.groundtruth.poses) == capture.n_frames
    again = read_groundtruth(capture_dir, capture.n_frames, capture.color_size)
    for name in ("depth", "normals", "albedo", "poses"):
        assert np.array_equal(getattr(again, name), getattr(capture.groundtruth, name)), name
    assert read_groundtruth(capture_dir / "color", capture.n_frames, capture.color_size) is None


# --- bad folders -------------------------------------------------------------------------


def test_read_missing_path(tmp_path):
    with pytest.raises(CaptureError, match="does not exist; check the path"):
        read_capture(tmp_path / "nope")


def test_read_path_is_a_file(tmp_path):
    (tmp_path / "file.txt").write_text("x")
    with pytest.raises(CaptureError, match="is a file, not a capture folder"):
        read_capture(tmp_path / "file.txt")


@pytest.mark.parametrize("sub", ["color", "depth"])
def test_read_missing_frame_folder(folder, sub):
    for p in (folder / sub).iterdir():
        p.unlink()
    (folder / sub).rmdir()
    with pytest.raises(CaptureError, match=rf"{sub} is missing; a capture folder needs color/ and depth/"):
        read_capture(folder)


def test_read_no_frames(folder):
    for sub in ("color", "depth"):
        for p in (folder / sub).iterdir():
            p.unlink()
    with pytest.raises(CaptureError, match="holds no frames; add"):
        read_capture(folder)


def test_read_missing_intrinsic(folder):
    (folder / "intrinsic.json").unlink()
    with pytest.raises(CaptureError, match="intrinsic.json is missing; write the camera intrinsics"):
        read_capture(folder)


@pytest.mark.parametrize("name", ["intrinsic.json", "depth_intrinsic.json"])
def test_read_malformed_intrinsic(folder, name):
    (folder / name).write_text('{"width": 32, "height"')
    with pytest.raises(CaptureError, match=rf"cannot read .*/{name} \(.*fix or rewrite the JSON"):
        read_capture(folder)
    (folder / name).write_text('{"width": 32, "height": 24, "intrinsic_matrix": [1, 2, 3]}')
    message = rf"/{name} is not an Open3D PinholeCameraIntrinsic JSON.*write_pinhole_camera_intrinsic"
    with pytest.raises(CaptureError, match=message):
        read_capture(folder)


def test_read_intrinsic_with_nan(folder):
    edit_json(folder / "intrinsic.json", intrinsic_matrix=[float("nan")] + [0.0] * 7 + [1.0])
    with pytest.raises(CaptureError, match="intrinsic.json: intrinsics must be a finite 3x3 matrix"):
        read_capture(folder)


def test_read_intrinsic_for_other_size(folder):
    edit_json(folder / "intrinsic.json", width=64, height=48)
    with pytest.raises(CaptureError, match="is for 64x48 images but color/ frames are 32x24"):
        read_capture(folder)


def test_read_frame_count_mismatch(folder):
    (folder / "depth" / "000002.png").unlink()
    with pytest.raises(CaptureError, match=r"color/ has 3 frames and depth/ has 2; missing: \S*depth/000002.png "
                                           r"\(for \S*color/000002.png\)"):
        read_capture(folder)


def test_read_frame_name_mismatch(folder):
    (folder / "depth" / "000002.png").rename(folder / "depth" / "000009.png")
    with pytest.raises(CaptureError, match=r"missing: \S*depth/000002.png \(for \S*color/000002.png\), "
                                           r"\S*color/000009.png \(for \S*depth/000009.png\)"):
        read_capture(folder)


def test_read_frames_field_mismatch(folder):
    edit_json(folder / "capture.json", frames=5)
    with pytest.raises(CaptureError, match="says 5 frames but color/ has 3"):
        read_capture(folder)


def test_read_unknown_encoding(folder):
    edit_json(folder / "capture.json", color_encoding="gamma22")
    with pytest.raises(CaptureError, match="color_encoding 'gamma22' is unknown; use one of"):
        read_capture(folder)


def test_read_colour_sizes_differ(folder):
    cv2.imwrite(str(folder / "color" / "000001.png"), np.zeros((H // 2, W // 2, 3), np.uint8))
    with pytest.raises(CaptureError, match=r"colour frame 1 \(000001\) is 16x12 but frame 0 \(000000\) is 32x24"):
        read_capture(folder)


def test_read_depth_sizes_differ(folder):
    cv2.imwrite(str(folder / "depth" / "000002.png"), np.full((4, 4), 600, np.uint16))
    with pytest.raises(CaptureError, match=r"depth frame 2 \(000002\) is 4x4 but frame 0 \(000000\) is 16x12"):
        read_capture(folder)


def test_read_depth_not_colour_over_sf(folder):
    for i in range(N):
        cv2.imwrite(str(folder / "depth" / f"{i:06d}.png"), np.full((7, 10), 600, np.uint16))
    with pytest.raises(CaptureError, match="depth is 10x7 but colour is 32x24.*integer multiple SF"):
        read_capture(folder)


def test_read_depth_in_wrong_unit(folder):
    edit_json(folder / "capture.json", depth_scale=1)
    message = r"median depth 5\d\d m is outside 0.05-20 m, so the unit looks wrong:"
    message += " depth_scale in capture.json is probably wrong"
    with pytest.raises(CaptureError, match=message):
        read_capture(folder)


def test_read_empty_mask(folder):
    cv2.imwrite(str(folder / "mask" / "000002.png"), np.zeros((H, W), np.uint8))
    with pytest.raises(CaptureError, match=r"mask of frame 2 \(000002\) has no object pixel; remove that mask"):
        read_capture(folder)


def test_read_mask_wrong_size(folder):
    cv2.imwrite(str(folder / "mask" / "000000.png"), np.full((H // 2, W // 2), 255, np.uint8))
    with pytest.raises(CaptureError, match=r"mask of frame 0 \(000000\) has shape \(12, 16\) but colour is 32x24"):
        read_capture(folder)


def test_read_mask_without_frame(folder):
    cv2.imwrite(str(folder / "mask" / "000007.png"), np.full((H, W), 255, np.uint8))
    with pytest.raises(CaptureError, match="000007.png has no colour frame of the same name"):
        read_capture(folder)


@pytest.mark.parametrize("sub", ["color", "depth", "mask"])
def test_read_corrupt_image(folder, sub):
    (folder / sub / "000000.png").write_bytes(b"\x89PNG not really")
    with pytest.raises(CaptureError, match=rf"cannot read image .*{sub}/000000.png \(corrupt"):
        read_capture(folder)


def test_read_8bit_depth(folder):
    cv2.imwrite(str(folder / "depth" / "000001.png"), np.full((H // SF, W // SF), 60, np.uint8))
    with pytest.raises(CaptureError, match="000001.png is uint8 .*single-channel 16-bit PNG"):
        read_capture(folder)


def test_read_greyscale_colour(folder):
    cv2.imwrite(str(folder / "color" / "000001.png"), np.full((H, W), 60, np.uint8))
    with pytest.raises(CaptureError, match="000001.png is uint8 with shape .*save colour as 8- or 16-bit RGB"):
        read_capture(folder)


@pytest.mark.parametrize("damage, problem", [
    ("corrupt", r"cannot read it \(.*"),
    ("partial", r"cannot read it \(.*normals.npy"),
    ("foreign", r"ground truth depth has shape \(5, 5\), expected \(24, 32\)"),
])
def test_unusable_groundtruth_is_reported_and_ignored(folder, damage, problem):
    gt = folder / "groundtruth"
    if damage == "corrupt":
        (gt / "poses.npy").write_bytes(b"junk")
    elif damage == "partial":  # a real capture's folder holding only depth.npy
        for p in gt.iterdir():
            if p.name != "depth.npy":
                p.unlink()
    else:
        np.save(gt / "depth.npy", np.zeros((5, 5), np.float32))
    with pytest.warns(UserWarning, match=rf"ignoring .*groundtruth: {problem}.*refinement goes on without it"):
        capture = read_capture(folder)
    assert capture.groundtruth is None
    np.testing.assert_array_equal(capture.color_array(0), make_capture().color_array(0))


# --- what real files get wrong ------------------------------------------------------------


def test_read_depth_in_whole_metres(folder):
    metres = np.random.default_rng(0).integers(0, 4, size=(H // SF, W // SF)).astype(np.uint16)  # float m cast
    cv2.imwrite(str(folder / "depth" / "000001.png"), metres)
    message = r"000001.png holds only the values 1..3: it looks like depth in metres stored as integers.*millimetres"
    with pytest.raises(CaptureError, match=message):
        read_capture(folder)


def test_read_depth_from_another_camera(folder):
    for i in range(N):  # a 640x480 depth camera beside a 1920x1080 colour camera, scaled down
        cv2.imwrite(str(folder / "depth" / f"{i:06d}.png"), np.full((9, 12), 600, np.uint16))
    message = r"depth is 12x9 but colour is 32x24.*integer multiple.*different cameras.*register_depth"
    with pytest.raises(CaptureError, match=message):
        read_capture(folder)


def test_read_intrinsics_of_a_resized_image(folder):
    edit_json(folder / "intrinsic.json", width=64, height=48)
    with pytest.raises(CaptureError, match=r"frames are 0.5 times that size.*scale the intrinsics by 0.5"):
        read_capture(folder)


def test_read_exif_rotated_jpeg(folder):
    from PIL import Image

    (folder / "color" / "000001.png").unlink()
    exif = Image.Exif()
    exif[0x0112] = 6  # "rotate 90 degrees clockwise to display"
    Image.fromarray(np.zeros((H, W, 3), np.uint8)).save(folder / "color" / "000001.jpg", exif=exif)
    message = r"000001.jpg carries EXIF orientation 6 .*clear the tag \(exiftool -Orientation=1 -n FILE\)"
    with pytest.raises(CaptureError, match=message):
        read_capture(folder)


def test_read_upright_jpeg(folder):
    from PIL import Image

    (folder / "color" / "000001.png").unlink()
    Image.fromarray(np.full((H, W, 3), 128, np.uint8)).save(folder / "color" / "000001.jpg", quality=100)
    assert read_capture(folder).color_size == (H, W)


def test_read_frame_without_depth(folder):
    cv2.imwrite(str(folder / "depth" / "000002.png"), np.zeros((H // SF, W // SF), np.uint16))
    with pytest.raises(CaptureError, match=r"depth frame 2 \(000002\) has no measurement at all.*remove the frame"):
        read_capture(folder)


# --- bad in-memory captures (write) ---------------------------------------------------------


def with_frame(images, i, array):
    images = list(images)
    images[i] = image_from_array(array)
    return images


def color_of(i=0):
    return make_capture().color_array(i)


def depth_of(i=0):
    return make_capture().depth_array(i)[..., None]


BAD_CAPTURES = {
    "empty": (lambda c: replace(c, color=[], depth=[], masks=None, groundtruth=None), "the capture has no frames"),
    "count": (lambda c: replace(c, depth=c.depth[:2]), "3 colour frames but 2 depth frames"),
    "no depth frames": (lambda c: replace(c, depth=[]), "3 colour frames but 0 depth frames"),
    "colour size": (
        lambda c: replace(c, color=with_frame(c.color, 1, color_of()[:12, :16])),
        r"colour frame 1 is 16x12 but frame 0 is 32x24",
    ),
    "depth size": (
        lambda c: replace(c, depth=with_frame(c.depth, 2, depth_of()[:6])),
        "depth frame 2 is 16x6 but frame 0 is 16x12",
    ),
    "scale factor": (
        lambda c: replace(c, depth=[image_from_array(depth_of()[:, :-1]) for _ in range(N)]),
        "depth is 15x12 but colour is 32x24",
    ),
    "colour NaN": (
        lambda c: replace(c, color=with_frame(c.color, 0, np.where(color_of() > 0.5, np.nan, color_of()))),
        "colour frame 0 contains NaN or inf",
    ),
    "depth inf": (
        lambda c: replace(c, depth=with_frame(c.depth, 1, np.where(depth_of() > 0.6, np.inf, depth_of()))),
        "depth frame 1 contains NaN or inf; replace them",
    ),
    "colour range": (
        lambda c: replace(c, color=with_frame(c.color, 2, color_of() * 255)),
        r"colour frame 2 has values in \[0, 255\]; colour must be linear RGB in \[0, 1\]",
    ),
    "negative depth": (
        lambda c: replace(c, depth=with_frame(c.depth, 0, -depth_of())),
        "depth must be metres >= 0",
    ),
    "millimetres": (
        lambda c: replace(c, depth=[image_from_array(depth_of() * 1000) for _ in range(N)]),
        r"frame 0: median depth 5\d\d m is outside 0.05-20 m.*in-memory depth is not in metres",
    ),
    "no depth": (
        lambda c: replace(c, depth=[image_from_array(depth_of() * 0) for _ in range(N)]),
        r"depth frame 0 has no measurement at all \(every pixel 0\)",
    ),
    "one frame without depth": (
        lambda c: replace(c, depth=with_frame(c.depth, 1, depth_of() * 0)),
        r"depth frame 1 has no measurement at all \(every pixel 0\): re-export that depth frame, or remove",
    ),
    "intrinsic NaN": (
        lambda c: replace(c, color_intrinsic=o3d.core.Tensor(np.where(K == 1, np.nan, K))),
        "the colour intrinsics: intrinsics must be a finite 3x3 matrix",
    ),
    "empty mask": (
        lambda c: replace(c, masks=[None, image_from_array(np.zeros((H, W, 1), np.uint8)), None]),
        "mask of frame 1 has no object pixel",
    ),
    "mask size": (
        lambda c: replace(c, masks=[image_from_array(np.full((H, W // 2, 1), 255, np.uint8)), None, None]),
        r"mask of frame 0 has shape \(24, 16\) but colour is 32x24",
    ),
    "mask count": (lambda c: replace(c, masks=c.masks[:1]), "3 frames but 1 masks; give one entry per frame"),
    "encoding": (lambda c: replace(c, color_encoding="rec709"), "color_encoding 'rec709' is unknown"),
    "bit depth": (
        lambda c: replace(c, metadata={"color_bit_depth": 12}),
        "color_bit_depth 12 is unsupported; use 8 or 16",
    ),
    "depth scale": (lambda c: replace(c, depth_scale=0.0), "depth_scale 0.0 must be a positive number"),
    "uint16 overflow": (
        lambda c: replace(c, depth_scale=10000.0, depth=[image_from_array(depth_of() * 15) for _ in range(N)]),
        "does not fit a uint16 PNG at depth_scale 10000; lower depth_scale",
    ),
    "metadata": (lambda c: replace(c, metadata={"when": object()}), "capture.metadata is not JSON-serialisable"),
    "groundtruth": (
        lambda c: replace(c, groundtruth=replace(c.groundtruth, poses=np.eye(4)[None])),
        r"ground truth poses has shape \(1, 4, 4\), expected \(3, 4, 4\)",
    ),
}


@pytest.mark.parametrize("case", sorted(BAD_CAPTURES))
def test_write_rejects_bad_capture(tmp_path, case):
    corrupt, message = BAD_CAPTURES[case]
    with pytest.raises(CaptureError, match=message):
        write_capture(corrupt(make_capture()), tmp_path / "out")
    assert siblings(tmp_path / "out") == []  # nothing written, no temporary folder


def test_validate_accepts_good_capture():
    validate_capture(make_capture())


# --- overwrite and atomicity -----------------------------------------------------------------


def test_overwrite_refused_keeps_earlier_output(folder):
    before = snapshot(folder)
    message = r"capture .* already exists and is not empty; pass overwrite=True to replace"
    with pytest.raises(OutputExistsError, match=message):
        write_capture(make_capture("linear", seed=1), folder)
    assert snapshot(folder) == before
    assert siblings(folder) == ["capture"]


def test_overwrite_true_replaces_output(folder):
    write_capture(make_capture("linear", seed=1), folder, overwrite=True)
    assert read_capture(folder).color_encoding == "linear"
    assert siblings(folder) == ["capture"]


def test_write_into_empty_existing_folder(tmp_path):
    (tmp_path / "out").mkdir()
    write_capture(make_capture(), tmp_path / "out")
    assert read_capture(tmp_path / "out").n_frames == N


def test_write_onto_a_file_refused(tmp_path):
    (tmp_path / "out").write_text("precious")
    with pytest.raises(OutputExistsError, match="is a file, not a capture folder; choose another output path"):
        write_capture(make_capture(), tmp_path / "out", overwrite=True)
    assert (tmp_path / "out").read_text() == "precious"


def failing_writer(monkeypatch, after: int):
    """Make the PNG writer raise on its (after+1)-th call."""
    real, calls = capture_writing._write_png, []

    def write(path, image):
        calls.append(path)
        if len(calls) > after:
            raise OSError("disk full (simulated)")
        real(path, image)

    monkeypatch.setattr(capture_writing, "_write_png", write)


def test_failed_write_leaves_nothing(tmp_path, monkeypatch):
    failing_writer(monkeypatch, after=3)
    with pytest.raises(OSError, match="disk full"):
        write_capture(make_capture(), tmp_path / "out")
    assert siblings(tmp_path / "out") == []


def test_failed_overwrite_keeps_old_output(folder, monkeypatch):
    before = snapshot(folder)
    failing_writer(monkeypatch, after=4)
    with pytest.raises(OSError, match="disk full"):
        write_capture(make_capture("linear", seed=1), folder, overwrite=True)
    assert snapshot(folder) == before
    assert siblings(folder) == ["capture"]


def test_failed_swap_restores_old_output(folder, monkeypatch):
    """If renaming the new folder into place fails, the old one is renamed back."""
    before, real_rename = snapshot(folder), fileio.os.rename

    def rename(src, dst):
        if ".tmp-" in str(src):
            raise OSError("rename failed (simulated)")
        real_rename(src, dst)

    monkeypatch.setattr(fileio.os, "rename", rename)
    with pytest.raises(OSError, match="rename failed"):
        write_capture(make_capture("linear", seed=1), folder, overwrite=True)
    assert snapshot(folder) == before
    assert siblings(folder) == ["capture"]


def test_read_reports_the_first_corrupt_frame(folder):
    """Frames are decoded on several threads; the error still names the first bad file in frame order."""
    for name in ("000001.png", "000002.png"):
        (folder / "color" / name).write_bytes(b"\x89PNG not really")
    with pytest.raises(CaptureError, match=r"cannot read image .*color/000001.png \(corrupt"):
        read_capture(folder)
