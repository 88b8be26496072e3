"""capture_io: bags, nerfstudio folders, COLMAP datasets and image folders into a Capture."""

import json
from pathlib import Path

import numpy as np
import pytest
from nav_msgs.msg import Odometry
from PIL import Image

from ooi_seg_ros import capture_io, msgconv
from ooi_seg_ros.bag import BagReader, BagWriter
from ooi_seg_ros.core.geometry import look_at
from ooi_seg_ros.core.types import CameraIntrinsics, Capture, InputError, Pose, View

T0 = 1_700_000_000_000_000_000
MS = 1_000_000
BONSAI = Path(__file__).resolve().parents[2] / "shared" / "data" / "mipnerf360-bonsai"


def _capture(n=4, w=32, h=24, dist=False, seed=0):
    rng = np.random.default_rng(seed)
    cam = CameraIntrinsics(w, h, 30.0, 31.0, (w - 1) / 2 + 0.25, (h - 1) / 2 - 0.5,
                           "plumb_bob" if dist else "none",
                           np.array([-0.05, 0.01, 0.001, 0.0, 0.0]) if dist else np.zeros(0))
    views = []
    yy, xx = np.mgrid[:h, :w]
    for i in range(n):
        a = 2 * np.pi * i / n
        pose = look_at(np.array([2 * np.cos(a), 2 * np.sin(a), 1.0]), np.zeros(3))
        img = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
        mask = (xx - w / 2 - i) ** 2 + (yy - h / 2) ** 2 < (h / 3) ** 2
        views.append(View(str(T0 + i * 100 * MS), T0 + i * 100 * MS, cam, pose, img, mask))
    return Capture(views=views, source="test", gt_ooi_points=rng.normal(size=(50, 3)) * 0.1,
                   meta={"scene": "unit", "n": np.int64(n)})


def _same(a: Capture, b: Capture, pose_atol=1e-9):
    assert len(a) == len(b)
    for va, vb in zip(a.views, b.views):
        assert va.stamp_ns == vb.stamp_ns
        assert np.array_equal(va.get_image(), vb.get_image())
        assert np.array_equal(va.gt_mask, vb.gt_mask)
        assert np.allclose(va.pose.matrix(), vb.pose.matrix(), atol=pose_atol)
        ca, cb = va.camera, vb.camera
        assert (ca.width, ca.height, ca.distortion_model) == (cb.width, cb.height,
                                                              cb.distortion_model)
        assert np.allclose([ca.fx, ca.fy, ca.cx, ca.cy], [cb.fx, cb.fy, cb.cx, cb.cy])
        assert np.allclose(ca.dist, cb.dist)
    assert np.allclose(a.gt_ooi_points, b.gt_ooi_points, atol=1e-6)


@pytest.mark.parametrize("compressed", [False, True])
def test_bag_round_trip_and_determinism(tmp_path, compressed):
    cap = _capture(dist=True)
    p1 = capture_io.write_capture_bag(cap, tmp_path / "a" / "cap.mcap", compressed=compressed)
    p2 = capture_io.write_capture_bag(cap, tmp_path / "b" / "cap.mcap", compressed=compressed)
    assert p1.read_bytes() == p2.read_bytes()
    back = capture_io.read_capture(p1)
    _same(cap, back)
    assert [v.key for v in back.views] == [str(v.stamp_ns) for v in cap.views]
    assert back.meta["scene"] == "unit" and back.meta["n"] == 4 and back.meta["dropped"] == {}
    assert not list(p1.parent.glob("*.part"))
    assert not any(v.compressed for v in back.views)  # png (or raw): lossless


def test_jpeg_bag_images_are_marked_compressed(tmp_path):
    """JPEG CompressedImage messages give views marked ``compressed`` (the refinement's
    ``hull_graph`` acts on those); the images decode at their size."""
    cap = _capture()
    p = capture_io.write_capture_bag(cap, tmp_path / "j.mcap", compressed=True,
                                     image_format="jpeg")
    back = capture_io.read_capture(p)
    assert len(back.views) == len(cap.views) and all(v.compressed for v in back.views)
    for a, b in zip(cap.views, back.views):
        assert a.get_image().shape == b.get_image().shape and a.key == b.key


def test_folder_round_trip(tmp_path):
    cap = _capture(dist=True)
    out = capture_io.write_capture(cap, tmp_path / "cap")
    data = json.loads((out / "transforms.json").read_text())
    assert data["camera_model"] == "OPENCV" and data["fl_x"] == 30.0
    assert data["cx"] == cap.views[0].camera.cx + 0.5  # nerfstudio's pixel-centre convention
    assert len(data["frames"]) == 4 and "transform_matrix" in data["frames"][0]
    back = capture_io.read_capture(out)
    _same(cap, back)
    assert [v.key for v in back.views] == [v.key for v in cap.views]
    # rewriting replaces the old capture; a non-capture folder is refused
    capture_io.write_capture(back, tmp_path / "cap")
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("keep me")
    with pytest.raises(InputError, match="not a capture folder"):
        capture_io.write_capture(cap, tmp_path / "other")


def _pose_image_bag(path, pose_dt_ms=33, pose_offset_ms=7, n_img=6, odometry=False,
                    mount=None):
    cam = CameraIntrinsics(16, 12, 15, 15, 7.5, 5.5)
    with BagWriter(path) as w:
        w.add_topic("/camera/image_raw", "sensor_msgs/msg/Image", "sensor_data")
        w.add_topic("/camera/camera_info", "sensor_msgs/msg/CameraInfo")
        ptopic = "/vehicle/odom" if odometry else "/camera/pose"
        w.add_topic(ptopic, "nav_msgs/msg/Odometry" if odometry
                    else "geometry_msgs/msg/PoseStamped")
        msgs = []
        for k in range(0, 40):
            t = T0 + (pose_offset_ms + k * pose_dt_ms) * MS
            pose = Pose(np.eye(3), np.array([k * 0.1, 0.0, 1.0]))
            if odometry:
                m = Odometry()
                m.header = msgconv.make_header(t, "map")
                m.pose.pose = msgconv.pose_to_msg(pose)
            else:
                m = msgconv.pose_to_pose_stamped(pose, t)
            msgs.append((t, ptopic, m))
        for i in range(n_img):
            t = T0 + (100 + 200 * i) * MS
            msgs.append((t, "/camera/image_raw",
                         msgconv.rgb_to_image(np.full((12, 16, 3), i, np.uint8), t)))
            msgs.append((t, "/camera/camera_info", msgconv.intrinsics_to_camera_info(cam, t)))
        for t, topic, m in sorted(msgs, key=lambda x: (x[0], x[1])):
            w.write(topic, m, t)
    return path


def test_bag_poses_interpolated_and_drops_counted(tmp_path):
    p = _pose_image_bag(tmp_path / "p.mcap", n_img=8)  # poses end at 7 + 39*33 = 1294 ms
    cap = capture_io.read_capture(p)
    assert len(cap) == 6 and cap.meta["dropped"] == {"no_pose_within_tolerance": 2}
    assert cap.meta["pose_tolerance_ns"] == int(1.5 * 33 * MS)
    for v in cap.views:
        ms = (v.stamp_ns - T0) / MS
        k = (ms - 7) / 33  # pose k has x = 0.1 k
        assert abs(v.pose.t[0] - 0.1 * k) < 1e-9
    tight = capture_io.read_capture(p, pose_tolerance_ns=10 * MS)
    assert len(tight) < 6 and sum(tight.meta["dropped"].values()) == 8 - len(tight)
    half = capture_io.read_capture(p, downscale=2)
    assert half.views[0].get_image().shape == (6, 8, 3) and half.views[0].camera.width == 8


def test_bag_odometry_with_mount(tmp_path):
    p = _pose_image_bag(tmp_path / "o.mcap", odometry=True, n_img=3)
    mount = Pose(np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float), np.array([0.2, 0, 0]))
    cap = capture_io.read_capture(p, mount=mount)
    assert cap.meta["pose_topic"] == "/vehicle/odom" and len(cap) == 3
    v = cap.views[0]
    k = (100 - 7) / 33
    assert np.allclose(v.pose.R, mount.R) and np.allclose(v.pose.t, [0.1 * k + 0.2, 0, 1.0])


def test_bad_bags(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        capture_io.read_capture(tmp_path / "none.mcap")
    # no camera_info topic
    p = tmp_path / "noinfo.mcap"
    with BagWriter(p) as w:
        w.write("/camera/image_raw", msgconv.rgb_to_image(np.zeros((4, 4, 3), np.uint8), 1), 1)
    with pytest.raises(InputError, match="/camera/camera_info"):
        capture_io.read_capture(p)
    # no image topic at all
    p = tmp_path / "noimg.mcap"
    with BagWriter(p) as w:
        w.write("/camera/camera_info", msgconv.intrinsics_to_camera_info(
            CameraIntrinsics(4, 4, 4, 4, 1.5, 1.5), 1), 1)
    with pytest.raises(InputError, match="image_topic"):
        capture_io.read_capture(p)
    # image whose size fields do not match its data, and a bayer image
    for name, fix, match in (("step", lambda m: setattr(m, "step", 5), "step"),
                             ("bayer", lambda m: setattr(m, "encoding", "bayer_rggb8"), "rgb8")):
        cap = _capture(n=2)
        good = tmp_path / f"{name}.mcap"
        capture_io.write_capture_bag(cap, good)
        bad = tmp_path / f"{name}_bad.mcap"
        r = BagReader(good)
        with BagWriter(bad) as w:
            for t, info in r.topics().items():
                w.add_topic(t, info.type, info.qos)
            for m in r.records():
                data = m.data
                if m.topic == "/camera/image_raw":
                    msg = r.decode(m.type, data)
                    fix(msg)
                    data = msg
                w.write(m.topic, data, m.log_time_ns)
        with pytest.raises(InputError, match=match):
            capture_io.read_capture(bad)
    # a truncated capture bag: only complete chunks, with a warning naming the damage
    cap = _capture(n=6, w=64, h=48)
    full = capture_io.write_capture_bag(cap, tmp_path / "full.mcap")
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(full.read_bytes()[:100])
    with pytest.raises(InputError, match="mcap recover|not a readable"):
        capture_io.read_capture(cut)


def test_failed_write_leaves_nothing(tmp_path):
    cap = _capture(n=3)
    cap.views[2].image = cap.views[2].image.astype(np.float32)  # cannot become rgb8
    with pytest.raises(InputError):
        capture_io.write_capture_bag(cap, tmp_path / "x.mcap")
    with pytest.raises(InputError, match="uint8"):
        capture_io.write_capture_folder(cap, tmp_path / "x")
    assert list(tmp_path.iterdir()) == []


def test_folder_write_is_deterministic(tmp_path):
    cap = _capture()
    a = capture_io.write_capture_folder(cap, tmp_path / "a")
    b = capture_io.write_capture_folder(cap, tmp_path / "b")
    fa = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert fa == sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    assert all((a / f).read_bytes() == (b / f).read_bytes() for f in fa)


def test_nerfstudio_folder_from_elsewhere(tmp_path):
    d = tmp_path / "ns"
    (d / "images").mkdir(parents=True)
    frames = []
    for i in range(3):
        Image.fromarray(np.full((20, 30, 3), 40 * i, np.uint8)).save(d / "images" / f"f{i}.jpg")
        pose = look_at(np.array([1.0 + i, 0, 1]), np.zeros(3))
        from ooi_seg_ros.core.geometry import pose_to_gl_c2w
        frames.append({"file_path": f"images/f{i}.jpg",
                       "transform_matrix": pose_to_gl_c2w(pose).tolist()})
    json.dump({"w": 30, "h": 20, "fl_x": 25.0, "fl_y": 25.0, "cx": 15.0, "cy": 10.0,
               "camera_model": "OPENCV", "k1": 0.0, "frames": frames},
              open(d / "transforms.json", "w"))
    cap = capture_io.read_capture(d / "transforms.json", downscale=2)
    assert [v.key for v in cap.views] == ["f0", "f1", "f2"]
    v = cap.views[1]
    assert v.camera.distortion_model == "none" and v.camera.width == 15
    assert np.allclose(v.pose.t, [2.0, 0, 1]) and v.get_image().shape == (10, 15, 3)
    assert cap.gt_ooi_points is None and not cap.has_gt_masks
    assert all(v.compressed for v in cap.views)  # .jpg frames
    json.dump({"frames": frames}, open(d / "transforms.json", "w"))
    with pytest.raises(InputError, match="fl_x"):
        capture_io.read_capture(d)


def test_colmap_text_model(tmp_path):
    s = tmp_path / "sparse" / "0"
    s.mkdir(parents=True)
    (tmp_path / "images").mkdir()
    (s / "cameras.txt").write_text("1 PINHOLE 32 24 30 31 16 12\n")
    (s / "images.txt").write_text("1 1 0 0 0 0 0 4 1 a.png\n10.5 12.5 1 5.5 6.5 -1\n"
                                  "2 1 0 0 0 -1 0 4 1 b.png\n11.5 12.5 1 6.5 6.5 2\n")
    (s / "points3D.txt").write_text("1 0.1 0.2 0.3 255 0 0 0.5 1 0 2 0\n"
                                    "2 0.5 0.5 0.5 0 255 0 0.25 1 1 2 1\n")
    for n in "ab":
        Image.fromarray(np.zeros((24, 32, 3), np.uint8)).save(tmp_path / "images" / f"{n}.png")
    cap, cloud = capture_io.read_capture_and_cloud(tmp_path)
    assert [v.key for v in cap.views] == ["a", "b"] and cap.meta["input"] == "colmap"
    assert np.allclose(cap.views[1].pose.t, [1, 0, -4])  # c2w of t_cw = (-1, 0, 4)
    assert cap.views[0].camera.cx == 15.5  # COLMAP +0.5 centres -> ROS integer centres
    assert len(cloud) == 2 and cloud.track_lengths().tolist() == [2, 2]
    assert np.allclose(cloud.obs_xy[0], [10.0, 12.0])
    (tmp_path / "images" / "b.png").unlink()
    with pytest.raises(InputError, match="missing"):
        capture_io.read_capture(tmp_path)


@pytest.mark.slow
@pytest.mark.skipif(not BONSAI.is_dir(), reason="bonsai dataset missing")
def test_mipnerf360_bonsai():
    cap, cloud = capture_io.read_capture_and_cloud(BONSAI, downscale=2)
    assert len(cap) == 289 and len(cloud) == 96664 and cap.has_poses
    assert cap.views[0].key == "DSCF5565"
    assert cap.views[0].get_image().shape == (cap.views[0].camera.height, 400, 3)


def test_plain_image_folder(tmp_path):
    for i in range(2):
        Image.fromarray(np.full((30, 40, 3), i * 50, np.uint8)).save(tmp_path / f"img{i}.png")
    exif = Image.Exif()
    exif.get_ifd(0x8769)[0xA405] = 28  # FocalLengthIn35mmFilm
    Image.fromarray(np.zeros((30, 40, 3), np.uint8)).save(tmp_path / "img2.jpg", exif=exif)
    cap = capture_io.read_capture(tmp_path)
    assert [v.key for v in cap.views] == ["img0", "img1", "img2"]
    assert all(v.pose is None for v in cap.views)
    assert cap.views[0].camera.fx == 1.2 * 40
    assert abs(cap.views[2].camera.fx - 28 / 36 * 40) < 1e-9
    assert cap.meta["focal_source"] == {"default": 2, "exif": 1}
    assert [v.compressed for v in cap.views] == [False, False, True]  # the .jpg is lossy
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(InputError, match="no bag"):
        capture_io.read_capture(empty)
    with pytest.raises(InputError, match="downscale"):
        capture_io.read_capture(tmp_path, downscale=0.5)
    # macOS's "._NAME" metadata beside each photo copied to an SD card is not a photo (it
    # stopped the reading: "cannot identify image file"); suffixes count in any case
    (tmp_path / "._img0.png").write_bytes(b"\x00\x05\x16\x07 AppleDouble")
    Image.fromarray(np.zeros((30, 40, 3), np.uint8)).save(tmp_path / "img3.TIF")
    assert [v.key for v in capture_io.read_capture(tmp_path).views] == [
        "img0", "img1", "img2", "img3"]


def test_plain_image_folder_turns_exif_rotated_photos_upright_and_drops_unreadable(tmp_path):
    """A phone's portrait photo is stored landscape with an EXIF Orientation tag; viewers
    (and any mask a user draws) show it upright, so the capture loads it upright: its camera
    is 30x40 and its pixels are the turned ones. A file that is no image is dropped and
    counted (it stopped the whole folder once), not a crash."""
    upright = np.zeros((40, 30, 3), np.uint8)
    upright[:5] = 255  # a white band at the top of the upright photo
    stored = Image.fromarray(upright).rotate(90, expand=True)  # 40 wide, band on the left
    exif = Image.Exif()
    exif[0x0112] = 6  # "turn 90 degrees clockwise to view"
    stored.save(tmp_path / "a.jpg", exif=exif, quality=95)
    Image.fromarray(np.zeros((30, 40, 3), np.uint8)).save(tmp_path / "b.jpg")
    (tmp_path / "c.jpg").write_bytes(b"not a photo at all")
    cap = capture_io.read_capture(tmp_path)
    assert [v.key for v in cap.views] == ["a", "b"]
    a, b = cap.views
    assert (a.camera.width, a.camera.height) == (30, 40)
    assert (b.camera.width, b.camera.height) == (40, 30)
    img = a.get_image()
    assert img.shape == (40, 30, 3)
    assert img[:5].mean() > 200 and img[10:].mean() < 30  # the band is at the top again
    assert cap.meta["exif_turned"] == 1
    assert cap.meta["dropped"] == {"unreadable_image": 1} and cap.meta["unreadable"] == ["c.jpg"]
    half = capture_io.read_capture(tmp_path, downscale=2)
    assert half.views[0].get_image().shape == (20, 15, 3)
    for f in ("a.jpg", "b.jpg"):
        (tmp_path / f).unlink()
    with pytest.raises(InputError, match="none of its 1 image files can be read"):
        capture_io.read_capture(tmp_path)


def test_ply_points_own_and_foreign(tmp_path):
    pts = np.random.default_rng(1).normal(size=(20, 3))
    capture_io.write_ply_points(tmp_path / "a.ply", pts)
    assert np.allclose(capture_io.read_ply_points(tmp_path / "a.ply"), pts.astype(np.float32))
    import open3d as o3d
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    o3d.io.write_point_cloud(str(tmp_path / "b.ply"), pc, write_ascii=True)
    assert np.allclose(capture_io.read_ply_points(tmp_path / "b.ply"), pts, atol=1e-5)
    with pytest.raises(InputError, match="does not exist"):
        capture_io.read_ply_points(tmp_path / "c.ply")


def test_info_cli_on_capture_folder(tmp_path, capsys):
    from ooi_seg_ros.cli import main as cli_main
    out = capture_io.write_capture(_capture(n=3), tmp_path / "cap")
    assert cli_main(["info", str(out)]) == 0
    text = capsys.readouterr().out
    assert "(nerfstudio)" in text and "views:    3" in text and "gt masks: 3" in text
    bag = capture_io.write_capture(_capture(n=3), tmp_path / "cap.mcap")
    assert cli_main(["info", str(bag)]) == 0
    assert "/ground_truth/mask" in capsys.readouterr().out


def test_capture_bag_decodes_from_embedded_definitions(tmp_path):
    """Tools without ROS (Foxglove, mcap_ros2) decode every message from the schemas alone."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    cap = _capture(n=2, dist=True)
    p = capture_io.write_capture_bag(cap, tmp_path / "c.mcap")
    n = 0
    by_stamp = {v.stamp_ns: v.image.tobytes() for v in cap.views}
    with open(p, "rb") as f:
        for _s, ch, _m, dec in make_reader(f, decoder_factories=[DecoderFactory()]) \
                .iter_decoded_messages():
            n += 1
            if ch.topic == "/camera/image_raw":
                assert dec.encoding == "rgb8" and dec.width == 32
                stamp = dec.header.stamp.sec * 10**9 + dec.header.stamp.nanosec
                assert bytes(dec.data) == by_stamp[stamp]
            if ch.topic == "/camera/camera_info":
                assert dec.distortion_model == "plumb_bob" and list(dec.k)[0] == 30.0
    assert n == 2 * 4 + 1


def test_bad_camera_info_dropped_or_fatal(tmp_path):
    cam = CameraIntrinsics(8, 6, 5, 5, 3.5, 2.5)
    for n_good, expect in ((1, None), (0, "all zeros")):
        p = tmp_path / f"ci{n_good}.mcap"
        with BagWriter(p) as w:
            for i in range(3):
                t = T0 + i * MS
                info = msgconv.intrinsics_to_camera_info(cam, t)
                if i >= n_good:
                    info.k = [0.0] * 9
                w.write("/camera/camera_info", info, t)
                w.write("/camera/image_raw", msgconv.rgb_to_image(
                    np.zeros((6, 8, 3), np.uint8), t), t)
        if expect is None:
            cap = capture_io.read_capture(p)
            assert len(cap) == 3 and cap.meta["dropped"] == {"invalid_camera_info": 2}
            assert "no poses" in cap.meta["note"] and cap.views[0].pose is None
        else:
            with pytest.raises(InputError, match=expect):
                capture_io.read_capture(p)


@pytest.mark.parametrize("compressed", [False, True])
def test_lazy_bag_images_equal_eager(tmp_path, compressed):
    cap = _capture(n=5)
    p = capture_io.write_capture_bag(cap, tmp_path / "l.mcap", compressed=compressed)
    lazy = capture_io.read_capture(p, lazy_images=True)
    assert all(v.image is None and v.loader is not None for v in lazy.views)
    _same(cap, lazy)
    half = capture_io.read_capture(p, lazy_images=True, downscale=2)
    eager = capture_io.read_capture(p, downscale=2)
    for a, b in zip(half.views, eager.views):
        assert np.array_equal(a.get_image(), b.get_image())
