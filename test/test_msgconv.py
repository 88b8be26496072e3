"""Message <-> numpy conversions, checked through real CDR serialisation where it matters."""

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, PointCloud2
from visualization_msgs.msg import Marker

from ooi_seg_ros import msgconv
from ooi_seg_ros.core.geometry import look_at
from ooi_seg_ros.core.types import CameraIntrinsics, InputError, SfmCloud, TriMesh, View

RNG = np.random.default_rng(0)
RGB = RNG.integers(0, 256, (5, 7, 3), dtype=np.uint8)


def _cdr(msg):
    return deserialize_message(serialize_message(msg), type(msg))


def _img(encoding, arr, step=None, bigendian=0):
    h, w = arr.shape[:2]
    raw = np.ascontiguousarray(arr)
    row = raw.reshape(h, -1).view(np.uint8)
    step = step or row.shape[1]
    pad = np.zeros((h, step - row.shape[1]), np.uint8)
    data = np.concatenate([row, pad], axis=1).tobytes()
    return Image(height=h, width=w, encoding=encoding, is_bigendian=bigendian, step=step,
                 data=data)


def test_stamps():
    for ns in (0, 1, 1_700_000_000_123_456_789, -1):
        assert msgconv.stamp_to_ns(msgconv.ns_to_stamp(ns)) == ns
    t = msgconv.ns_to_stamp(1_500_000_001)
    assert (t.sec, t.nanosec) == (1, 500_000_001)


@pytest.mark.parametrize("enc,make", [
    ("rgb8", lambda x: x), ("bgr8", lambda x: x[..., ::-1]),
    ("rgba8", lambda x: np.dstack([x, np.full(x.shape[:2], 9, np.uint8)])),
    ("bgra8", lambda x: np.dstack([x[..., ::-1], np.full(x.shape[:2], 9, np.uint8)]))])
def test_color_encodings_to_rgb(enc, make):
    msg = _cdr(_img(enc, make(RGB)))
    assert np.array_equal(msgconv.image_to_rgb(msg), RGB)
    padded = _cdr(_img(enc, make(RGB), step=RGB.shape[1] * make(RGB).shape[2] + 3))
    assert np.array_equal(msgconv.image_to_rgb(padded), RGB)


def test_mono_encodings_and_masks():
    g = RGB[..., 0]
    out = msgconv.image_to_rgb(_cdr(_img("mono8", g)))
    assert np.array_equal(out, np.repeat(g[..., None], 3, 2))
    g16 = g.astype(np.uint16) * 256 + 7
    assert np.array_equal(msgconv.image_to_rgb(_cdr(_img("mono16", g16)))[..., 1], g)
    big = _img("mono16", g16.astype(">u2"), bigendian=1)
    assert np.array_equal(msgconv.image_to_rgb(big)[..., 2], g)
    mask = g > 128
    m = _cdr(msgconv.mask_to_image(mask, 5, "cam"))
    assert m.encoding == "mono8" and m.header.frame_id == "cam"
    assert np.array_equal(msgconv.image_to_mask(m), mask)
    with pytest.raises(InputError, match="mono8"):
        msgconv.image_to_mask(msgconv.rgb_to_image(RGB, 0))


def test_image_validation():
    good = msgconv.rgb_to_image(RGB, 1)
    short = _img("rgb8", RGB)
    short.data = bytes(short.data)[:-5]
    with pytest.raises(InputError, match="truncated"):
        msgconv.image_to_rgb(short)
    bad_step = _img("rgb8", RGB)
    bad_step.step = 7 * 3 - 1
    with pytest.raises(InputError, match="step"):
        msgconv.image_to_rgb(bad_step)
    for enc in ("bayer_rggb8", "32FC1", "yuv422"):
        m = _img("rgb8", RGB)
        m.encoding = enc
        with pytest.raises(InputError, match="rgb8"):
            msgconv.image_to_rgb(m)
    assert np.array_equal(msgconv.image_to_rgb(_cdr(good)), RGB)
    with pytest.raises(InputError):
        msgconv.rgb_to_image(RGB.astype(np.float32), 0)


def test_compressed_images():
    png = _cdr(msgconv.rgb_to_compressed(RGB, 3))
    assert isinstance(png, CompressedImage) and png.format == "png"
    assert np.array_equal(msgconv.compressed_to_rgb(png), RGB)
    smooth = np.repeat(np.linspace(0, 255, 32, dtype=np.uint8)[None, :, None], 3, 2)
    smooth = np.repeat(smooth, 16, 0)
    jpg = msgconv.rgb_to_compressed(smooth, 3, fmt="jpeg", quality=95)
    assert np.abs(msgconv.compressed_to_rgb(jpg).astype(int) - smooth).max() < 12
    assert msgconv.is_lossy(jpg) and not msgconv.is_lossy(png)
    jpg.data = b"\xff\xd8garbage"
    with pytest.raises(InputError, match="jpeg or png"):
        msgconv.compressed_to_rgb(jpg)


def test_camera_info_round_trip_and_validation():
    cam = CameraIntrinsics(640, 480, 500.0, 505.0, 319.5, 240.25, "plumb_bob",
                           np.array([-0.1, 0.01, 0.001, -0.002, 0.0]))
    msg = _cdr(msgconv.intrinsics_to_camera_info(cam, 7, "cam"))
    assert msg.k[0] == 500.0 and msg.p[0] == 500.0 and msg.distortion_model == "plumb_bob"
    back = msgconv.camera_info_to_intrinsics(msg)
    assert (back.width, back.height, back.fx, back.fy, back.cx, back.cy) == \
        (640, 480, 500.0, 505.0, 319.5, 240.25)
    assert np.allclose(back.dist, cam.dist)
    plain = msgconv.camera_info_to_intrinsics(
        msgconv.intrinsics_to_camera_info(CameraIntrinsics(8, 6, 5, 5, 3.5, 2.5), 0))
    assert plain.distortion_model == "none" and not plain.has_distortion
    with pytest.raises(InputError, match="all zeros"):
        msgconv.camera_info_to_intrinsics(CameraInfo(width=640, height=480))
    bad = msgconv.intrinsics_to_camera_info(cam, 0)
    bad.distortion_model = "fisheye_weird"
    with pytest.raises(InputError, match="distortion model"):
        msgconv.camera_info_to_intrinsics(bad)


def test_pose_round_trip_and_validation():
    pose = look_at(np.array([1.0, 2.0, 3.0]), np.array([0.0, 0.0, 0.5]))
    msg = _cdr(msgconv.pose_to_pose_stamped(pose, 11, "map"))
    stamp, back = msgconv.pose_stamped_to_pose(msg)
    assert stamp == 11 and msg.header.frame_id == "map"
    assert np.allclose(back.R, pose.R, atol=1e-12) and np.allclose(back.t, pose.t)
    msg.pose.orientation.w = 3.0
    with pytest.raises(InputError, match="quaternion"):
        msgconv.pose_from_msg(msg.pose)
    msg.pose.position.x = float("nan")
    with pytest.raises(InputError, match="NaN"):
        msgconv.pose_from_msg(msg.pose)


def test_pointcloud_xyzrgb_and_extra_fields():
    xyz = RNG.normal(size=(20, 3))
    rgb = RNG.integers(0, 256, (20, 3), dtype=np.uint8)
    extra = {"opacity": RNG.random(20), "scale_0": RNG.random(20), "f_dc_0": RNG.random(20)}
    msg = _cdr(msgconv.xyzrgb_to_pointcloud2(xyz, rgb, 4, "map", extra=extra))
    assert isinstance(msg, PointCloud2)
    assert [f.name for f in msg.fields] == ["x", "y", "z", "rgb", "opacity", "scale_0", "f_dc_0"]
    assert msg.point_step == 28 and msg.width == 20
    bx, brgb = msgconv.pointcloud2_to_xyzrgb(msg)
    assert np.allclose(bx, xyz.astype(np.float32)) and np.array_equal(brgb, rgb)
    f = msgconv.pointcloud2_to_fields(msg, ["opacity"])
    assert np.allclose(f["opacity"], extra["opacity"].astype(np.float32))
    # RViz's packed colour: red is 0x00FF0000 in the float's bits
    assert msgconv.pack_rgb(np.array([[255, 0, 0]])).view(np.uint32)[0] == 0x00FF0000
    empty = msgconv.xyzrgb_to_pointcloud2(np.zeros((0, 3)), None, 0)
    assert msgconv.pointcloud2_to_xyzrgb(empty)[0].shape == (0, 3)
    with pytest.raises(InputError, match="no field"):
        msgconv.pointcloud2_to_fields(msg, ["intensity"])


def test_sfm_cloud_with_observations_round_trip():
    cam = CameraIntrinsics(8, 6, 5, 5, 3.5, 2.5)
    views = [View(str(s), s, cam, None) for s in (10, 2_000_000_020, 30)]
    xyz = RNG.normal(size=(4, 3))
    ptr = np.array([0, 2, 2, 5, 6])
    ov = np.array([0, 1, 0, 1, 2, 2], np.int32)
    oxy = RNG.random((6, 2)).astype(np.float32)
    cloud = SfmCloud(xyz, np.zeros((4, 3), np.uint8), np.array([0.1, 0.2, 0.3, 0.4]), ptr, ov,
                     oxy, views)
    pts = _cdr(msgconv.sfm_cloud_to_pointcloud2(cloud, 0))
    obs = _cdr(msgconv.observations_to_pointcloud2(cloud, 0))
    back = msgconv.pointcloud2_to_sfm_cloud(pts, obs, views)
    assert np.array_equal(back.obs_ptr, ptr) and np.array_equal(back.obs_view, ov)
    assert np.allclose(back.obs_xy, oxy) and np.allclose(back.error, cloud.error)
    # a receiver that knows only some views keeps only their observations
    part = msgconv.pointcloud2_to_sfm_cloud(pts, obs, views[:2])
    assert part.track_lengths().tolist() == [2, 0, 2, 0]
    assert len(msgconv.pointcloud2_to_sfm_cloud(pts, None, views).obs_view) == 0


def test_mesh_marker():
    mesh = TriMesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]]),
                   np.array([[0, 1, 2], [0, 2, 3]], np.int32))
    m = _cdr(msgconv.mesh_to_marker(mesh, 3, "map"))
    assert isinstance(m, Marker) and m.type == Marker.TRIANGLE_LIST and len(m.points) == 6
    back = msgconv.marker_to_mesh(m)
    assert np.allclose(back.vertices[back.triangles[1]], mesh.vertices[mesh.triangles[1]])


def test_organised_cloud_with_row_padding_and_truncation():
    xyz = np.arange(12, dtype=float).reshape(4, 3)
    flat = msgconv.xyzrgb_to_pointcloud2(xyz, None, 0)
    org = msgconv.xyzrgb_to_pointcloud2(xyz, None, 0)
    org.height, org.width, org.row_step = 2, 2, 2 * 12 + 4
    raw = bytes(flat.data)
    org.data = raw[:24] + b"\x00" * 4 + raw[24:] + b"\x00" * 4
    got, _ = msgconv.pointcloud2_to_xyzrgb(_cdr(org))
    assert np.array_equal(got, xyz)
    flat.data = raw[:-3]
    with pytest.raises(InputError, match="truncated"):
        msgconv.pointcloud2_to_xyzrgb(flat)
