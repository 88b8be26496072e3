"""Unit tests of the segmentation stages on small synthetic clouds with known answers."""

from dataclasses import replace

import numpy as np
import pytest
from scipy import ndimage

from ooi_seg_ros.core.geometry import look_at
from ooi_seg_ros.core.types import CameraIntrinsics, SfmCloud, View
from ooi_seg_ros.seg.density import DensityConfig, density_filter, monte_carlo_density, spacing
from ooi_seg_ros.seg.floor import FloorConfig, floor_filter
from ooi_seg_ros.seg.masks import (MaskConfig, mesh_masks, point_masks, project_distorted,
                                   undistorted_dirs)
from ooi_seg_ros.seg.mesh import MeshConfig, build_mesh
from ooi_seg_ros.seg.metrics import mask_metrics, scene_metrics
from ooi_seg_ros.seg.noise import NoiseConfig, noise_filter


def _ring_views(n=8, radius=3.0, height=1.5, target=(0, 0, 0.5), size=(64, 48)):
    cam = CameraIntrinsics(size[0], size[1], 50.0, 50.0, (size[0] - 1) / 2, (size[1] - 1) / 2)
    views = []
    for k in range(n):
        a = 2 * np.pi * k / n
        eye = np.array([radius * np.cos(a), radius * np.sin(a), height])
        views.append(View(f"v{k}", k, cam, look_at(eye, np.array(target, float))))
    return views


def _sphere(n, r=0.5, c=(0, 0, 0.5), seed=0):
    p = np.random.default_rng(seed).normal(size=(n, 3))
    return p / np.linalg.norm(p, axis=1, keepdims=True) * r + np.array(c)


def test_density_keeps_dense_blob_over_sparse_noise():
    rng = np.random.default_rng(0)
    blob = rng.normal(scale=0.05, size=(2000, 3))
    noise = rng.uniform(-2, 2, size=(600, 3))
    keep, p = density_filter(np.vstack([blob, noise]), DensityConfig(seed=1))
    assert (keep < 2000).sum() > 0.9 * len(keep)
    assert p["bandwidth"] > 0


def test_density_relative_cut_takes_what_is_sparse_however_many_points_that_is():
    # an object of uneven density (a dense body, a sparser wing) and a few isolated specks:
    # a cut at a fraction of the median density takes the specks and keeps the wing, with
    # 10 specks or 100; a fixed share takes its count whatever the points are
    rng = np.random.default_rng(4)
    body = rng.uniform([-0.5, -0.2, -0.2], [0.5, 0.2, 0.2], (3000, 3))
    wing = rng.uniform([0.5, -0.05, -1.5], [0.8, 0.05, 1.5], (400, 3))
    obj = np.vstack([body, wing])
    for n_specks in (10, 100):
        specks = rng.uniform(-6, 6, (n_specks, 3))
        x = np.vstack([obj, specks])
        keep, p = density_filter(x, DensityConfig(seed=1, drop_fraction=0.0, first_peak=False,
                                                  relative_cut=0.1))
        kept = np.zeros(len(x), bool)
        kept[keep] = True
        assert kept[:len(obj)].mean() > 0.995  # the sparse wing stays
        assert kept[len(obj):].mean() < 0.1  # the specks go
        assert 0 < p["relative_cut"] < np.inf
        share, _ = density_filter(x, DensityConfig(seed=1, drop_fraction=0.05, first_peak=False))
        took = np.setdiff1d(np.arange(len(x)), share)
        assert len(took) == pytest.approx(0.05 * len(x), abs=1)
        if n_specks == 10:  # a 5% share of 3,410 points is 170: 160 of them the object's
            assert (took < len(obj)).sum() > 100


def test_density_sparse_share_flags_the_kept_points_the_share_would_cut():
    # the relative cut keeps the sparse wing; ``sparse_share`` names the kept points that the
    # sparsest-5% share would have taken (positions in the kept array), and only those
    rng = np.random.default_rng(4)
    body = rng.uniform([-0.5, -0.2, -0.2], [0.5, 0.2, 0.2], (3000, 3))
    wing = rng.uniform([0.5, -0.05, -1.5], [0.8, 0.05, 1.5], (400, 3))
    x = np.vstack([body, wing, rng.uniform(-6, 6, (10, 3))])
    base = dict(seed=1, drop_fraction=0.0, first_peak=False, relative_cut=0.1)
    keep, p = density_filter(x, DensityConfig(**base, sparse_share=0.05))
    plain, q = density_filter(x, DensityConfig(**base))
    assert np.array_equal(keep, plain) and "sparse" not in q  # the kept set is the cut's
    share, _ = density_filter(x, DensityConfig(seed=1, drop_fraction=0.05, first_peak=False))
    flagged = keep[p["sparse"]]
    assert len(flagged) > 100  # most of the share's 170 points are the wing's, kept here
    assert np.array_equal(np.sort(flagged), np.setdiff1d(keep, share))


def test_framing_warning_reports_an_ooi_that_reaches_out_of_the_cameras_frame():
    """roi.framing_warning: the cameras keep the object they orbit in frame; an OOI cloud with
    more than ``warn_unframed_share`` of its points inside the frame of fewer than half the
    views holds something around the object (the toy car of seed 1 on one ring: clutter
    chained to it, 5.9% so, IoU 0.45 with no warning before). A neighbour nearer the object,
    still framed, is not reported: the check only sees what leaves the frame."""
    from ooi_seg_ros.seg.roi import RoiConfig, framing_warning
    views = _ring_views()
    obj = _sphere(1000, r=0.4, c=(0, 0, 0.5), seed=1)
    assert framing_warning(obj, views, RoiConfig()) is None
    for x, warned in ((1.5, False), (2.5, True)):
        xyz = np.vstack([obj, _sphere(150, r=0.3, c=(x, 0, 0.3), seed=2)])
        w = framing_warning(xyz, views, RoiConfig())
        assert (w is not None) == warned
        if warned:
            assert w.startswith("13.0% of the OOI points") and "neighbour" in w
            assert framing_warning(xyz, views, RoiConfig(warn_unframed_share=0.0)) is None
            assert framing_warning(xyz, views, RoiConfig(warn_unframed_share=0.2)) is None
    assert framing_warning(np.zeros((0, 3)), views, RoiConfig()) is None


def test_capped_discs_draw_inside_the_uncapped_silhouette():
    from ooi_seg_ros.core.types import TriMesh
    from ooi_seg_ros.seg.masks import render_masks
    views = _ring_views()
    xyz = np.vstack([_sphere(400), _sphere(8, r=0.8, seed=1)])  # a sphere and 8 far points
    small = np.zeros(len(xyz), bool)
    small[400:] = True
    cfg = MaskConfig(mode="points")
    empty = TriMesh(np.zeros((0, 3)), np.zeros((0, 3), np.int32))
    wide, pw = render_masks(views, cfg, empty, xyz)
    tight, pt = render_masks(views, cfg, empty, xyz, small)
    assert pt["capped_discs"] == 8 and "capped_discs" not in pw
    assert all((tight[k] <= wide[k]).all() for k in wide)
    assert sum(int(wide[k].sum() - tight[k].sum()) for k in wide) > 0


def test_density_options_out_of_range_are_a_config_error():
    from ooi_seg_ros.core.types import InputError
    from ooi_seg_ros.seg.pipeline import make_config
    with pytest.raises(InputError, match="drop_fraction"):
        make_config("ours", {"density": {"drop_fraction": 1.5}})
    with pytest.raises(InputError, match="relative_cut"):
        make_config("ours", {"density": {"relative_cut": -0.1}})
    with pytest.raises(InputError, match="sparse_share"):
        make_config("ours", {"density": {"sparse_share": 1.0}})


def test_density_truncated_kernel_ranks_like_dense_kde():
    x = np.random.default_rng(2).normal(size=(800, 3)) * [1, 1, 0.3]
    a, _ = monte_carlo_density(x, DensityConfig(seed=3, method="kdtree"))
    b, _ = monte_carlo_density(x, DensityConfig(seed=3, method="sklearn"))
    ra, rb = np.argsort(np.argsort(a)), np.argsort(np.argsort(b))
    assert np.corrcoef(ra, rb)[0, 1] > 0.95


def _floor_scene(seed=0):
    rng = np.random.default_rng(seed)
    floor = np.c_[rng.uniform(-2, 2, (4000, 2)), rng.normal(0, 0.003, 4000)]
    obj = rng.uniform([-0.3, -0.3, 0.05], [0.3, 0.3, 0.8], (800, 3))
    return np.vstack([floor, obj]), np.r_[np.zeros(4000, bool), np.ones(800, bool)]


@pytest.mark.parametrize("mode", ["paper", "support"])
def test_floor_removes_plane_and_keeps_object(mode):
    xyz, is_obj = _floor_scene()
    views = _ring_views()
    centers = np.array([v.pose.t for v in views])
    up = -np.mean([v.pose.R[:, 1] for v in views], axis=0)
    keep, p = floor_filter(xyz, FloorConfig(mode=mode, n_thresholds=20), centers, up,
                           np.array([0, 0, 0.5]))
    kept_obj = is_obj[keep].sum()
    assert kept_obj > 0.8 * is_obj.sum()
    assert (~is_obj[keep]).sum() < 0.05 * (~is_obj).sum()


def test_support_floor_warns_without_plane_under_object():
    xyz = _sphere(2000)
    views = _ring_views()
    keep, p = floor_filter(xyz, FloorConfig(mode="support"),
                           np.array([v.pose.t for v in views]), np.array([0, 0, 1.0]),
                           np.array([0, 0, 0.5]))
    assert len(keep) == len(xyz) and "warning" in p


def test_noise_largest_and_central_cluster():
    rng = np.random.default_rng(4)
    big = rng.normal([3, 0, 0], 0.1, (1500, 3))
    small = rng.normal([0, 0, 0], 0.1, (600, 3))
    xyz = np.vstack([big, small, rng.uniform(-6, 6, (30, 3))])
    k1, _ = noise_filter(xyz, NoiseConfig(select="largest"), np.zeros(3), 0.5)
    k2, _ = noise_filter(xyz, NoiseConfig(select="central"), np.zeros(3), 0.5)
    assert (k1 < 1500).mean() > 0.99 and len(k1) > 1400
    assert ((k2 >= 1500) & (k2 < 2100)).mean() > 0.99 and len(k2) > 550
    k3, p = noise_filter(xyz, NoiseConfig(method="sor", iterations=3), np.zeros(3), 0.5)
    assert len(k3) < len(xyz) and p["rounds"] >= 1


def test_mesh_of_sphere_and_mask_is_a_disc():
    views = _ring_views(4)
    cloud = SfmCloud.from_points(_sphere(3000))
    cloud.views = views
    mesh, p = build_mesh(cloud, MeshConfig(poisson_depth=6, trim_quantile=0.02))
    assert not mesh.is_empty
    r = np.linalg.norm(mesh.vertices - [0, 0, 0.5], axis=1)
    assert abs(np.median(r) - 0.5) < 0.05
    m = mesh_masks(mesh, views, MaskConfig())["v0"]
    # the sphere seen from distance d has angular radius asin(r/d)
    d = np.linalg.norm(views[0].pose.t - [0, 0, 0.5])
    rad_px = 50.0 * np.tan(np.arcsin(0.5 / d))
    assert abs(m.sum() - np.pi * rad_px ** 2) < 0.15 * np.pi * rad_px ** 2
    pm = point_masks(cloud.xyz, np.full(len(cloud), 0.03), views[:1], MaskConfig())["v0"]
    assert mask_metrics(pm, m)["iou"] > 0.65


def test_poisson_mesh_is_the_same_on_every_call():
    """Open3D's multi-threaded Poisson returns a different mesh per call (isl-org/Open3D#2117),
    which made one input's masks differ between runs; the mesh stage runs it on one thread."""
    cloud = SfmCloud.from_points(_sphere(3000))
    cloud.views = _ring_views(4)
    meshes = [build_mesh(cloud, MeshConfig(poisson_depth=8))[0] for _ in range(3)]
    for m in meshes[1:]:
        assert np.array_equal(m.vertices, meshes[0].vertices)
        assert np.array_equal(m.triangles, meshes[0].triangles)


def test_distortion_roundtrip():
    cam = CameraIntrinsics(80, 60, 60.0, 60.0, 40.0, 30.0, "plumb_bob",
                           np.array([-0.2, 0.05, 0.001, -0.001, 0.0]))
    view = _ring_views(1)[0]
    dirs = undistorted_dirs(cam) @ view.pose.R.T
    pts = view.pose.t + dirs * 2.0
    uv, z = project_distorted(pts, cam, view.pose)
    uu, vv = np.meshgrid(np.arange(80.0), np.arange(60.0))
    assert np.abs(uv - np.c_[uu.ravel(), vv.ravel()]).max() < 1e-3


def test_metrics_known_values():
    gt = np.zeros((10, 10), bool)
    gt[:5] = True
    pred = np.zeros((10, 10), bool)
    pred[:, :5] = True
    m = mask_metrics(pred, gt)
    assert m["iou"] == pytest.approx(25 / 75)
    assert m["precision"] == pytest.approx(0.5) and m["recall"] == pytest.approx(0.5)
    assert m["dice"] == pytest.approx(0.5)
    s = scene_metrics({"a": pred, "b": gt}, {"a": gt, "b": gt, "c": gt})
    assert s["mean"]["iou"] == pytest.approx((1 / 3 + 1) / 2)
    assert s["missing_predictions"] == ["c"]


def test_fill_small_holes_keeps_large_ones():
    from ooi_seg_ros.seg.masks import fill_small_holes
    m = np.zeros((60, 60), bool)
    m[5:55, 5:55] = True
    m[10:12, 10:12] = False  # small gap between points
    m[20:45, 20:45] = False  # a wheel
    f = fill_small_holes(m, 0.02)
    assert f[10:12, 10:12].all() and not f[20:45, 20:45].any()


def test_alpha_masks_cover_sphere_like_points_mode():
    from ooi_seg_ros.seg.masks import alpha_masks, point_radii
    views = _ring_views(2)
    xyz = _sphere(1500)
    r = point_radii(xyz, 4, 0.6)
    a = alpha_masks(xyz, r, views, MaskConfig(closing_kernel=3))
    p = point_masks(xyz, r, views, MaskConfig(closing_kernel=3))
    for k in a:
        assert a[k].sum() >= p[k].sum() and mask_metrics(a[k], p[k])["iou"] > 0.8


def test_splat_discs_with_centres_outside_the_image():
    """Discs centred up to one radius outside the frame draw their inner part, no crash."""
    from ooi_seg_ros.seg.masks import _splat
    uv = np.array([[-3.0, 10.0], [25.0, -2.0], [41.0, 29.0], [20.0, 15.0]])
    rad = np.array([5.0, 4.0, 6.0, 3.0])
    m = _splat(uv, rad, 30, 40)
    assert m.shape == (30, 40)
    assert m[10, 0] and m[0, 25] and m[29, 39] and m[15, 20]
    assert not m[15, 10]
    # a point just in front of the camera plane projects to a huge finite uv: ignored quietly
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        far = _splat(np.vstack([uv, [[1e25, 5.0], [-3e30, 1e40]]]), np.r_[rad, 40.0, 40.0],
                     30, 40)
    assert np.array_equal(far, m)


def test_splat_discs_far_larger_than_the_image_draw_exactly_in_bounded_memory():
    """A huge max_splat_px once built a distance-transform box of (2 r)^2 pixels (r = 1e5:
    80 GB); such bins are drawn as row spans, pixel for pixel what d <= r gives."""
    import tracemalloc
    from ooi_seg_ros.seg.masks import _draw_spans, _splat
    rng = np.random.default_rng(0)
    h, w = 48, 64
    r = 1.2 ** np.floor(np.log(1e5) / np.log(1.2))  # the radius the bins round 1e5 down to
    # three discs that each cover a part of the image: from the left, from below, a corner
    uv = np.array([[10.0 - r, 20.0], [30.0, r + 40.0], [-r / 1.4142, -r / 1.4142]])
    rad = np.array([1e5, 1e5, 1e5])
    tracemalloc.start()
    m = _splat(uv, rad, h, w)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 50e6
    # the same discs by brute force
    yy, xx = np.mgrid[0:h, 0:w]
    ref = np.zeros((h, w), bool)
    for u, v in np.rint(uv).astype(int):
        ref |= (xx - u) ** 2 + (yy - v) ** 2 <= r * r
    assert 0 < ref.sum() < h * w and np.array_equal(m, ref)
    # ellipses as large: the same discs as covariances r^2 I
    from ooi_seg_ros.seg.masks import _splat_ellipses
    tracemalloc.start()
    e = _splat_ellipses(uv, np.repeat((r * r * np.eye(2))[None], 3, axis=0), h, w)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 50e6 and np.array_equal(e, m)
    # the span drawing agrees with the distance transform on ordinary discs too
    ui, vi = rng.integers(-8, 70, 200), rng.integers(-8, 55, 200)
    for rr in (1.0, 2.5, 7.3):
        spans = np.zeros((h, w), bool)
        _draw_spans(spans, ui, vi, rr, chunk=37)
        ref = np.zeros((h, w), bool)
        for u, v in zip(ui, vi):
            ref |= (xx - u) ** 2 + (yy - v) ** 2 <= rr * rr
        assert np.array_equal(spans, ref)


def test_ellipse_splats_hug_a_thin_tube_and_stay_discs_on_a_surface():
    """Sparse points along a thin rod: the ellipse splat narrows across the rod (a fraction
    of the disc's area, every point still drawn, the rod's true width covered); on a
    sphere's surface the ellipsoid stays the disc's sphere."""
    from ooi_seg_ros.seg.masks import _splat_ellipses, point_covariances, point_radii
    from ooi_seg_ros.seg.masks import _splat
    # a single ellipse: semi-axes 10 (x) and 3 (y) px centred on the pixel nearest its centre
    m = _splat_ellipses(np.array([[30.2, 20.0]]), np.array([[[100.0, 0], [0, 9.0]]]), 40, 60)
    assert m[20, 20] and m[20, 40] and m[23, 30] and not m[24, 30] and not m[20, 41]
    assert abs(m.sum() - np.pi * 30) < 12
    # round shapes draw exactly ``_splat``'s discs
    rng = np.random.default_rng(2)
    uv = rng.uniform(-5, 65, (30, 2))
    rad = np.where(rng.random(30) < 0.2, 0.0, 1.2 ** rng.integers(0, 10, 30))  # on its bins
    assert np.array_equal(_splat_ellipses(uv, rad[:, None, None] ** 2 * np.eye(2), 40, 60),
                          _splat(uv, np.maximum(rad * 1.0001, 0.5), 40, 60))
    rng = np.random.default_rng(3)
    t = np.sort(rng.uniform(-0.5, 0.5, 40))
    rod = np.column_stack([t, 0.005 * rng.normal(size=40), 0.5 + 0.005 * rng.normal(size=40)])
    r = point_radii(rod, 4, 0.6)
    cov = point_covariances(rod, r, 8, 2.0)
    ax = np.sqrt(np.linalg.eigvalsh(cov))  # ascending semi-axes
    assert np.allclose(ax[:, 2], r)
    assert np.median(ax[:, 0] / r) < 0.5
    cam = CameraIntrinsics(160, 120, 150.0, 150.0, 79.5, 59.5)
    views = [View(v.key, v.stamp_ns, cam, v.pose) for v in _ring_views()]
    cfg = MaskConfig(mode="points", closing_kernel=1)
    disc = point_masks(rod, r, views, cfg)
    ell = point_masks(rod, r, views, cfg, cov=cov)
    for v in views:
        uv, z = project_distorted(rod, v.camera, v.pose)
        ui, vi = np.rint(uv).astype(int).T
        inside = (ui >= 0) & (ui < 160) & (vi >= 0) & (vi < 120)
        assert ell[v.key][vi[inside], ui[inside]].all()
    sph = point_masks(rod, r, views, cfg, cov=r[:, None, None] ** 2 * np.eye(3))
    assert all(np.array_equal(sph[k], disc[k]) for k in disc)
    area_d = sum(m.sum() for m in disc.values())
    area_e = sum(m.sum() for m in ell.values())
    assert area_e < 0.7 * area_d
    ball = _sphere(600, r=0.4)
    rs = point_radii(ball, 4, 0.6)
    cs = point_covariances(ball, rs, 8, 2.0)
    axs = np.sqrt(np.linalg.eigvalsh(cs))
    assert np.median(axs[:, 0] / rs) > 0.99


def test_local_radii_shrink_a_stray_point_not_an_evenly_sparse_part():
    """``point_radii(local=True)``: a stray point 2.5 cm off a dense patch (1 cm spacing) gets
    the patch's spacing instead of a disc reaching across the gap; the points of an evenly
    sparse row keep their radii."""
    from ooi_seg_ros.seg.masks import point_radii
    g = np.arange(10) * 0.01
    patch = np.column_stack([np.repeat(g, 10), np.tile(g, 10), np.zeros(100)])
    stray = np.array([[0.115, 0.05, 0.0]])
    row = np.column_stack([np.arange(8) * 0.1 + 1.0, np.zeros(8), np.zeros(8)])
    xyz = np.vstack([patch, stray, row])
    plain = point_radii(xyz, 4, 1.0)
    local = point_radii(xyz, 4, 1.0, local=True, local_factor=1.5)
    assert plain[100] > 0.02 and local[100] < 0.015
    assert np.allclose(local[:100], plain[:100]) and np.allclose(local[101:], plain[101:])
    # with a factor only radii above that multiple of the neighbours' are replaced
    assert np.isclose(point_radii(xyz, 4, 1.0, local=True, local_factor=10.0)[100], plain[100])


def test_support_band_covers_a_rough_floor_skin():
    """A lawn-like floor scatters points up to 4 cm above and below the plane; an object
    stands on it. The band measured below the plane removes the skin, not the object."""
    rng = np.random.default_rng(7)
    xy = rng.uniform(-2, 2, (6000, 2))
    z = np.clip(rng.laplace(0, 0.008, 6000), -0.04, 0.04)  # heavy-tailed skin
    floor = np.column_stack([xy, z])
    obj = _sphere(800, r=0.3, c=(0, 0, 0.4))  # bottom at 0.1 m
    xyz = np.vstack([floor, obj])
    views = _ring_views()
    centers = np.array([v.pose.t for v in views])
    up = -np.mean([v.pose.R[:, 1] for v in views], axis=0)
    keep, p = floor_filter(xyz, FloorConfig(mode="support"), centers, up,
                           np.array([0, 0, 0.4]))
    assert p["band_mirror"] > p["band_inliers"]  # the skin is thicker than the inliers' band
    skin_left = (keep < 6000).sum()
    off = FloorConfig(mode="support", band_mirror_quantile=0.0)
    keep0, _ = floor_filter(xyz, off, centers, up, np.array([0, 0, 0.4]))
    assert skin_left < 0.5 * (keep0 < 6000).sum()
    assert (keep >= 6000).sum() == 800  # every object point kept


def test_skin_end_stops_where_the_depths_below_the_plane_stop_decaying():
    """A cloth hanging over a table's edge spreads points evenly over depth below the table
    top: the quantile reads it as skin up to the window's edge, the tail level does not; the
    object's foot just above the skin then stays. With no such tail it changes nothing."""
    from ooi_seg_ros.seg.floor import skin_end
    rng = np.random.default_rng(11)
    skin = np.abs(rng.normal(0, 0.004, 6000))  # 4 mm skin below a table top
    assert skin_end(skin, 0.1, 0.005) == 0.1  # no tail: the quantile decides
    xy = rng.uniform(-1, 1, (6000, 2))
    top = np.column_stack([xy, rng.normal(0, 0.004, 6000)])
    ang = rng.uniform(0, 2 * np.pi, 3000)  # the cloth's sides: a cylinder of radius 1.1
    side = np.column_stack([1.1 * np.cos(ang), 1.1 * np.sin(ang), -rng.uniform(0, 0.5, 3000)])
    obj = _sphere(800, r=0.3, c=(0, 0, 0.33))  # its lowest points 3 cm above the top
    xyz = np.vstack([top, side, obj])
    views = _ring_views()
    centers = np.array([v.pose.t for v in views])
    up = -np.mean([v.pose.R[:, 1] for v in views], axis=0)
    target = np.array([0, 0, 0.33])
    keep0, p0 = floor_filter(xyz, FloorConfig(mode="support"), centers, up, target)
    keep1, p1 = floor_filter(xyz, FloorConfig(mode="support", band_tail=True), centers, up,
                             target)
    assert p1["band"] < 0.5 * p0["band"]
    assert (keep1 >= 9000).sum() > (keep0 >= 9000).sum() + 10  # the object's foot stays
    assert (keep1 < 6000).sum() < 0.02 * 6000  # the table top still goes


def _stool_scene(seed=3):
    """A floor, a cloth-covered stool (top at 0.5 m, textured sides hanging to the floor) and
    a ball on it whose lowest points are 3 cm above the top."""
    rng = np.random.default_rng(seed)
    floor = np.column_stack([rng.uniform(-2, 2, (8000, 2)), rng.normal(0, 0.004, 8000)])
    hid = np.hypot(floor[:, 0], floor[:, 1]) < 0.41  # under the stool: seen by no camera
    floor[hid, :2] *= 0.41 / np.hypot(floor[hid, 0], floor[hid, 1])[:, None] + 1.0
    r = 0.4 * np.sqrt(rng.uniform(0, 1, 2500))
    a = rng.uniform(0, 2 * np.pi, 2500)
    top = np.column_stack([r * np.cos(a), r * np.sin(a), 0.5 + rng.normal(0, 0.004, 2500)])
    a = rng.uniform(0, 2 * np.pi, 2500)
    side = np.column_stack([0.41 * np.cos(a), 0.41 * np.sin(a), rng.uniform(0.02, 0.5, 2500)])
    ball = _sphere(800, r=0.15, c=(0, 0, 0.68), seed=seed)
    views = _ring_views(target=(0, 0, 0.68))
    centers = np.array([v.pose.t for v in views])
    up = -np.mean([v.pose.R[:, 1] for v in views], axis=0)
    return np.vstack([floor, top, side, ball]), centers, up, np.array([0, 0, 0.68])


def test_support_is_the_surface_under_the_object_not_the_floor_under_the_stool():
    """Both the floor and the stool's top lie below the object with the cameras above them;
    the floor holds more points, the stool's top is the one the object stands on."""
    from ooi_seg_ros.seg.floor import surround
    xyz, centers, up, target = _stool_scene()
    _, most = floor_filter(xyz, FloorConfig(mode="support"), centers, up, target)
    assert abs(most["support_plane"][3]) < 0.05  # the floor (z = 0)
    keep, near = floor_filter(xyz, FloorConfig(mode="support", support_select="nearest"),
                              centers, up, target)
    assert abs(abs(near["support_plane"][3]) - 0.5) < 0.02  # the stool's top
    assert [t.get("surround_sectors") for t in near["planes_tried"]] == [None, 8]  # top first
    assert (keep < 10500).sum() < 0.02 * 10500  # floor and stool top removed
    # a plane beside the object (a shelf to one side) does not surround its foot
    shelf = np.column_stack([np.random.default_rng(0).uniform(1, 2, (500, 2)), np.zeros(500)])
    assert surround(shelf, np.array([0, 0, 1.0, 0]), target) <= 2


def test_a_plane_through_the_object_with_its_support_visible_under_it_is_no_support():
    """A plane through the object's middle (clutter tops around a toy car) surrounds its
    foot too, but the bench under it is in view; the floor under a stool's top is not."""
    from ooi_seg_ros.seg.floor import under_interior
    xyz, centers, up, target = _stool_scene()
    floor, top = xyz[:8000], xyz[8000:10500]
    assert under_interior(np.array([0, 0, 1.0, -0.5]), top, target, floor) == 0.0
    rng = np.random.default_rng(1)
    bench = np.column_stack([rng.uniform(-1, 1, (4000, 2)), np.zeros(4000)])
    ring = np.column_stack([rng.uniform(-1, 1, (600, 2)), np.full(600, 0.15)])
    assert under_interior(np.array([0, 0, 1.0, -0.15]), ring, np.array([0, 0, 0.16]),
                          bench) > 1.0
    xyz2 = np.vstack([bench, ring, _sphere(300, r=0.1, c=(0, 0, 0.16))])
    _, p = floor_filter(xyz2, FloorConfig(mode="support", support_select="nearest"),
                        centers, up, np.array([0, 0, 0.16]))
    assert abs(p["support_plane"][3]) < 0.01  # the bench, not the clutter's tops


def test_a_support_over_a_dense_floor_hides_it_per_area_not_per_inlier():
    """``max_under_density``: a sparse stool top over a dense floor (a wide frame) has a few
    floor points seen under its edge -- more than ``max_under`` per inlier of the top, yet a
    small share of the floor's density around it. Per area it still hides the floor; a plane
    through the object's middle does not."""
    from ooi_seg_ros.seg.floor import under_density
    rng = np.random.default_rng(5)
    floor = np.column_stack([rng.uniform(-2, 2, (16000, 2)), rng.normal(0, 0.004, 16000)])
    rf = np.hypot(floor[:, 0], floor[:, 1])
    floor = np.vstack([floor[rf >= 0.41], floor[rf < 0.2][:20]])  # 20 seen under the edge
    r = 0.4 * np.sqrt(rng.uniform(0, 1, 300))
    a = rng.uniform(0, 2 * np.pi, 300)
    top = np.column_stack([r * np.cos(a), r * np.sin(a), 0.5 + rng.normal(0, 0.004, 300)])
    a = rng.uniform(0, 2 * np.pi, 300)
    side = np.column_stack([0.41 * np.cos(a), 0.41 * np.sin(a), rng.uniform(0.02, 0.5, 300)])
    ball = _sphere(800, r=0.15, c=(0, 0, 0.68), seed=5)
    xyz = np.vstack([floor, top, side, ball])
    views = _ring_views(target=(0, 0, 0.68))
    centers = np.array([v.pose.t for v in views])
    up = -np.mean([v.pose.R[:, 1] for v in views], axis=0)
    target = np.array([0, 0, 0.68])
    ratio = under_density(np.array([0, 0, 1.0, -0.5]), top, target, floor)
    assert ratio is not None and ratio < 0.15  # the ring starts at the stool's edge
    cfg = FloorConfig(mode="support", support_select="nearest", band_interior=True,
                      support_min_of="remaining")
    _, p0 = floor_filter(xyz, cfg, centers, up, target)
    assert abs(p0["support_plane"][3]) < 0.05  # the top fails max_under: the floor is taken
    cfg.max_under_density = 0.2
    keep, p1 = floor_filter(xyz, cfg, centers, up, target)
    assert abs(abs(p1["support_plane"][3]) - 0.5) < 0.02  # the stool's top
    assert np.isin(np.arange(len(xyz) - 800, len(xyz)), keep).mean() > 0.95  # the ball stays
    assert np.isin(np.arange(len(floor), len(floor) + 300), keep).mean() < 0.05
    # the ground seen under a plane through the object's middle: about its density around
    bench = np.column_stack([rng.uniform(-1, 1, (4000, 2)), np.zeros(4000)])
    ring = np.column_stack([rng.uniform(-1, 1, (600, 2)), np.full(600, 0.15)])
    assert under_density(np.array([0, 0, 1.0, -0.15]), ring, np.array([0, 0, 0.16]),
                         bench) > 0.5
    assert under_density(np.array([0, 0, 1.0, -0.5]), top, target, floor[:10]) is None


def _wide_stool_scene(seed=3):
    """The stool scene seen through a wide lens: the same stool and ball, but the floor around
    them out to 5 m at the same density (a wider frame or a farther orbit lets in more of the
    room), so the stool's top holds under 10% of the cloud."""
    xyz, centers, up, target = _stool_scene(seed)
    rng = np.random.default_rng(seed + 10)
    far = np.column_stack([rng.uniform(-5, 5, (50000, 2)), rng.normal(0, 0.004, 50000)])
    far = far[(np.abs(far[:, 0]) > 2.0) | (np.abs(far[:, 1]) > 2.0)]
    return np.vstack([far, xyz]), len(far), centers, up, target


def test_a_small_support_is_found_among_much_floor():
    """``support_min_of="remaining"``: a stool's top that holds under ``support_min_inliers``
    of a cloud full of floor is still tried once the floor is gone, and taken."""
    xyz, n_far, centers, up, target = _wide_stool_scene()
    cfg = FloorConfig(mode="support", support_select="nearest", band_interior=True)
    _, p0 = floor_filter(xyz, cfg, centers, up, target)
    assert abs(p0["support_plane"][3]) < 0.05  # the floor: the top was never tried
    assert len(p0["planes_tried"]) == 1
    cfg.support_min_of = "remaining"
    keep, p1 = floor_filter(xyz, cfg, centers, up, target)
    assert abs(abs(p1["support_plane"][3]) - 0.5) < 0.02  # the stool's top
    ball = np.arange(len(xyz) - 800, len(xyz))
    assert np.isin(ball, keep).mean() > 0.95
    assert (keep < len(xyz) - 800).sum() < 0.02 * (len(xyz) - 800)


def test_a_far_floor_s_thicker_skin_is_removed_ring_by_ring():
    """``band_local``: a floor whose SfM skin thickens away from the object (seen farther
    off and at a shallower angle, as through a wide lens) leaves its outer skin above a band
    measured under the interior; measured ring by ring beyond the interior, it goes, and the
    ball standing on the floor at the centre stays."""
    rng = np.random.default_rng(4)
    xy = rng.uniform(-5, 5, (40000, 2))
    r = np.hypot(xy[:, 0], xy[:, 1])
    floor = np.column_stack([xy, rng.normal(0, 0.003 + 0.006 * r)])
    ball = _sphere(300, r=0.3, c=(0, 0, 0.32), seed=4)
    xyz = np.vstack([floor, ball])
    views = _ring_views(target=(0, 0, 0.32))
    centers = np.array([v.pose.t for v in views])
    up = -np.mean([v.pose.R[:, 1] for v in views], axis=0)
    target = np.array([0, 0, 0.32])
    cfg = FloorConfig(mode="support", support_select="nearest", band_interior=True)
    k0, p0 = floor_filter(xyz, cfg, centers, up, target)
    cfg.band_local = 4
    k1, p1 = floor_filter(xyz, cfg, centers, up, target)
    assert (k0 < 40000).sum() > 400  # the outer skin left above the interior's band
    assert (k1 < 40000).sum() < 0.25 * (k0 < 40000).sum()
    assert len(p1["band_rings"]) == 4 and p1["band_rings"][-1] > 1.4 * p1["band"]
    assert (k1 >= 40000).sum() >= (k0 >= 40000).sum() - 3  # the ball stays


def test_skin_under_the_support_interior_ignores_a_cloth_hanging_at_its_edge():
    """The cloth's sides below the stool's top are not the top's skin: measured under the
    top's interior, the band stays thin and the object's foot stays."""
    xyz, centers, up, target = _stool_scene()
    cfg = FloorConfig(mode="support", support_select="nearest")
    k0, p0 = floor_filter(xyz, cfg, centers, up, target)
    cfg.band_interior = True
    k1, p1 = floor_filter(xyz, cfg, centers, up, target)
    assert p1["band"] < 0.5 * p0["band"]
    assert (k1 >= 13000).sum() > (k0 >= 13000).sum() + 20
    assert (k1 >= 13000).sum() >= 790


def test_band_gap_ignores_stray_depths_under_a_sparse_supports_interior():
    """``band_gap``: under an opaque support's interior only its skin is seen, so the skin's
    99% depth quantile measures the band -- but on a sparse top (a few dozen depths) two
    SfM strays 15-22 cm down are that quantile, and the band took the whole pot (the stool
    through a 90 deg lens at 544x408, seed 2: band 0.169 m, IoU 0.66). The depths end at the
    first gap wider than the fit threshold; the strays stay out of the band."""
    rng = np.random.default_rng(4)
    floor = np.column_stack([rng.uniform(-2, 2, (4000, 2)), rng.normal(0, 0.004, 4000)])
    hid = np.hypot(floor[:, 0], floor[:, 1]) < 0.41  # under the stool: seen by no camera
    floor[hid, :2] *= 0.41 / np.hypot(floor[hid, 0], floor[hid, 1])[:, None] + 1.0
    r, a = 0.4 * np.sqrt(rng.uniform(0, 1, 300)), rng.uniform(0, 2 * np.pi, 300)
    top = np.column_stack([r * np.cos(a), r * np.sin(a), 0.5 + rng.normal(0, 0.004, 300)])
    strays = np.array([[0.05, 0.02, 0.35], [-0.03, 0.06, 0.28]])
    a = rng.uniform(0, 2 * np.pi, 400)
    pot = np.column_stack([0.08 * np.cos(a), 0.08 * np.sin(a), rng.uniform(0.5, 0.6, 400)])
    leaves = _sphere(400, r=0.12, c=(0, 0, 0.72), seed=2)
    xyz = np.vstack([floor, top, strays, pot, leaves])
    views = _ring_views(target=(0, 0, 0.65))
    centers = np.array([v.pose.t for v in views])
    up = -np.mean([v.pose.R[:, 1] for v in views], axis=0)
    cfg = FloorConfig(mode="support", support_select="nearest", band_interior=True)
    k0, p0 = floor_filter(xyz, cfg, centers, up, np.array([0, 0, 0.65]))
    k1, p1 = floor_filter(xyz, replace(cfg, band_gap=True), centers, up, np.array([0, 0, 0.65]))
    assert p0["band_mirror"] > 0.15 and p1["band_mirror"] < 0.05
    obj = 4302  # the pot's and the leaves' points come last
    assert (k0 >= obj).sum() < 0.6 * 800 and (k1 >= obj).sum() > (k0 >= obj).sum() + 200
    assert not np.isin(np.arange(4000, 4302), k1).any()  # the top and the strays still go


def test_a_pot_s_foot_in_the_floor_s_skin_stays_when_it_touches_the_object():
    """``layer_attach``: a stool's cloth top scatters its SfM points a few cm above and below
    the plane, so the band removes the lowest few cm of a pot standing on it. A point in that
    layer within reach of a point above the band is the object's foot and stays; the skin's
    points away from the object still go."""
    rng = np.random.default_rng(2)
    r = 0.4 * np.sqrt(rng.uniform(0, 1, 4000))
    a = rng.uniform(0, 2 * np.pi, 4000)
    top = np.column_stack([r * np.cos(a), r * np.sin(a),
                           0.5 + np.clip(rng.laplace(0, 0.008, 4000), -0.04, 0.04)])
    a = rng.uniform(0, 2 * np.pi, 600)
    pot = np.column_stack([0.08 * np.cos(a), 0.08 * np.sin(a), rng.uniform(0.5, 0.65, 600)])
    leaves = _sphere(600, r=0.12, c=(0, 0, 0.75), seed=2)
    xyz = np.vstack([top, pot, leaves])
    views = _ring_views(target=(0, 0, 0.65))
    centers = np.array([v.pose.t for v in views])
    up = -np.mean([v.pose.R[:, 1] for v in views], axis=0)
    target = np.array([0, 0, 0.65])
    k0, p0 = floor_filter(xyz, FloorConfig(mode="support"), centers, up, target)
    k1, p1 = floor_filter(xyz, FloorConfig(mode="support", layer_attach=2.0), centers, up,
                          target)
    assert p1["band"] == p0["band"] and p0["band"] > 1.5 * p0["band_inliers"]
    z = xyz[:, 2] - 0.5
    zp = z[4000:4600]
    foot = 4000 + np.nonzero((zp > p0["band_inliers"]) & (zp < p0["band"]))[0]
    assert len(foot) > 40 and not np.isin(foot, k0).any()  # the band took the foot
    assert np.isin(foot, k1).mean() > 0.9  # attached to the pot above it: kept
    # the skin away from the pot: only what touches a speck of skin the band already left
    far = np.nonzero(np.hypot(xyz[:4000, 0], xyz[:4000, 1]) > 0.2)[0]
    joined = np.setdiff1d(far[np.isin(far, k1)], k0)
    specks = far[np.isin(far, k0)]
    reach = 2.0 * p1["threshold"]
    assert len(joined) < 0.01 * len(far)
    assert all(np.linalg.norm(xyz[specks] - xyz[j], axis=1).min() <= reach for j in joined)
    assert np.isin(np.arange(4000, 5200), k1).sum() >= np.isin(np.arange(4000, 5200), k0).sum()


def test_central_cluster_does_not_merge_a_neighbour_beyond_its_reach():
    rng = np.random.default_rng(5)
    obj = _sphere(1500, r=0.3, c=(0, 0, 0), seed=1)
    part = _sphere(150, r=0.05, c=(0, 0, 0.2), seed=2)  # a split-off part inside its reach
    neighbour = _sphere(800, r=0.15, c=(0.75, 0, 0), seed=3)  # the thing beside it
    xyz = np.vstack([obj, part, neighbour, rng.uniform(-3, 3, (20, 3))])
    cfg = NoiseConfig(select="central", eps_scale=1.5)
    keep, p = noise_filter(xyz, cfg, np.zeros(3), 2.0)
    assert (keep < 1500).sum() > 1400
    assert ((keep >= 1650) & (keep < 2450)).sum() == 0
    old, _ = noise_filter(xyz, NoiseConfig(select="central", eps_scale=1.5,
                                           merge_reach_quantile=0.0), np.zeros(3), 2.0)
    assert ((old >= 1650) & (old < 2450)).sum() > 700  # the frame-radius rule merged it


def test_widening_goes_on_while_a_sparse_part_is_in_no_cluster():
    # a dense body and a sparser part on top of it (a plant's leaves over its pot): at one
    # spacing DBSCAN finds one cluster and leaves the whole part as noise, so "more than one
    # cluster" alone never starts the widening; widen_unclustered widens while a settle_change
    # share of the points is in no cluster, and the part joins
    from ooi_seg_ros.seg.pipeline import preset
    rng = np.random.default_rng(1)
    body = rng.normal(0, 0.15, (400, 3)) + [0, 0, 0.4]
    top = rng.uniform([-0.25, -0.25, 0.75], [0.25, 0.25, 0.75 + 0.1 * 1.8 ** 3], (100, 3))
    xyz = np.vstack([body, top])
    skip = ("method", "widen_unclustered")
    kw = {k: v for k, v in preset("ours")["noise"].items() if k not in skip}
    target = np.array([0, 0, 0.4])
    k0, p0 = noise_filter(xyz, NoiseConfig(widen_unclustered=False, **kw), target, 1.0)
    assert p0["clusters"] == 1 and p0["unclustered"] >= kw["settle_change"]
    assert "eps_scales_tried" not in p0 and (k0 >= 400).sum() < 10
    k1, p1 = noise_filter(xyz, NoiseConfig(widen_unclustered=True, **kw), target, 1.0)
    assert p1["eps_scales_tried"][0] == 1.0 and len(p1["eps_scales_tried"]) > 1
    assert (k1 >= 400).sum() >= 90 and (k1 < 400).sum() >= (k0 < 400).sum()


def test_refine_observations_follow_view_keys():
    """Observations index the cloud's own views: a reordered subset of views gets its own."""
    from ooi_seg_ros.seg.refine import _obs_by_view
    views = _ring_views(4)
    cloud = SfmCloud(np.zeros((2, 3)), np.zeros((2, 3), np.uint8), np.zeros(2),
                     np.array([0, 2, 3]), np.array([0, 3, 1], np.int32),
                     np.array([[1, 1], [3, 3], [2, 2]], np.float32), views)
    obs = _obs_by_view(cloud, [views[3], views[1]])
    assert obs[0].tolist() == [[3, 3]] and obs[1].tolist() == [[2, 2]]


def test_point_support_and_hull_carve_remove_a_one_view_blob():
    """A blob that only one view's mask claims gets no support and is carved from it."""
    from ooi_seg_ros.seg.masks import hull_carve, point_radii
    from ooi_seg_ros.seg.refine import point_support
    views = _ring_views(8)
    xyz = _sphere(1500)
    masks = point_masks(xyz, point_radii(xyz, 4, 1.0), views, MaskConfig(closing_kernel=3))
    stray = np.array([[0.0, 0.0, 1.6]])  # above the sphere, in frame of every view
    blob = masks[views[0].key].copy()
    uv, _ = project_distorted(stray, views[0].camera, views[0].pose)
    u, v = np.rint(uv[0]).astype(int)
    blob[max(0, v - 3):v + 4, max(0, u - 3):u + 4] = True
    masks[views[0].key] = blob
    sup = point_support(np.vstack([xyz, stray]), masks, views)
    assert np.median(sup[:-1]) > 0.95 and sup[-1] < 0.2
    carved, p = hull_carve(masks, views, xyz, MaskConfig())
    assert p["applied"] and not carved[views[0].key][v, u]
    for vw in views[1:]:  # the consistent masks keep (almost) all of their area
        assert carved[vw.key].sum() > 0.9 * masks[vw.key].sum()


def test_plane_check_calls_the_floor_floor_and_the_object_not():
    """Plane-induced photo-consistency on a simulator capture with exact masks and depths:
    textured table top around the plant is called floor, the plant (almost) never."""
    from ooi_seg_ros.seg.photo import PlaneCheckConfig, PlaneConsistency
    from ooi_seg_ros.sim import simulate_capture
    sim = simulate_capture("tabletop", n_views=24, width=128, height=96, seed=0)
    views = sim.capture.views
    plane = np.array([0.0, 0.0, 1.0, -sim.scene.support_z])
    target = np.mean(sim.capture.gt_ooi_points, axis=0)
    pc = PlaneConsistency(views, plane, target, PlaneCheckConfig(enabled=True, max_deg=40.0))
    obj_hit, obj_n, floor_hit, floor_n = 0, 0, 0, 0
    for i in range(0, 24, 4):
        v = views[i]
        fl = pc.floor_map(i, (0, 96, 0, 128))
        # true floor pixels: the depth's 3D point lies on the table plane
        dirs = undistorted_dirs(v.camera).reshape(96, 128, 3) @ v.pose.R.T
        p = v.pose.t + dirs * sim.depths[i][..., None]
        on_plane = np.abs(p[..., 2] - sim.scene.support_z) < 1e-3
        near = ndimage.binary_dilation(v.gt_mask, iterations=8) & ~v.gt_mask & on_plane
        obj_hit += (fl & v.gt_mask).sum()
        obj_n += v.gt_mask.sum()
        floor_hit += (fl & near).sum()
        floor_n += near.sum()
    print("object called floor", obj_hit / obj_n, "floor near it called floor",
          floor_hit / floor_n)
    assert obj_hit < 0.02 * obj_n
    assert floor_hit > 0.25 * floor_n
    # on a reduced grid (what GrabCut works on for large crops): same shape, same kind of map
    full = pc.floor_map(4, (0, 96, 0, 128))
    half = pc.floor_map(4, (0, 96, 0, 128), (48, 64))
    assert half.shape == (48, 64)
    assert abs(half.mean() - full.mean()) < 0.1
    assert (half & views[4].gt_mask[::2, ::2]).sum() < 0.02 * views[4].gt_mask[::2, ::2].sum()


def test_tune_support_moves_a_plane_fitted_a_little_low_onto_the_textured_top():
    """plane_check.tune_support: a support plane fitted 3.3% of the object's radius below the
    table top (a least-squares fit of noisy points can sit a few mm off) matches fewer of
    the top's patches; the offset search over the inlier band finds the top again, from
    either side, and leaves a right plane where it is."""
    from ooi_seg_ros.seg.photo import PlaneCheckConfig, PlaneConsistency
    from ooi_seg_ros.sim import simulate_capture
    W, H = 160, 120
    sim = simulate_capture("tabletop", n_views=24, width=W, height=H, seed=0)
    views = sim.capture.views
    sz = sim.scene.support_z
    rad = sim.scene.summary()["ooi_radius"]
    target = np.mean(sim.capture.gt_ooi_points, axis=0)
    masks = {v.key: v.gt_mask for v in views}
    near = {}
    for i in range(0, 24, 4):
        v = views[i]
        dirs = undistorted_dirs(v.camera).reshape(H, W, 3) @ v.pose.R.T
        p = v.pose.t + dirs * sim.depths[i][..., None]
        near[i] = (ndimage.binary_dilation(v.gt_mask, iterations=8) & ~v.gt_mask
                   & (np.abs(p[..., 2] - sz) < 1e-3))

    def floor_share(pc):
        return (sum((pc.floor_map(i, (0, H, 0, W)) & near[i]).sum() for i in near)
                / sum(n.sum() for n in near.values()))

    cfg = PlaneCheckConfig(enabled=True, max_deg=40.0, tune_support=8)
    for frac in (0.033, -0.033, 0.0):
        delta = frac * rad
        pc = PlaneConsistency(views, np.array([0.0, 0.0, 1.0, -(sz - delta)]), target, cfg)
        before = floor_share(pc)
        out = pc.tune_support(masks, 0.08 * rad)
        err = -pc.planes[0, 3] - sz
        after = floor_share(pc)
        print(frac, out["offset"], err, before, after)
        assert abs(err) <= 0.5 * 0.01 * rad + 1e-9  # within half a step of the top
        if frac:
            assert np.sign(out["offset"]) == np.sign(frac)
            assert after > before + 0.05
        else:
            assert out["offset"] == 0.0 and after == before
    # off (0 steps) or no band: nothing moves
    pc = PlaneConsistency(views, np.array([0.0, 0.0, 1.0, -(sz - 0.01)]), target,
                          PlaneCheckConfig(enabled=True, max_deg=40.0))
    assert pc.tune_support(masks, 0.08 * rad)["offset"] == 0.0 and pc.planes[0, 3] == -(sz - 0.01)


def _floor_calls(pc, views) -> tuple[float, float]:
    """(share of the object, share of the floor within 8 px of it) that the plane check
    ``pc`` calls floor in every 4th of 24 views of a 128x96 capture."""
    obj_hit = obj_n = floor_hit = floor_n = 0
    for i in range(0, 24, 4):
        v = views[i]
        fl = pc.floor_map(i, (0, 96, 0, 128))
        near = ndimage.binary_dilation(v.gt_mask, iterations=8) & ~v.gt_mask
        obj_hit += (fl & v.gt_mask).sum()
        obj_n += v.gt_mask.sum()
        floor_hit += (fl & near).sum()
        floor_n += near.sum()
    return obj_hit / obj_n, floor_hit / floor_n


def test_plane_check_exposure_matches_a_neighbour_s_gain_before_the_colour_test():
    """Every other view 20% brighter (auto exposure): the colour test (max_diff) then fails
    on bright floor texture that lines up; with ``exposure`` the pair's gain is measured on
    the patches whose NCC matches and the floor is found again, the object still not."""
    import dataclasses
    from ooi_seg_ros.seg.photo import PlaneCheckConfig, PlaneConsistency, _pair_gain
    from ooi_seg_ros.sim import simulate_capture
    sel = np.zeros((10, 10), bool)
    assert _pair_gain(np.full((10, 10), 110.0), np.full((10, 10), 100.0), sel) == 1.0
    sel[:6] = True  # 60 patches: enough to measure
    assert _pair_gain(np.full((10, 10), 110.0), np.full((10, 10), 100.0), sel) == \
        pytest.approx(1.1)
    assert _pair_gain(np.full((10, 10), 500.0), np.full((10, 10), 100.0), sel) == 2.0
    sim = simulate_capture("tabletop", n_views=24, width=128, height=96, seed=0)
    views = [dataclasses.replace(v, image=np.clip(v.get_image() * (1.2 if k % 2 else 1.0),
                                                  0, 255).astype(np.uint8), loader=None)
             for k, v in enumerate(sim.capture.views)]
    plane = np.array([0.0, 0.0, 1.0, -sim.scene.support_z])
    target = np.mean(sim.capture.gt_ooi_points, axis=0)
    found = {}
    for exposure in (False, True, "auto"):
        pc = PlaneConsistency(views, plane, target,
                              PlaneCheckConfig(enabled=True, max_deg=40.0,
                                               exposure=exposure is True,
                                               exposure_auto=exposure == "auto"))
        obj, found[exposure] = _floor_calls(pc, views)
        print("exposure", exposure, "object called floor", obj,
              "floor near it called floor", found[exposure])
        assert obj < 0.02
    assert found[True] > 1.25 * found[False]  # measured 0.119 -> 0.165
    # exposure_auto: a 20% gain moves the floor's grey level past half max_diff: matched too
    assert found["auto"] > 1.25 * found[False]
    # ... while on the capture as simulated (3% swings) it changes nothing
    pc0, pc1 = (PlaneConsistency(sim.capture.views, plane, target,
                                 PlaneCheckConfig(enabled=True, max_deg=40.0, exposure_auto=a))
                for a in (False, True))
    same = [np.array_equal(pc0.floor_map(i, (0, 96, 0, 128)), pc1.floor_map(i, (0, 96, 0, 128)))
            for i in range(0, 24, 4)]
    print("views unchanged by exposure_auto", same)
    assert sum(same) >= 5


def test_view_exposures_recovers_each_view_s_gain_from_the_sfm_observations():
    """10% exposure swings: each view's log exposure, solved from the grey levels at the points
    the views share (x = s_point + e_view, alternating medians), matches the simulator's own
    draw; points whose brightness changes with the viewing angle (a quarter of them 1.4x
    brighter in every other view, as a sheen would) move no view's exposure much (a gain
    measured on those points' patches alone would be 1.4), and views seeing too few points
    stay at 0."""
    from ooi_seg_ros.seg.photo import view_exposures
    from ooi_seg_ros.sim import simulate_capture
    from ooi_seg_ros.sim.capture import _view_rng
    sim = simulate_capture("tabletop", n_views=24, width=128, height=96, seed=0,
                           exposure_jitter=0.1)
    views = sim.capture.views
    true = np.log([np.clip(1.0 + _view_rng(0, k).normal(0, 0.1), 0.8, 1.2)
                   for k in range(len(views))])
    # surface points on every surface: view 0's and view 12's depth maps back-projected
    pts = []
    for i in (0, 12):
        v, d = views[i], sim.depths[i]
        ys, xs = np.mgrid[3:96:8, 3:128:8]
        z = d[ys, xs]
        ok = np.isfinite(z) & (z > 0)
        xn = (xs[ok] - v.camera.cx) / v.camera.fx * z[ok]
        yn = (ys[ok] - v.camera.cy) / v.camera.fy * z[ok]
        pts.append(np.c_[xn, yn, z[ok]] @ v.pose.R.T + v.pose.t)
    xyz = np.vstack(pts)
    # a quarter of the points change brightness with the viewing angle (a sheen, a highlight)
    sheen_pt = np.random.default_rng(0).random(len(xyz)) < 0.25

    def observations(images):
        obs = []
        for v, d in zip(views, sim.depths):
            xy, z = project_distorted(xyz, v.camera, v.pose)
            inb = (z > 0) & (xy[:, 0] >= 0) & (xy[:, 0] < 127.5) & (xy[:, 1] >= 0) & \
                (xy[:, 1] < 95.5)
            idx = np.nonzero(inb)[0]
            r, c = np.round(xy[idx, 1]).astype(int), np.round(xy[idx, 0]).astype(int)
            vis = np.abs(d[r, c] - z[idx]) < 0.01 * z[idx]  # not hidden
            obs.append((idx[vis], xy[idx[vis]].astype(np.float32)))
        return obs

    obs = observations(views)
    e = view_exposures(obs, views)
    err = (e - np.median(e)) - (true - np.median(true))
    print("true", np.round(true, 3), "\nerr", np.round(err, 3))
    assert np.ptp(true) > 0.3
    assert np.abs(err).max() < 0.04  # 4%: a 120 grey level within 5
    # a capped solve (a share of the points, the same in every view) agrees
    half = view_exposures(obs, views, max_obs=sum(len(o[0]) for o in obs) // 2)
    print("half the points: max change", np.abs(half - e).max())
    assert np.abs(half - e).max() < 0.03
    # the sheen: those points' pixels 1.4x brighter in every other view
    shone = []
    for k, (v, o) in enumerate(zip(views, obs)):
        im = v.get_image().astype(np.float32)
        if k % 2:
            sel = sheen_pt[o[0]]
            r, c = np.round(o[1][sel, 1]).astype(int), np.round(o[1][sel, 0]).astype(int)
            lit = np.zeros(im.shape[:2], bool)
            lit[r, c] = True
            im[ndimage.binary_dilation(lit, np.ones((5, 5), bool))] *= 1.4
        shone.append(replace(v, image=np.clip(im, 0, 255).astype(np.uint8), loader=None))
    e2 = view_exposures(obs, shone)
    err2 = (e2 - np.median(e2)) - (true - np.median(true))
    print("err with the sheen", np.round(err2, 3))
    assert np.abs(err2).max() < 0.3 * np.log(1.4)  # measured 0.057 of the sheen's 0.336
    # a view with fewer than min_points usable observations stays at 0
    few = [o if k != 3 else (o[0][:5], o[1][:5]) for k, o in enumerate(obs)]
    assert view_exposures(few, views)[3] == 0.0


def test_noise_sigma_measures_pixel_noise_not_the_image_s_texture():
    """The robust Laplacian estimator recovers white noise's std under smooth shading and
    texture, reads near 0 on the same image without noise, and ignores pixels not ``ok``."""
    from ooi_seg_ros.seg.photo import noise_sigma
    rng = np.random.default_rng(0)
    y, x = np.mgrid[0:120, 0:160].astype(np.float32)
    clean = 100 + 0.3 * x + 20 * np.sin(x / 9.0) * np.cos(y / 7.0)
    assert noise_sigma(clean) < 0.3
    for sd in (1.5, 4.0, 8.0):
        est = noise_sigma(clean + rng.normal(0, sd, clean.shape).astype(np.float32))
        assert est == pytest.approx(sd, rel=0.15)
    ok = np.zeros(clean.shape, bool)
    ok[:, :80] = True
    half = clean.copy()
    half[:, 80:] += rng.normal(0, 20, (120, 80)).astype(np.float32)
    assert noise_sigma(half, ok) < 0.3
    assert noise_sigma(np.zeros((2, 2), np.float32)) == 0.0


def test_capture_noise_tells_a_dim_capture_from_a_clean_one_and_adapts_the_plane_check():
    """``capture_noise`` reads the simulator's clean 320x240 images (sensor noise 1.5) under
    the ``ours`` preset's ``adapt_noise`` and dim ones (6) over it; the refinement reports the
    reading (the pipeline tests check a clean capture is not adapted)."""
    from ooi_seg_ros.seg.pipeline import make_config
    from ooi_seg_ros.seg.photo import capture_noise
    from ooi_seg_ros.sim import simulate_capture
    level = make_config("ours").refine.plane_check.adapt_noise
    assert level > 0
    read = {}
    for noise in (1.5, 6.0):
        sim = simulate_capture("tabletop", n_views=8, width=320, height=240, seed=0,
                               sensor_noise=noise)
        read[noise] = capture_noise(sim.capture.views)
    print(read)
    assert read[1.5] < level < read[6.0]
    assert capture_noise([]) == 0.0


def test_plane_check_noise_ncc_finds_the_floor_of_a_noisy_capture():
    """Sensor noise 6 (of 255; the default capture's is 1.5) lowers the NCC of floor patches
    that line up under ``min_ncc``, and GrabCut then takes the floor. With ``noise_ncc`` the
    NCC is corrected for the noise both images carry: the floor near the object is found
    again and the object still is not."""
    from ooi_seg_ros.seg.photo import PlaneCheckConfig, PlaneConsistency
    from ooi_seg_ros.sim import simulate_capture
    sim = simulate_capture("tabletop", n_views=24, width=128, height=96, seed=0,
                           sensor_noise=6.0)
    views = sim.capture.views
    plane = np.array([0.0, 0.0, 1.0, -sim.scene.support_z])
    target = np.mean(sim.capture.gt_ooi_points, axis=0)
    found = {}
    for noise_ncc in (False, True):
        pc = PlaneConsistency(views, plane, target,
                              PlaneCheckConfig(enabled=True, max_deg=40.0, noise_ncc=noise_ncc))
        obj, found[noise_ncc] = _floor_calls(pc, views)
        print("noise_ncc", noise_ncc, "object called floor", obj,
              "floor near it called floor", found[noise_ncc])
        assert obj < 0.02
    assert found[True] > 1.25 * found[False]


@pytest.mark.parametrize("dist", [(), (-0.12, 0.03, 0.001, -0.002, 0.0)])
def test_plane_check_samples_in_float32_where_float64_would(dist):
    """``PointSet``: the plane check projects each crop's points into ~8 neighbours in float32
    from a nearby origin. Against ``project_distorted`` (float64) the pixel coordinates near
    the image agree to 1e-3 px (pinhole and plumb_bob), points behind the camera, missing or
    non-finite are never valid, and the colours match the float64 coordinates' remap."""
    from ooi_seg_ros.seg.photo import PlaneCheckConfig, PlaneConsistency, PointSet
    rng = np.random.default_rng(3)
    cam = CameraIntrinsics(320, 240, 280.0, 285.0, 161.0, 118.5,
                           distortion_model="plumb_bob" if dist else "none",
                           dist=np.array(dist, float))
    poses = [look_at(np.array([4.0 * np.cos(a), 4.0 * np.sin(a), 2.0]), np.zeros(3),
                     np.array([0, 0, 1.0])) for a in (0.0, 0.4)]
    img = (rng.random((240, 320, 3)) * 255).astype(np.uint8)
    views = [View(key=str(k), stamp_ns=k, camera=cam, pose=pq, image=img)
             for k, pq in enumerate(poses)]
    X = rng.normal(0.0, 0.8, (5000, 3))
    X[rng.random(5000) > 0.9] += [5.0, 0.0, 0.0]  # some far off: behind, outside
    X[:3] = [np.nan, 0.0, 0.0], [np.inf, 1.0, 1.0], poses[1].t + [0.0, 0.0, -0.5]
    hit = rng.random(5000) > 0.1
    hit[:3] = True
    pts = PointSet(X, hit)
    u, v, z = pts.project(cam, poses[1])
    uv, z64 = project_distorted(X, cam, poses[1])
    good = hit & (z64 > 0.05) & np.isfinite(uv).all(1)
    # within reach of the image (far outside it float32 keeps ~7 digits, not 1e-3 px)
    near = good & (np.abs(uv[:, 0] - 160) < 480) & (np.abs(uv[:, 1] - 120) < 360)
    assert near.sum() > 3000
    np.testing.assert_allclose(u[near], uv[near, 0], atol=1e-3)
    np.testing.assert_allclose(v[near], uv[near, 1], atol=1e-3)
    pc = PlaneConsistency(views, np.array([0.0, 0.0, 1.0, 0.0]), np.zeros(3),
                          PlaneCheckConfig(enabled=True))
    col, ok = pc.sample(1, pts, None, (50, 100))
    assert np.array_equal(ok, pc.sample(1, X, hit, (50, 100))[1])  # arrays: the same path
    assert not ok.ravel()[:3].any()  # nan, inf and a point behind the camera
    with np.errstate(invalid="ignore"):
        ok64 = good & (uv[:, 0] >= 0) & (uv[:, 0] <= 319) & (uv[:, 1] >= 0) & (uv[:, 1] <= 239)
    edge = np.minimum(np.abs(uv[:, 0] - np.array([[0], [319]])).min(0),
                      np.abs(uv[:, 1] - np.array([[0], [239]])).min(0)) < 1e-3
    assert np.array_equal(ok.ravel()[~edge], ok64[~edge])
    # the colours of float64 coordinates (the form before), through the same bilinear remap
    import cv2
    mx = np.where(ok64, uv[:, 0], -1).astype(np.float32).reshape(50, 100)
    my = np.where(ok64, uv[:, 1], -1).astype(np.float32).reshape(50, 100)
    col64 = cv2.remap(img.astype(np.float32), mx, my, cv2.INTER_LINEAR,
                      borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    assert np.abs(col - col64)[ok].mean() < 0.5  # on 0-255: remap's 1/32-px grid at most


def test_plane_check_samples_a_column_longer_than_remap_takes():
    """Every mask pixel of a large image tested at once (``behind_cut`` on a 1280x720 keyframe:
    100k+ pixels as one column) exceeds cv2.remap's 32767 rows; ``sample`` gives the same
    colours and validity as for the same points laid out in a block (the 30 Hz node bench
    failed its runs with an OpenCV assertion before)."""
    from ooi_seg_ros.seg.photo import PlaneCheckConfig, PlaneConsistency
    rng = np.random.default_rng(5)
    cam = CameraIntrinsics(320, 240, 280.0, 280.0, 159.5, 119.5)
    poses = [look_at(np.array([4.0 * np.cos(a), 4.0 * np.sin(a), 2.0]), np.zeros(3),
                     np.array([0, 0, 1.0])) for a in (0.0, 0.4)]
    img = (rng.random((240, 320, 3)) * 255).astype(np.uint8)
    views = [View(key=str(k), stamp_ns=k, camera=cam, pose=pq, image=img)
             for k, pq in enumerate(poses)]
    n = 200 * 250  # > 32767
    X = rng.normal(0.0, 0.8, (n, 3))
    hit = rng.random(n) > 0.1
    pc = PlaneConsistency(views, np.array([0.0, 0.0, 1.0, 0.0]), np.zeros(3),
                          PlaneCheckConfig(enabled=True))
    col, ok = pc.sample(1, X, hit, (n, 1))
    colb, okb = pc.sample(1, X, hit, (200, 250))
    assert col.shape == (n, 1, 3) and ok.shape == (n, 1)
    assert ok.sum() > 0.5 * n
    assert np.array_equal(ok.ravel(), okb.ravel())
    np.testing.assert_array_equal(col.reshape(-1, 3), colb.reshape(-1, 3))


def test_background_planes_find_the_wall_not_the_object():
    """A wall behind the object is returned; the support plane (touching the object) and no
    plane through the object are."""
    from ooi_seg_ros.seg.photo import background_planes
    rng = np.random.default_rng(0)
    floor = np.c_[rng.uniform(-4, 4, (3000, 2)), rng.normal(0, 0.005, 3000)]
    wall = np.c_[rng.uniform(-4, 4, 1500), np.full(1500, 4.0) + rng.normal(0, 0.005, 1500),
                 rng.uniform(0, 3, 1500)]
    obj = _sphere(800, r=0.5, c=(0, 0, 0.5))
    cams = np.array([v.pose.t for v in _ring_views(12, radius=3.0, height=1.5)])
    planes = background_planes(np.vstack([floor, wall]), obj, cams, 0.02, 3, seed=0)
    assert len(planes) == 1
    n, d = planes[0][:3], planes[0][3]
    assert abs(abs(n[1]) - 1) < 1e-2 and abs(abs(d) - 4.0) < 0.05
    assert (obj @ n + d > 0).all()  # normal towards the cameras, object on their side


def test_background_planes_skip_a_second_layer_of_the_same_wall():
    """A thick wall (two RANSAC layers) is one plane, not two."""
    from ooi_seg_ros.seg.photo import background_planes
    rng = np.random.default_rng(1)
    wall = np.c_[rng.uniform(-4, 4, 3000), np.full(3000, 4.0) + rng.uniform(-0.1, 0.1, 3000),
                 rng.uniform(0, 3, 3000)]
    obj = _sphere(800, r=0.5, c=(0, 0, 0.5))
    cams = np.array([v.pose.t for v in _ring_views(12, radius=3.0, height=1.5)])
    assert len(background_planes(wall, obj, cams, 0.02, 3, seed=0)) == 1


def test_background_planes_are_the_same_from_call_to_call():
    """The same input gives the same planes (open3d's RANSAC, used until session 28, gave
    different ones from call to call whatever its seed, and the masks moved with them); a
    thick, noisy wall lets every RANSAC draw pick a slightly different plane."""
    from ooi_seg_ros.seg.photo import background_planes
    rng = np.random.default_rng(2)
    floor = np.c_[rng.uniform(-4, 4, (4000, 2)), rng.normal(0, 0.01, 4000)]
    wall = np.c_[rng.uniform(-4, 4, 4000), np.full(4000, 4.0) + rng.normal(0, 0.03, 4000),
                 rng.uniform(0, 3, 4000)]
    obj = _sphere(800, r=0.5, c=(0, 0, 0.5))
    cams = np.array([v.pose.t for v in _ring_views(12, radius=3.0, height=1.5)])
    runs = [background_planes(np.vstack([floor, wall]), obj, cams, 0.02, 3, seed=0)
            for _ in range(6)]
    assert len(runs[0]) >= 1
    assert all(np.array_equal(r, runs[0]) for r in runs[1:])
    other = background_planes(np.vstack([floor, wall]), obj, cams, 0.02, 3, seed=1)
    assert len(other) == len(runs[0])  # another seed: another draw of the same wall


def test_eps_widening_joins_a_sparse_part_but_not_a_neighbour():
    rng = np.random.default_rng(6)
    body = _sphere(2000, r=0.3, c=(0, 0, 0), seed=1)
    tail = rng.normal((0, 0, 0.42), 0.02, (60, 3))  # a part beyond a gap of ~2 spacings
    single = NoiseConfig(select="central", eps_scale=1.5)
    wide = NoiseConfig(select="central", eps_scale=1.5, eps_max_scale=4.0)
    xyz = np.vstack([body, tail])
    k0, _ = noise_filter(xyz, single, np.zeros(3), 2.0)
    k1, p = noise_filter(xyz, wide, np.zeros(3), 2.0)
    assert (k0 >= 2000).sum() == 0 and (k1 >= 2000).sum() == 60 and (k1 < 2000).sum() == 2000
    assert p["eps_scales_tried"][0] == 1.5 and len(p["eps_scales_tried"]) >= 2
    # a neighbouring object a little farther out: the widening stops before it joins (the
    # selection's extent would grow far beyond the object's)
    nb = _sphere(800, r=0.15, c=(0.53, 0, 0), seed=3)
    xyz2 = np.vstack([xyz, nb])
    k2, p2 = noise_filter(xyz2, wide, np.zeros(3), 2.0)
    assert (k2 >= 2060).sum() == 0 and (k2 < 2000).sum() == 2000 and "stopped_at_scale" in p2
    unguarded = NoiseConfig(select="central", eps_scale=1.5, eps_max_scale=4.0,
                            max_extent_growth=100.0)
    k3, _ = noise_filter(xyz2, unguarded, np.zeros(3), 2.0)
    assert (k3 >= 2060).sum() == 800


def test_merge_reach_scale_takes_a_part_just_past_the_core_not_a_neighbour():
    rng = np.random.default_rng(7)
    a, z = rng.uniform(0, 2 * np.pi, 2000), rng.uniform(-0.18, 0.18, 2000)
    pot = np.c_[0.08 * np.cos(a), 0.08 * np.sin(a), z]  # a tall core: its reach is its ends
    leaf = rng.normal((0.22, 0, 0), 0.01, (150, 3))  # median distance ~1.1x the core's reach
    nb = rng.normal((0.3, 0.15, 0), 0.015, (150, 3))  # a neighbour at ~1.7x the reach
    xyz = np.vstack([pot, leaf, nb])
    own = NoiseConfig(select="central", eps_scale=1.5)
    k1, _ = noise_filter(xyz, own, np.zeros(3), 2.0)
    k2, p = noise_filter(xyz, NoiseConfig(select="central", eps_scale=1.5,
                                          merge_reach_scale=1.2), np.zeros(3), 2.0)
    assert (k1 < 2000).sum() == 2000 and (k1 >= 2000).sum() == 0
    assert (k2 < 2000).sum() == 2000 and ((k2 >= 2000) & (k2 < 2150)).sum() == 150
    assert (k2 >= 2150).sum() == 0 and p["chosen_clusters"] == 2


def test_grabcut_band_reaches_more_gaps_where_the_seeds_are_sparse():
    """``refine.band_gaps``: the "probably background" band is at least that many mean gaps
    between the view's object seeds (sqrt(silhouette area / seeds in it)). A disc of 120 px
    with 16 seeds (gap ~26 px) gets 3 gaps; with 900 seeds (gap ~3.5 px) it keeps the
    fraction's 18 px; seeds outside the silhouette or the frame do not count; 0 = off."""
    from ooi_seg_ros.seg.refine import RefineConfig, _band_px
    yy, xx = np.mgrid[0:240, 0:320]
    m = (xx - 160) ** 2 + (yy - 120) ** 2 < 60 ** 2
    area = m.sum()
    g = np.linspace(-40, 40, 4)
    sparse = np.stack(np.meshgrid(160 + g, 120 + g), -1).reshape(-1, 2)
    dense = np.stack(np.meshgrid(160 + np.linspace(-40, 40, 30),
                                 120 + np.linspace(-40, 40, 30)), -1).reshape(-1, 2)
    off = RefineConfig(band_fraction=0.15)
    on = RefineConfig(band_fraction=0.15, band_gaps=3.0)
    assert _band_px(m, sparse, off) == (int(0.15 * 119), False)
    band, wider = _band_px(m, sparse, on)
    assert wider and band == int(round(3.0 * np.sqrt(area / 16)))
    assert _band_px(m, dense, on) == (int(0.15 * 119), False)
    # seeds outside the silhouette or outside the frame are not the silhouette's samples
    extra = np.array([[10.0, 10.0], [-50.0, 120.0], [160.0, 900.0]])
    assert _band_px(m, np.concatenate([sparse, extra]), on) == (band, True)
    assert _band_px(m, np.zeros((0, 2)), on) == (int(0.15 * 119), False)


def test_dense_object_seeds_are_thinned_at_random_to_the_share_they_may_cover():
    """``refine.seed_cover``: where the sure object seeds' discs (side 3 at radius 1) would
    cover more than that share of the image around them, each is kept with the probability
    that brings the cover there to the share. A silhouette dense on its left half (gap 2 px:
    thinned to about 1 in 4 there) and sparse on its right (gap 8 px: every seed kept); the
    seeds outside the silhouette are all kept, the pick depends only on the seed given, and
    0 is off."""
    from ooi_seg_ros.seg.refine import _thin_seeds
    yy, xx = np.mgrid[0:240, 0:320]
    m = (xx - 160) ** 2 + (yy - 120) ** 2 < 80 ** 2
    dense = np.stack(np.meshgrid(np.arange(100.0, 160.0, 2.0),
                                 np.arange(80.0, 160.0, 2.0)), -1).reshape(-1, 2)
    sparse = np.stack(np.meshgrid(np.arange(176.0, 224.0, 8.0),
                                  np.arange(80.0, 160.0, 8.0)), -1).reshape(-1, 2)
    outside = np.array([[10.0, 10.0], [300.0, 230.0], [-5.0, 100.0]])
    xy = np.concatenate([dense, sparse, outside])
    out = _thin_seeds(xy, m, 0.5625, 1, 7)  # target gap 3 / 0.75 = 4 px
    assert {tuple(p) for p in out} <= {tuple(p) for p in xy}  # a subset, not new points
    kept = {tuple(p) for p in out}
    left = sum(tuple(p) in kept for p in dense) / len(dense)
    assert 0.15 < left < 0.45, left  # (2 / 4)^2 = 1/4 deep inside, more near its edges
    assert all(tuple(p) in kept for p in sparse)
    assert np.array_equal(out[-3:], outside)  # kept, in their order
    # spread over the dense part, not a cluster: each quarter of it keeps some
    d = np.array([p for p in dense if tuple(p) in kept])
    quad = np.bincount((d[:, 0] >= 130) * 2 + (d[:, 1] >= 120), minlength=4)
    assert quad.min() > 0.15 * len(d), quad
    assert np.array_equal(out, _thin_seeds(xy, m, 0.5625, 1, 7))  # reproducible
    assert not np.array_equal(out, _thin_seeds(xy, m, 0.5625, 1, 8))
    assert np.array_equal(_thin_seeds(sparse, m, 0.5625, 1, 7), sparse)
    assert np.array_equal(_thin_seeds(xy, m, 0.0, 1, 7), xy)
    # larger discs: the same cover is reached with fewer seeds
    assert len(_thin_seeds(xy, m, 0.5625, 2, 7)) < len(out)


def test_edge_matte_grows_an_eroded_mask_to_the_half_coverage_outline():
    """A two-colour disc with an anti-aliased outline: a mask one pixel inside the truth
    (coverage >= 0.5) grows back onto it, and nothing far from the outline is added."""
    from ooi_seg_ros.seg.refine import edge_matte
    h, w, s = 60, 80, 8
    yy, xx = np.mgrid[0:h * s, 0:w * s]
    inside = ((xx + 0.5) / s - 40.3) ** 2 + ((yy + 0.5) / s - 29.6) ** 2 < 17.2 ** 2
    cover = inside.reshape(h, s, w, s).mean(axis=(1, 3))
    img = (np.array([40.0, 90.0, 60.0]) * (1 - cover[..., None])
           + np.array([210.0, 180.0, 60.0]) * cover[..., None])
    img = np.clip(img + np.random.default_rng(0).normal(0, 3, img.shape), 0, 255)
    gt = cover >= 0.5
    mask = ndimage.binary_erosion(gt, np.ones((3, 3), bool))
    out = edge_matte(img.astype(np.uint8), mask, 7)
    assert (out & ~mask).sum() > 0.8 * (gt & ~mask).sum()  # most of the lost ring is back
    assert (out & ~gt).sum() <= 0.05 * (gt & ~mask).sum()  # almost nothing beyond the truth
    assert not (out & ~ndimage.binary_dilation(mask, np.ones((3, 3), bool))).any()
    assert (edge_matte(img.astype(np.uint8), mask, 0) == mask).all()  # 0 = off
    # the coverage threshold: 0.5 is the default rule; a lower one only adds ring pixels
    assert (edge_matte(img.astype(np.uint8), mask, 7, 0.5) == out).all()
    low = edge_matte(img.astype(np.uint8), mask, 7, 0.3)
    assert (low >= out).all()
    assert not (low & ~ndimage.binary_dilation(mask, np.ones((3, 3), bool))).any()


@pytest.mark.parametrize("window", [0, 3])
def test_behind_check_calls_background_behind_the_object_not_the_object(window):
    """Background seen past the object (sim tabletop: chair, shelves, wall) is called
    background at the depth of the nearest background point beyond the object; the object is
    (almost) never -- with the planes' 5-px patches and with the behind test's own 3-px ones
    (``behind_window``: gaps between leaves narrower than a 5-px patch)."""
    from ooi_seg_ros.seg.photo import PlaneCheckConfig, PlaneConsistency
    from ooi_seg_ros.sim import simulate_capture
    sim = simulate_capture("tabletop", n_views=24, width=256, height=192, seed=0)
    views = sim.capture.views
    target = np.mean(sim.capture.gt_ooi_points, axis=0)
    rng = np.random.default_rng(0)
    pts = []
    for i in range(0, 24, 2):  # sparse "SfM" background points: depths of background pixels
        v = views[i]
        dirs = undistorted_dirs(v.camera).reshape(192, 256, 3) @ v.pose.R.T
        p = v.pose.t + dirs * sim.depths[i][..., None]
        bg = ~v.gt_mask & np.isfinite(sim.depths[i])
        cand = p[bg]
        pts.append(cand[rng.choice(len(cand), 400, replace=False)])
    cfg = PlaneCheckConfig(enabled=True, max_deg=40.0, behind=True, behind_window=window)
    below = np.array([0.0, 0.0, 1.0, 1e3])  # a plane far below: only the behind test acts
    pc = PlaneConsistency(views, below, target, cfg)
    pc.behind_xyz = np.vstack(pts)
    pc.ooi_xyz = sim.capture.gt_ooi_points
    obj_hit = obj_n = bg_hit = bg_n = 0
    for i in range(1, 24, 4):
        v = views[i]
        fl = pc.floor_map(i, (0, 192, 0, 256))
        zo = project_distorted(pc.ooi_xyz, v.camera, v.pose)[1]
        behind = sim.depths[i] > np.quantile(zo, 0.98)  # truly beyond the object
        near = ndimage.binary_dilation(v.gt_mask, iterations=8) & ~v.gt_mask & behind
        obj_hit += (fl & v.gt_mask).sum()
        obj_n += v.gt_mask.sum()
        bg_hit += (fl & near).sum()
        bg_n += near.sum()
    print("object called background", obj_hit / obj_n, "background near it", bg_hit / bg_n)
    assert obj_hit < 0.02 * obj_n
    assert bg_hit > 0.08 * bg_n


def test_shifted_plane_check_and_object_keep_on_a_known_scene():
    """The shifted-patch test (a pixel inside a matching patch whose own colour matches the
    warp) calls more of the floor right next to the object floor than the centred test, and
    still (almost) none of the object; the object-keep map is (almost) all object and never
    overlaps the floor map."""
    from ooi_seg_ros.seg.photo import PlaneCheckConfig, PlaneConsistency
    from ooi_seg_ros.sim import simulate_capture
    sim = simulate_capture("tabletop", n_views=24, width=128, height=96, seed=0)
    views = sim.capture.views
    plane = np.array([0.0, 0.0, 1.0, -sim.scene.support_z])
    target = np.mean(sim.capture.gt_ooi_points, axis=0)
    maps = {}
    for name, shifted in (("centred", False), ("shifted", True)):
        pc = PlaneConsistency(views, plane, target, PlaneCheckConfig(
            enabled=True, max_deg=40.0, shifted=shifted, object_keep=shifted))
        pc.ooi_xyz = sim.capture.gt_ooi_points
        maps[name] = [pc.floor_maps(i, (0, 96, 0, 128)) for i in range(0, 24, 4)]
    hits = {m: [0, 0] for m in maps}
    n_obj = n_near = keep_n = keep_obj = 0
    for k, i in enumerate(range(0, 24, 4)):
        v = views[i]
        dirs = undistorted_dirs(v.camera).reshape(96, 128, 3) @ v.pose.R.T
        p = v.pose.t + dirs * sim.depths[i][..., None]
        on_plane = np.abs(p[..., 2] - sim.scene.support_z) < 1e-3
        near = ndimage.binary_dilation(v.gt_mask, iterations=3) & ~v.gt_mask & on_plane
        n_obj += v.gt_mask.sum()
        n_near += near.sum()
        for m in maps:
            hits[m][0] += (maps[m][k][0] & v.gt_mask).sum()
            hits[m][1] += (maps[m][k][0] & near).sum()
        assert not maps["centred"][k][1].any()  # no object map unless asked for
        fl, keep = maps["shifted"][k]
        assert not (fl & keep).any()
        keep_n += keep.sum()
        keep_obj += (keep & v.gt_mask).sum()
    print({m: (h[0] / n_obj, h[1] / n_near) for m, h in hits.items()}, keep_obj, keep_n)
    assert hits["shifted"][1] > 1.2 * hits["centred"][1]  # more of the floor within 3 px
    assert hits["shifted"][0] < 0.02 * n_obj
    assert keep_n > 0.05 * n_obj and keep_obj > 0.95 * keep_n


def test_object_guard_keeps_patches_the_object_explains_out_of_the_floor():
    """``object_guard``: a patch that the support plane explains no better than the object's
    own depth does (low on the object, where the parallax between the two is small) does not
    vote floor. With a loose NCC threshold (0.3) the plane calls some of the plant's pot
    floor; the guard removes most of those pixels and keeps the floor around the pot."""
    from ooi_seg_ros.seg.photo import PlaneCheckConfig, PlaneConsistency
    from ooi_seg_ros.sim import simulate_capture
    w, h = 160, 120
    sim = simulate_capture("tabletop", n_views=24, width=w, height=h, seed=0)
    views = sim.capture.views
    plane = np.array([0.0, 0.0, 1.0, -sim.scene.support_z])
    target = np.mean(sim.capture.gt_ooi_points, axis=0)
    counts = {}
    for guard in (False, True):
        pc = PlaneConsistency(views, plane, target, PlaneCheckConfig(
            enabled=True, max_deg=35.0, neighbours=8, rank=3, min_ncc=0.3,
            object_guard=guard))
        pc.ooi_xyz = sim.capture.gt_ooi_points
        obj = near_hit = 0
        for i in range(0, 24, 3):
            v = views[i]
            fl = pc.floor_map(i, (0, h, 0, w))
            dirs = undistorted_dirs(v.camera).reshape(h, w, 3) @ v.pose.R.T
            p = v.pose.t + dirs * sim.depths[i][..., None]
            on_plane = np.abs(p[..., 2] - sim.scene.support_z) < 1e-3
            near = ndimage.binary_dilation(v.gt_mask, iterations=8) & ~v.gt_mask & on_plane
            obj += (fl & v.gt_mask).sum()
            near_hit += (fl & near).sum()
        counts[guard] = (int(obj), int(near_hit))
    print("object / floor near it called floor, without and with the guard", counts)
    assert counts[False][0] >= 50  # the loose threshold does call some of the object floor
    assert counts[True][0] < 0.7 * counts[False][0]
    assert counts[True][1] >= 0.98 * counts[False][1]


def test_strict_pixel_votes_need_the_object_depth_to_fail():
    """``pixel_strict``: a per-pixel floor vote also needs the object's depth to fail to
    explain the pixel (not merely to explain it worse). Its votes are a subset of the loose
    ones; on the tabletop's exact geometry it roughly halves the plant's pixels voted floor
    and keeps most of the floor's votes next to the pot."""
    from ooi_seg_ros.seg.photo import PlaneCheckConfig, PlaneConsistency
    from ooi_seg_ros.sim import simulate_capture
    w, h = 160, 120
    sim = simulate_capture("tabletop", n_views=24, width=w, height=h, seed=0)
    views = sim.capture.views
    plane = np.array([0.0, 0.0, 1.0, -sim.scene.support_z])
    target = np.mean(sim.capture.gt_ooi_points, axis=0)
    pts = sim.capture.gt_ooi_points
    pts = pts[np.random.default_rng(0).choice(len(pts), min(600, len(pts)), replace=False)]
    counts, maps = {}, {}
    for strict in (False, True):
        pc = PlaneConsistency(views, plane, target, PlaneCheckConfig(
            enabled=True, max_deg=35.0, neighbours=8, rank=3, shifted=True,
            pixel_votes=True, pixel_strict=strict))
        pc.ooi_xyz = pts
        obj = near_hit = 0
        for i in range(0, 24, 3):
            v = views[i]
            pc.floor_map(i, (0, h, 0, w))
            pf = pc.pixel_floor[(i, (0, h, 0, w))]
            maps[strict, i] = pf
            dirs = undistorted_dirs(v.camera).reshape(h, w, 3) @ v.pose.R.T
            p = v.pose.t + dirs * sim.depths[i][..., None]
            on_plane = np.abs(p[..., 2] - sim.scene.support_z) < 1e-3
            near = ndimage.binary_dilation(v.gt_mask, iterations=8) & ~v.gt_mask & on_plane
            obj += (pf & v.gt_mask).sum()
            near_hit += (pf & near).sum()
        counts[strict] = (int(obj), int(near_hit))
    print("object / floor near it voted floor pixel by pixel, loose and strict", counts)
    for i in range(0, 24, 3):
        assert not (maps[True, i] & ~maps[False, i]).any()
    assert counts[False][0] >= 30  # the loose vote does call some of the plant floor
    assert counts[True][0] < 0.7 * counts[False][0]
    assert counts[True][1] >= 0.6 * counts[False][1] > 0


def _gmm_model(mean_bgr, var):
    """A one-component GrabCut colour model (OpenCV's [1, 65] layout, 5 components)."""
    a = np.zeros(65)
    a[0] = 1.0
    a[5:8] = mean_bgr
    for k in range(5):
        a[20 + 9 * k:29 + 9 * k] = (np.eye(3) * var).ravel()
    return a[None]


def test_gmm_log_likelihood_matches_a_gaussian():
    from scipy.stats import multivariate_normal
    from ooi_seg_ros.seg.refine import gmm_log_likelihood
    x = np.array([[10.0, 20.0, 30.0], [200.0, 0.0, 5.0]])
    got = gmm_log_likelihood(_gmm_model([12, 18, 33], 50.0), x)
    want = multivariate_normal([12, 18, 33], np.eye(3) * 50.0).logpdf(x)
    assert np.allclose(got, want)


def test_hull_additions_bring_back_a_part_other_views_hold():
    """A part missing from one view's mask returns when the other views' masks hold it and
    its colour is the object's; a hole of background colour inside the hull stays out."""
    from ooi_seg_ros.seg.masks import point_radii
    from ooi_seg_ros.seg.refine import RefineConfig, hull_additions
    base = _ring_views(8)
    xyz = _sphere(1500)
    masks = point_masks(xyz, point_radii(xyz, 4, 1.0), base, MaskConfig(closing_kernel=3))
    views = []
    for v in base:
        img = np.zeros((48, 64, 3), np.uint8)
        img[...] = (40, 160, 40)  # green background
        img[masks[v.key]] = (200, 30, 30)  # red object
        views.append(View(v.key, v.stamp_ns, v.camera, v.pose, img))
    m0 = masks[views[0].key]
    ys, xs = np.nonzero(m0)
    cut = m0 & (xs.mean() + 3 < np.arange(64))[None, :]  # the right part of view 0's mask
    hole = m0 & (np.arange(64) < xs.mean() - 3)[None, :] & (np.arange(48) < ys.mean())[:, None]
    views[0].get_image()[hole] = (40, 160, 40)  # background colour inside the silhouette
    masks[views[0].key] = m0 & ~cut & ~hole
    fgd = _gmm_model([30, 30, 200], 100.0)  # BGR, as GrabCut sees the image
    bgd = _gmm_model([40, 160, 40], 100.0)
    models = {v.key: (bgd, fgd, np.zeros_like(m0)) for v in views}
    out, p = hull_additions(masks, views, xyz, models, RefineConfig(hull_add=True))
    assert p["voxels"] > 0 and p["added_px"] > 0
    got = out[views[0].key]
    assert got[cut].mean() > 0.9  # the missing part is back
    assert not got[hole].any()  # background colour is not added
    assert not (got & ~m0).any()  # nothing outside the true silhouette
    for v in views[1:]:  # complete masks gain (almost) nothing
        assert (out[v.key] & ~masks[v.key]).sum() <= 0.02 * masks[v.key].sum()
    # the photo-consistency option only removes additions; the plain red part the
    # neighbours repeat at its depth still returns
    from ooi_seg_ros.seg.photo import PlaneCheckConfig, PlaneConsistency
    photo = PlaneConsistency(views, np.array([0.0, 0.0, 1.0, 0.0]), np.array([0, 0, 0.5]),
                             PlaneCheckConfig(max_deg=60.0))
    out2, _ = hull_additions(masks, views, xyz, models,
                             RefineConfig(hull_add=True, hull_photo=True), photo)
    assert not (out2[views[0].key] & ~got).any()
    assert out2[views[0].key][cut].mean() > 0.8
    # lossless images: no graph cut; the same pixels decoded from JPEG and handed over as raw
    # images (no ``compressed`` flag) are measured as chroma-subsampled and get the cut
    assert p["graph_views"] == 0 and not p["blended"]
    import io
    from PIL import Image

    def jpeg(img):
        buf = io.BytesIO()
        Image.fromarray(img).save(buf, "JPEG", quality=90)
        return np.asarray(Image.open(buf).convert("RGB"))
    decoded = [View(v.key, v.stamp_ns, v.camera, v.pose, jpeg(v.get_image())) for v in views]
    _, pj = hull_additions(masks, decoded, xyz, models, RefineConfig(hull_add=True))
    assert pj["blended"] and pj["graph_views"] > 0 and pj["chroma_sharpness"] < 0.9
    _, pn = hull_additions(masks, decoded, xyz, models,
                           RefineConfig(hull_add=True, blend_detect=False))
    assert pn["graph_views"] == 0


def test_hull_grid_projected_in_float32_votes_as_in_float64(monkeypatch):
    """The hull's voxel grid is projected into every view in float32 offsets (``PointSet``);
    its votes, and so the hull and the masks it grows, are those of float64 projections."""
    from ooi_seg_ros.seg import refine
    from ooi_seg_ros.seg.masks import point_radii
    base = _ring_views(8)
    xyz = _sphere(1500)
    masks = point_masks(xyz, point_radii(xyz, 4, 1.0), base, MaskConfig(closing_kernel=3))
    views = []
    for v in base:
        img = np.zeros((48, 64, 3), np.uint8)
        img[...] = (40, 160, 40)
        img[masks[v.key]] = (200, 30, 30)
        views.append(View(v.key, v.stamp_ns, v.camera, v.pose, img))
    k0 = views[0].key
    masks[k0] = masks[k0] & (np.arange(64) < 36)[None, :]  # a part for the hull to bring back
    models = {v.key: (_gmm_model([40, 160, 40], 100.0), _gmm_model([30, 30, 200], 100.0),
                      np.zeros_like(masks[k0])) for v in views}
    cfg = refine.RefineConfig(hull_add=True, hull_voxel_px=0.5)  # a fine grid: many centres
    out32, p32 = refine.hull_additions(masks, views, xyz, models, cfg)

    class Float64Cells:
        def __init__(self, X, hit):
            self.X = X

        def project(self, cam, pose):
            uv, z = project_distorted(self.X, cam, pose)
            return uv[:, 0], uv[:, 1], z
    monkeypatch.setattr(refine, "PointSet", Float64Cells)
    out64, p64 = refine.hull_additions(masks, views, xyz, models, cfg)
    assert p32["grid"] == p64["grid"] > 50_000 and p32["voxels"] == p64["voxels"] > 0
    assert p32["added_px"] == p64["added_px"] > 0
    assert all(np.array_equal(out32[k], out64[k]) for k in out64)


def test_border_leak_drops_growth_to_an_image_side_the_silhouette_does_not_reach():
    """``refine.border_leak``: a region GrabCut grew from the silhouette out to the top edge
    (which the silhouette does not reach) leaves; growth that stays inside the image, and
    growth at a side the silhouette itself reaches (the object leaves the frame there), stay."""
    from ooi_seg_ros.seg.refine import _drop_border_leaks
    H, W = 40, 60
    m = np.zeros((H, W), bool)
    m[8:30, 20:40] = True  # the silhouette, clear of every side
    res = m.copy()
    res[0:8, 25:35] = True  # grown up to the top edge: a leak
    res[30:33, 22:30] = True  # grown below, inside the image: kept
    box = (0, H, 0, W)  # the crop reached the image's edges (clipped band)
    out = _drop_border_leaks(res, m, m, box)
    assert not out[0:8, 25:35].any() and out[30:33, 22:30].all() and out[m].all()
    # the silhouette reaches the top row: the object leaves the frame there, growth stays
    m2 = m.copy()
    m2[0:8, 38:40] = True
    res2 = res | m2
    assert np.array_equal(_drop_border_leaks(res2, m2, m2, box), res2)
    # a crop that does not reach the image's top edge has a background margin there
    crop = m[4:, :]
    assert np.array_equal(_drop_border_leaks(res[4:, :], crop, m, (4, H, 0, W)), res[4:, :])


def test_hull_cut_grown_drops_a_leak_only_this_view_holds():
    """``hull_cut_grown``: mask pixels GrabCut grew past the splatted silhouette are dropped
    when the other views' masks do not hold them (a band leaking along a background edge of
    the object's colour); a part no point covers but every view's mask holds stays."""
    from ooi_seg_ros.seg.masks import point_radii
    from ooi_seg_ros.seg.refine import RefineConfig, hull_additions
    base = _ring_views(8)
    xyz = _sphere(1500)
    full = point_masks(xyz, point_radii(xyz, 4, 1.0), base, MaskConfig(closing_kernel=3))
    views, sil = [], {}
    for v in base:
        img = np.zeros((48, 64, 3), np.uint8)
        img[...] = (40, 160, 40)
        img[full[v.key]] = (200, 30, 30)
        views.append(View(v.key, v.stamp_ns, v.camera, v.pose, img))
        xs = np.nonzero(full[v.key])[1]
        # the splatted silhouette misses the right part (no SfM point there) in every view;
        # GrabCut grew the masks back over it
        sil[v.key] = full[v.key] & (np.arange(64) < xs.mean() + 2)[None, :]
    k0 = views[0].key
    ys, xs = np.nonzero(full[k0])
    row = int(round(ys.mean()))
    leak = np.zeros_like(full[k0])
    leak[row - 1:row + 2, :xs.min()] = True  # a rail of object colour out to the image edge
    views[0].get_image()[leak] = (200, 30, 30)
    masks = {k: m.copy() for k, m in full.items()}
    masks[k0] |= leak
    models = {v.key: (_gmm_model([40, 160, 40], 100.0), _gmm_model([30, 30, 200], 100.0),
                      np.zeros_like(full[k0])) for v in views}
    kept, p0 = hull_additions(masks, views, xyz, models, RefineConfig(hull_add=True), None, sil)
    assert kept[k0][leak].all() and p0["cut_px"] == 0  # off by default
    for agree in (0.5, 0.25):
        cfg = RefineConfig(hull_add=True, hull_cut_grown=True, hull_cut_agree=agree)
        out, p = hull_additions(masks, views, xyz, models, cfg, None, sil)
        # the rail is cut but next to the sphere, where the hull of 8 small views is fatter
        # than the sphere itself
        far = leak & ~ndimage.binary_dilation(full[k0], iterations=4)
        assert p["cut_px"] >= 0.8 * leak.sum() and not out[k0][far].any()
        for v in views:  # nothing the views agree on is cut: the grown right parts stay
            assert out[v.key][full[v.key]].mean() > 0.99
    # no silhouettes given (a caller that does not pass them): nothing is cut
    out, p = hull_additions(masks, views, xyz, models, cfg)
    assert out[k0][leak].all() and p["cut_px"] == 0


def test_hull_free_carves_space_the_cameras_saw_through():
    """``hull_free``: every view's GrabCut kept a blob of uniform wall above the object (so
    the hull of all views' masks holds it and ``hull_cut_grown`` alone keeps it), but the
    views observed background features through it: that space is carved from the hull and
    the blob leaves every mask; the object's pixels stay. ``_obs_depths`` reads the features'
    depths from an SfM cloud's observations."""
    from ooi_seg_ros.core.types import SfmCloud
    from ooi_seg_ros.seg.masks import point_radii
    from ooi_seg_ros.seg.refine import RefineConfig, _obs_depths, hull_additions
    base = _ring_views(8)
    xyz = _sphere(1500)
    # the wall seen past the object, inside the hull grid (the OOI box padded by 15%)
    ghost = _sphere(400, r=0.12, c=(0.45, 0.45, 0.95), seed=1)
    obj = point_masks(xyz, point_radii(xyz, 4, 1.0), base, MaskConfig(closing_kernel=3))
    both = np.vstack([xyz, ghost])
    grown = point_masks(both, point_radii(both, 4, 1.0), base, MaskConfig(closing_kernel=3))
    # the room: far points, observed by a view where they are in frame and not behind the
    # object (the blob is not solid: the cameras saw through it)
    room = _sphere(60_000, r=8.0, c=(0, 0, 0.5), seed=2)
    ptr, ov, oxy = [0], [], []
    per_point = [[] for _ in range(len(room))]
    for j, v in enumerate(base):
        uv, z = project_distorted(room, v.camera, v.pose)
        u, w = np.rint(uv[:, 0]).astype(int), np.rint(uv[:, 1]).astype(int)
        ok = (z > 0) & (u >= 0) & (u < 64) & (w >= 0) & (w < 48)
        ok[ok] &= ~obj[v.key][w[ok], u[ok]]
        for i in np.nonzero(ok)[0]:
            per_point[i].append((j, uv[i]))
    for obs in per_point:
        for j, xy in obs:
            ov.append(j)
            oxy.append(xy)
        ptr.append(len(ov))
    cloud = SfmCloud(room, np.zeros((len(room), 3), np.uint8), np.zeros(len(room)),
                     np.array(ptr, np.int64), np.array(ov, np.int32),
                     np.array(oxy, np.float32), list(base))
    free_obs = _obs_depths([cloud], base)
    assert sum(len(f[2]) for f in free_obs) == len(ov) > 1000
    views = []
    for v in base:
        img = np.zeros((48, 64, 3), np.uint8)
        img[...] = (40, 160, 40)
        img[grown[v.key]] = (200, 30, 30)  # the wall has the object's colour
        views.append(View(v.key, v.stamp_ns, v.camera, v.pose, img))
    models = {v.key: (_gmm_model([40, 160, 40], 100.0), _gmm_model([30, 30, 200], 100.0),
                      np.zeros_like(obj[v.key])) for v in views}
    masks = {k: m.copy() for k, m in grown.items()}
    blob = {k: grown[k] & ~obj[k] for k in grown}
    assert sum(b.sum() for b in blob.values()) > 100
    cfg = RefineConfig(hull_add=True, hull_cut_grown=True)
    kept, p0 = hull_additions(masks, views, xyz, models, cfg, None, obj)
    n_blob = sum(b.sum() for b in blob.values())
    assert sum((kept[k] & blob[k]).sum() for k in blob) >= 0.9 * n_blob  # the hull holds it
    cfg = RefineConfig(hull_add=True, hull_cut_grown=True, hull_free=2)
    out, p = hull_additions(masks, views, xyz, models, cfg, None, obj, free_obs=free_obs)
    assert p["free_voxels"] > 0
    assert sum((out[k] & blob[k]).sum() for k in blob) <= 0.05 * n_blob
    assert all(out[k][obj[k]].all() for k in obj)  # the object's pixels stay
    # without the features (no SfM observations handed over) nothing is carved
    same, _ = hull_additions(masks, views, xyz, models, cfg, None, obj)
    assert all(np.array_equal(same[k], kept[k]) for k in kept)


def test_border_leak_hull_drops_a_leak_to_the_edge_and_keeps_a_part_that_leaves_the_frame():
    """``border_leak_hull``: growth past the silhouette out to an image side the silhouette
    does not reach leaves the mask where its rays miss the hull of all views' masks (a band of
    the object's colour up to the top edge, held by this view alone) and stays where the
    other views hold it (the object's own side, cut by the frame in this view only) --
    where the per-view ``border_leak`` would drop both."""
    from ooi_seg_ros.seg.refine import RefineConfig, _drop_border_leaks, hull_additions
    base = _ring_views(8)
    c = base[0].camera
    # view 0 looks past the sphere: its right side leaves the frame there
    cam0 = CameraIntrinsics(c.width, c.height, c.fx, c.fy, c.width - 4.0, c.cy)
    base[0] = View(base[0].key, base[0].stamp_ns, cam0, base[0].pose)
    xyz = _sphere(1500)
    full = point_masks(xyz, np.full(len(xyz), 0.05), base, MaskConfig(closing_kernel=3))
    k0 = base[0].key
    H, W = full[k0].shape
    assert full[k0][:, W - 1].any() and not full[k0][0].any()
    views, sil = [], {}
    for v in base:
        img = np.zeros((H, W, 3), np.uint8)
        img[...] = (40, 160, 40)
        img[full[v.key]] = (200, 30, 30)
        views.append(View(v.key, v.stamp_ns, v.camera, v.pose, img))
        sil[v.key] = full[v.key].copy()
    sil[k0] &= (np.arange(W) < W - 6)[None, :]  # no SfM point near the frame's edge
    ys, xs = np.nonzero(full[k0])
    col = int(np.median(xs[xs < W - 8]))
    leak = np.zeros_like(full[k0])
    leak[:ys.min(), col - 1:col + 2] = True  # a pole of object colour up to the top edge
    views[0].get_image()[leak] = (200, 30, 30)
    masks = {k: m.copy() for k, m in full.items()}
    masks[k0] |= leak
    part = full[k0] & ~sil[k0]
    assert part[:, W - 1].any() and leak[0].any()
    models = {v.key: (_gmm_model([40, 160, 40], 100.0), _gmm_model([30, 30, 200], 100.0),
                      np.zeros_like(full[k0])) for v in views}
    # the per-view rule drops both
    per_view = _drop_border_leaks(masks[k0], sil[k0], sil[k0], (0, H, 0, W))
    assert not per_view[leak].any() and not per_view[part].any()
    kept, p0 = hull_additions(masks, views, xyz, models, RefineConfig(hull_add=True), None, sil)
    assert kept[k0][leak].all() and p0["border_cut_px"] == 0  # off by default
    cfg = RefineConfig(hull_add=True, border_leak_hull=True)
    out, p = hull_additions(masks, views, xyz, models, cfg, None, sil)
    far = leak & ~ndimage.binary_dilation(full[k0], iterations=3)
    assert far.sum() >= 3 and not out[k0][far].any() and p["border_cut_px"] >= far.sum()
    assert out[k0][part].all()  # the sphere's side out to the frame stays
    for v in views[1:]:
        assert np.array_equal(out[v.key], kept[v.key])


def test_hull_thin_agree_adds_a_part_a_minority_of_the_views_found():
    """``hull_thin_agree``: a stalk that only 3 of 8 views' masks hold (GrabCut lost it in
    the others) is outside the majority hull, so the default adds it nowhere; with 0.3 the
    looser hull reaches it and the colour test adds it to the other views (no plane check
    given here, so no photo-consistency gate). A share at or above ``hull_agree`` is refused."""
    from ooi_seg_ros.seg.refine import RefineConfig, hull_additions, refine_masks
    views0 = _ring_views(8)
    ball = _sphere(1500)
    t = np.linspace(1.0, 1.7, 200)
    stalk = np.stack([np.full_like(t, 0.013), np.full_like(t, 0.007), t], 1)
    radii = np.r_[np.full(len(ball), 0.04), np.full(len(stalk), 0.08)]  # 2-3 px wide
    whole = point_masks(np.vstack([ball, stalk]), radii, views0, MaskConfig(closing_kernel=1))
    body = point_masks(ball, np.full(len(ball), 0.04), views0, MaskConfig(closing_kernel=1))
    views = []
    for v in views0:
        img = np.zeros(whole[v.key].shape + (3,), np.uint8)
        img[...] = (40, 160, 40)
        img[whole[v.key]] = (200, 30, 30)
        views.append(View(v.key, v.stamp_ns, v.camera, v.pose, img))
    masks = {v.key: (whole if i < 3 else body)[v.key].copy() for i, v in enumerate(views)}
    models = {v.key: (_gmm_model([40, 160, 40], 100.0), _gmm_model([30, 30, 200], 100.0),
                      np.zeros_like(body[v.key])) for v in views}
    xyz = np.vstack([ball, stalk])
    part = {v.key: whole[v.key] & ~ndimage.binary_dilation(body[v.key], iterations=2)
            for v in views}
    assert all(part[v.key].sum() >= 5 for v in views)
    out0, p0 = hull_additions(masks, views, xyz, models, RefineConfig(hull_add=True))
    assert "thin_voxels" not in p0
    assert all(out0[v.key][part[v.key]].mean() < 0.2 for v in views[3:])
    out, p = hull_additions(masks, views, xyz, models,
                            RefineConfig(hull_add=True, hull_thin_agree=0.3))
    assert p["thin_voxels"] > 0 and p["thin_added_px"] > 0
    # most of it (a 3-view hull of a 2-3 px stalk is ragged at 1-px voxels)
    assert all(out[v.key][part[v.key]].mean() > 0.5 for v in views[3:])
    for v in views:  # nothing of the background joins
        assert not (out[v.key] & ~ndimage.binary_dilation(whole[v.key], iterations=2)).any()
    with pytest.raises(ValueError):
        refine_masks({}, [], SfmCloud.empty(), SfmCloud.empty(),
                     RefineConfig(hull_add=True, hull_thin_agree=0.5))
    with pytest.raises(ValueError):
        refine_masks({}, [], SfmCloud.empty(), SfmCloud.empty(),
                     RefineConfig(hull_add=True, hull_thin_agree=0.3, hull_thin_distinct=5))


def _stalk_in_a_room(textured: bool, n=24, size=(160, 120), coarse=1):
    """Views on a ring round a red vertical stalk (radius 0.04, z 0.2-1.2) inside a
    cylindrical wall (radius 8): uniform grey, or a random colour per patch (2 deg x 0.17,
    ``coarse`` times that).
    Ray-cast, so every view sees one consistent 3D scene. Returns (views, stalk masks)."""
    w, h = size
    cam = CameraIntrinsics(w, h, 125.0, 125.0, (w - 1) / 2, (h - 1) / 2)
    uu, vv = np.meshgrid(np.arange(w), np.arange(h))
    dc = np.stack([(uu - cam.cx) / cam.fx, (vv - cam.cy) / cam.fy, np.ones_like(uu, float)], -1)
    views, stalks = [], {}
    for k in range(n):
        a = 2 * np.pi * k / n
        eye = np.array([3.0 * np.cos(a), 3.0 * np.sin(a), 1.5])
        pose = look_at(eye, np.array([0.0, 0.0, 0.5]))
        d = dc.reshape(-1, 3) @ pose.R.T
        # the wall: |eye_xy + s d_xy| = 8
        qa = (d[:, :2] ** 2).sum(1)
        qb = 2 * d[:, :2] @ eye[:2]
        qc = eye[:2] @ eye[:2] - 64.0
        s = (-qb + np.sqrt(qb ** 2 - 4 * qa * qc)) / (2 * qa)
        X = eye + s[:, None] * d
        img = np.full((len(d), 3), 120.0)
        if textured:
            cell = (np.floor((np.arctan2(X[:, 1], X[:, 0]) + np.pi) / (2 * np.pi) * 180
                             / coarse) * 64 + np.floor(X[:, 2] * 6 / coarse) + 16).astype(int)
            img[:] = np.random.default_rng(7).uniform(0, 255, (180 * 64 + 64, 3))[cell]
        # the stalk: the ray's closest approach to the z axis
        t = -(d[:, :2] @ eye[:2]) / qa
        near = np.linalg.norm(eye[:2] + t[:, None] * d[:, :2], axis=1)
        z = eye[2] + t * d[:, 2]
        hit = (near < 0.04) & (z > 0.2) & (z < 1.2) & (t > 0)
        img[hit] = (200, 30, 30)
        key = f"v{k}"
        views.append(View(key, k, cam, pose, img.reshape(h, w, 3).astype(np.uint8)))
        stalks[key] = hit.reshape(h, w)
    return views, stalks


@pytest.mark.parametrize("textured", [False, True])
def test_photo_consistent_distinct_refuses_a_wall_that_matches_at_every_depth(textured):
    """``hull_thin_distinct``: a pixel of the wall whose ray crosses the hull round a stalk
    matches its neighbours there when the wall is uniform (the plain test adds it) -- but it
    matches as well at every depth off the hull, so the distinct test refuses it; the
    stalk's own pixels match only at its depth and pass both tests, on a uniform or a
    patchy wall."""
    from ooi_seg_ros.seg.photo import PlaneCheckConfig, PlaneConsistency
    from ooi_seg_ros.seg.refine import _photo_consistent
    views, stalks = _stalk_in_a_room(textured)
    photo = PlaneConsistency(views, np.array([0.0, 0.0, 1.0, 0.0]), np.array([0.0, 0, 0.5]),
                             PlaneCheckConfig(neighbours=8, min_deg=2.0, max_deg=35.0))
    vs = 0.05
    g = np.arange(-0.3, 0.3 + 1e-9, vs)
    hull = np.stack(np.meshgrid(g, g, np.arange(0.25, 1.2, vs), indexing="ij"), -1)
    hull = hull.reshape(-1, 3)  # a fat hull round the stalk (as a loose hull is)
    for i in (0, 7, 13):
        v = views[i]
        uv, _ = project_distorted(hull, v.camera, v.pose)
        reach = np.zeros_like(stalks[v.key])
        ui, vi = np.rint(uv[:, 0]).astype(int), np.rint(uv[:, 1]).astype(int)
        reach[vi, ui] = True
        reach = ndimage.binary_closing(reach, iterations=2)
        wall = reach & ~ndimage.binary_dilation(stalks[v.key], iterations=3)
        wall = ndimage.binary_erosion(wall, iterations=3)  # inside the hull's reach
        stalk = ndimage.binary_erosion(stalks[v.key], np.ones((1, 3), bool)) & reach
        assert wall.sum() > 100 and stalk.sum() > 30
        for pix, want_plain, want_distinct in ((wall, not textured, False),
                                               (stalk, True, True)):
            ys, xs = np.nonzero(pix)
            plain = _photo_consistent(photo, i, hull, vs, ys, xs, 8, 2)
            dist = _photo_consistent(photo, i, hull, vs, ys, xs, 8, 2, distinct=4)
            assert not (dist & ~plain).any()  # the distinct test only refuses
            assert (plain.mean() > 0.9) if want_plain else (plain.mean() < 0.5)
            assert (dist.mean() > 0.9) if want_distinct else (dist.mean() < 0.1)


@pytest.mark.parametrize("textured", [False, True])
def test_photo_behind_places_a_patchy_wall_past_the_hull(textured):
    """``behind_cut``: a pixel of a patchy wall seen through the hull round a stalk has its
    colour repeated by more neighbours at a depth past the hull than at any inside it, so the
    vote places it behind the object; a uniform wall repeats at every depth (no verdict) and
    the stalk's own pixels repeat best at the stalk's depth -- neither is placed behind."""
    from ooi_seg_ros.seg.photo import PlaneCheckConfig, PlaneConsistency
    from ooi_seg_ros.seg.refine import RefineConfig, _photo_behind, refine_masks
    views, stalks = _stalk_in_a_room(textured, n=60, coarse=3)
    photo = PlaneConsistency(views, np.array([0.0, 0.0, 1.0, 0.0]), np.array([0.0, 0, 0.5]),
                             PlaneCheckConfig(neighbours=8, min_deg=2.0, max_deg=35.0))
    cfg = RefineConfig()
    vs = 0.05
    g = np.arange(-0.3, 0.3 + 1e-9, vs)
    hull = np.stack(np.meshgrid(g, g, np.arange(0.25, 1.2, vs), indexing="ij"), -1)
    hull = hull.reshape(-1, 3)
    for i in (0, 7, 13):
        v = views[i]
        uv, _ = project_distorted(hull, v.camera, v.pose)
        reach = np.zeros_like(stalks[v.key])
        reach[np.rint(uv[:, 1]).astype(int), np.rint(uv[:, 0]).astype(int)] = True
        reach = ndimage.binary_closing(reach, iterations=2)
        wall = reach & ~ndimage.binary_dilation(stalks[v.key], iterations=3)
        wall = ndimage.binary_erosion(wall, iterations=3)
        stalk = ndimage.binary_erosion(stalks[v.key], np.ones((1, 3), bool)) & reach
        for pix, want in ((wall, textured), (stalk, False)):
            ys, xs = np.nonzero(pix)
            far = _photo_behind(photo, i, hull, vs, ys, xs, cfg.behind_margin,
                                cfg.behind_max_in, cfg.behind_step_px)
            assert (far.mean() > 0.6) if want else (far.mean() < 0.05), (i, far.mean())
    # a mask of more pixels than cv2.remap's 32767 rows (a large keyframe): the same verdicts
    ys, xs = np.nonzero(wall)
    k = 32768 // len(ys) + 1
    far = _photo_behind(photo, 13, hull, vs, ys, xs, cfg.behind_margin, cfg.behind_max_in,
                        cfg.behind_step_px)
    many = _photo_behind(photo, 13, hull, vs, np.tile(ys, k), np.tile(xs, k),
                         cfg.behind_margin, cfg.behind_max_in, cfg.behind_step_px)
    assert np.array_equal(many, np.tile(far, k))
    for bad in ({"behind_cut": "all"}, {"behind_cut": "mask", "behind_margin": 0},
                {"behind_cut": "grown", "behind_max_in": -1}):
        with pytest.raises(ValueError):
            refine_masks({}, [], SfmCloud.empty(), SfmCloud.empty(), RefineConfig(**bad))


@pytest.mark.parametrize("scene", ["aircraft", "tabletop", "bicycle", "toycar", "stool"])
def test_chroma_sharpness_tells_decoded_jpeg_from_full_colour(scene):
    """Every simulator scene: its renders measure ~1 (colour as sharp as brightness), the
    same renders through JPEG q90 (4:2:0 chroma) under ``blend_max``; grey and tiny images
    measure nothing."""
    import io
    from PIL import Image
    from ooi_seg_ros.seg.refine import RefineConfig, chroma_sharpness
    from ooi_seg_ros.sim import simulate_capture
    lim = RefineConfig().blend_max
    sim = simulate_capture(scene, n_views=3, width=160, height=120, seed=1)
    for v in sim.capture.views:
        img = np.asarray(v.image)[..., :3]
        buf = io.BytesIO()
        Image.fromarray(img).save(buf, "JPEG", quality=90)
        dec = np.asarray(Image.open(buf).convert("RGB"))
        assert chroma_sharpness(img) > lim + 0.05
        assert chroma_sharpness(dec) < lim - 0.05
    grey = np.repeat(np.random.default_rng(0).integers(0, 255, (50, 60, 1)), 3, 2)
    assert chroma_sharpness(grey.astype(np.uint8)) is None
    assert chroma_sharpness(np.zeros((8, 8, 3), np.uint8)) is None


def test_graph_verdict_drops_a_ragged_halo_and_keeps_a_thin_part():
    """On compressed images (``refine.hull_graph``) the hull additions must survive a graph
    cut: of a ragged 1-px ring of blended object / background colour round a solid mask, the
    cut keeps far fewer pixels than the per-pixel colour test; a 1-px line away from any thick
    mask part is kept by the thin-part guard, which the cut alone would remove."""
    from ooi_seg_ros.seg.refine import _graph_verdict, gmm_log_likelihood
    red, green = np.array([200, 30, 30]), np.array([40, 160, 40])
    img = np.zeros((48, 64, 3)) + green
    m = np.zeros((48, 64), bool)
    m[14:34, 10:30] = True
    img[m] = red
    yy, xx = np.mgrid[:48, :64]
    ring = np.zeros_like(m)
    ring[13:35, 9:31] = True
    halo = ring & ~m & ((yy + xx) % 2 == 0)  # every other outline pixel blended
    img[halo] = 0.55 * red + 0.45 * green
    line = np.zeros_like(m)
    line[20, 36:50] = True  # a thin part the mask missed
    img[line] = red
    img = np.clip(img + np.random.default_rng(0).normal(0, 30, img.shape), 0, 255)
    img = img.astype(np.uint8)
    cand = halo | line
    fgd, bgd = _gmm_model(red[::-1], 3000.0), _gmm_model(green[::-1], 3000.0)
    col = img[cand][:, ::-1].astype(float)
    per_pixel = gmm_log_likelihood(fgd, col) > gmm_log_likelihood(bgd, col)
    got = _graph_verdict(img, m, cand, bgd, fgd, 3.0)
    on_halo, on_line = halo[cand], line[cand]
    assert per_pixel[on_halo].mean() > 0.5 and per_pixel[on_line].all()
    assert got[on_halo].mean() < 0.5 * per_pixel[on_halo].mean()
    assert got[on_line].all()
    assert not _graph_verdict(img, m, cand, bgd, fgd, 0.0)[on_line].any()  # no guard


def test_settled_widening_keeps_parts_that_join_early_and_refuses_a_later_neighbour():
    """Persistence (``settle_change``): widening from 1 spacing, a core whose two wings join
    over the first steps (the extent triples: not settled yet, so accepted) is whole and
    unchanged over a step (settled); the neighbour that joins later moves the extent far out
    and is refused. Without it, the extent at the first eps is the reference and the wings
    are cut off (aircraft seed 1 from 1 spacing); from 1.5 spacings a neighbour that already
    chains in there cannot be refused (toy car seed 1)."""
    from ooi_seg_ros.seg.density import spacing
    for seed in (1, 2, 3):
        core = _sphere(500, r=0.1, c=(0, 0, 0), seed=seed)
        x1 = 0.2 + 1.1 * spacing(core, 8)  # wings one spacing off the core, same density
        wings = [_sphere(500, r=0.1, c=(s * x1, 0, 0), seed=seed + 10 * i)
                 for i, s in ((1, 1), (2, -1))]
        nb = _sphere(1125, r=0.15, c=(x1 + 0.25 + 2.0 * spacing(core, 8), 0, 0),
                     seed=seed + 30)
        xyz = np.vstack([core, *wings, nb])
        settle = NoiseConfig(select="central", eps_scale=1.0, eps_step=0.25,
                             eps_max_scale=4.0, settle_change=0.15)
        first = NoiseConfig(select="central", eps_scale=1.0, eps_step=0.25,
                            eps_max_scale=4.0)
        k, p = noise_filter(xyz, settle, np.zeros(3), 0.25)
        assert (k < 1500).sum() == 1500 and (k >= 1500).sum() == 0
        assert p["settled_at_scale"] > 1.0 and p["stopped_at_scale"] > p["settled_at_scale"]
        k2, _ = noise_filter(xyz, first, np.zeros(3), 0.25)
        assert ((k2 >= 500) & (k2 < 1500)).sum() == 0  # the wings cut off


def test_settled_widening_takes_the_other_half_that_centres_the_set():
    """A sparse object can settle on its half nearest the convergence point (the bicycle of
    seed 6 at 320x240); the other half then joins with a jump in extent like a neighbour's,
    but it moves the set's centre towards the point the cameras converge on, so it is
    accepted as a part (``parts_joined_at``)."""
    from ooi_seg_ros.seg.density import spacing
    from ooi_seg_ros.seg.noise import _off_centre
    cfg = NoiseConfig(select="central", eps_scale=1.0, eps_step=0.25, eps_max_scale=4.0,
                      settle_change=0.15)
    for seed in (1, 2, 3):
        a = _sphere(500, r=0.1, c=(-0.06, 0, 0), seed=seed)
        b = _sphere(500, r=0.1, c=(0.14 + 1.8 * spacing(a, 8), 0, 0), seed=seed + 5)
        xyz = np.vstack([a, b])
        assert _off_centre(xyz, np.zeros(3)) < _off_centre(a, np.zeros(3))
        for c in (cfg, replace(cfg, centre_absolute=True)):  # metres too: still a part
            k, p = noise_filter(xyz, c, np.zeros(3), 0.1)
            assert len(k) == 1000 and p["parts_joined_at"][0] > p["settled_at_scale"]


def test_chroma_vote_keeps_a_shaded_object_colour_not_a_neighbours_hue():
    """The keep_discs gate: a pixel of the object's hue in shadow votes object, a pixel of
    the background's hue does not, whatever their brightness."""
    from ooi_seg_ros.seg.refine import chroma_vote
    rng = np.random.default_rng(0)
    img = np.zeros((40, 40, 3), np.float32)
    img[:, :20] = (200, 170, 40)  # a yellow object, lit
    img[:, 20:] = (60, 70, 150)  # a blue neighbour (the clutter beside it)
    img += rng.normal(0, 4, img.shape)
    obj = np.zeros((40, 40), bool)
    obj[:, :18] = True
    bg = np.zeros((40, 40), bool)
    bg[:, 22:] = True
    img[5, 18] = (60, 51, 12)  # the object's hue at 30% brightness (its shaded side)
    img[5, 21] = (120, 140, 250)  # the neighbour's hue, brighter
    test = np.zeros((40, 40), bool)
    test[5, 18] = test[5, 21] = True
    assert chroma_vote(np.clip(img, 0, 255).astype(np.uint8), obj, bg, test, 0).tolist() == [
        True, False]
    assert not chroma_vote(img, obj, np.zeros_like(bg), test, 0).any()  # no background side


def test_pixel_floor_leaves_the_mask_only_where_colour_says_ground():
    """plane_check.pixel_votes: of the pixels the per-pixel plane votes call floor, those
    inside the mask with the ground's hue leave it (grass seen through a wheel); those with
    the object's hue stay, and so do the sure-object seeds."""
    from ooi_seg_ros.seg.refine import _drop_pixel_floor
    rng = np.random.default_rng(1)
    img = np.zeros((40, 40, 3), np.float32)
    img[:] = (60, 140, 50)  # grass
    img[10:30, 10:30] = (180, 30, 30)  # a red frame ...
    img[15:25, 15:25] = (60, 140, 50)  # ... with grass seen through it
    img = np.clip(img + rng.normal(0, 4, img.shape), 0, 255).astype(np.uint8)
    res = np.zeros((40, 40), bool)
    res[10:30, 10:30] = True  # the mask holds the see-through grass
    ground = ~res  # the plane check's floor outside the mask
    pixel = np.zeros((40, 40), bool)
    pixel[15:25, 15:25] = True  # per-pixel floor votes: the grass ...
    pixel[10:12, 10:30] = True  # ... and (wrongly) a strip of the frame
    sure = np.zeros((40, 40), bool)
    sure[20, 20] = True  # an OOI point projects here
    out = _drop_pixel_floor(res, pixel, ground, img, 0, sure)
    assert not out[15:25, 15:25][~sure[15:25, 15:25]].any()  # the grass left
    assert out[20, 20]  # the seed stayed
    assert out[10:12, 10:30].all() and out[12:30, 10:15].all()  # the frame stayed
    assert not (out & ~res).any()  # only removes
    assert _drop_pixel_floor(res, None, ground, img, 0, sure) is res
    # specks: grass-coloured single pixels inside the frame that the votes call floor leave
    # without min_region, and stay with it; the see-through grass (a large region) leaves
    # either way, as does a speck on the mask's edge (it touches the outside)
    img2 = img.copy()
    for y, x in ((13, 13), (27, 26), (10, 20)):
        img2[y, x] = (60, 140, 50)
        pixel[y, x] = True
    loose = _drop_pixel_floor(res, pixel, ground, img2, 0, sure)
    kept = _drop_pixel_floor(res, pixel, ground, img2, 0, sure, min_region=9)
    assert not loose[13, 13] and not loose[27, 26]
    assert kept[13, 13] and kept[27, 26] and not kept[10, 20]
    assert not kept[15:25, 15:25][~sure[15:25, 15:25]].any()


def test_pixel_reach_lets_the_colour_decide_the_ground_between_speckled_votes():
    """plane_check.pixel_reach: ground seen through a wheel votes floor pixel by pixel only in
    specks (the rest fails the noise test). Without reach only the specks leave; with it, the
    mask pixels beside a vote are put to the same chromaticity vote, so the see-through grass
    leaves whole and the frame, of the object's hue, stays."""
    from ooi_seg_ros.seg.refine import _drop_pixel_floor
    rng = np.random.default_rng(2)
    img = np.zeros((40, 40, 3), np.float32)
    img[:] = (60, 140, 50)  # grass
    img[8:32, 8:32] = (180, 30, 30)  # a red frame ...
    img[14:26, 14:26] = (60, 140, 50)  # ... with grass seen through it
    img = np.clip(img + rng.normal(0, 4, img.shape), 0, 255).astype(np.uint8)
    res = np.zeros((40, 40), bool)
    res[8:32, 8:32] = True
    ground = ~res
    pixel = np.zeros((40, 40), bool)
    pixel[14:26:3, 14:26:3] = True  # specks of votes over the grass
    sure = np.zeros((40, 40), bool)
    hole = np.zeros((40, 40), bool)
    hole[14:26, 14:26] = True
    plain = _drop_pixel_floor(res, pixel, ground, img, 0, sure)
    assert (res & ~plain).sum() == pixel.sum()  # the specks alone
    reach = _drop_pixel_floor(res, pixel, ground, img, 0, sure, reach=2)
    assert not reach[hole].any()  # the grass left whole
    assert reach[res & ~hole].all()  # the frame stayed
    assert not (reach & ~res).any()  # only removes
    # pixel_reach_density: a lone vote does not spread (too few votes around it)
    lone = np.zeros((40, 40), bool)
    lone[20, 20] = True
    gated = _drop_pixel_floor(res, lone, ground, img, 0, sure, reach=2, density=0.2)
    assert (res & ~gated).sum() == 1
    assert not _drop_pixel_floor(res, pixel, ground, img, 0, sure, reach=2,
                                 density=0.05)[16:24, 16:24].any()  # dense specks spread


def test_pixel_reach_ground_keeps_a_pixel_whose_colour_the_ground_only_partly_shares():
    """plane_check.pixel_reach_ground: a pixel beside the votes that did not vote itself
    leaves only with a clear ground majority among its chromaticity neighbours. An olive part
    of the object, beside grass seen through it, with olive leaves on the lawn too: at the
    plain majority most of it leaves; with a 0.8 margin most of it stays, and the grass,
    whose neighbours are all ground, leaves under both."""
    from ooi_seg_ros.seg.refine import _drop_pixel_floor
    rng = np.random.default_rng(3)
    img = np.zeros((40, 40, 3), np.float32)
    img[:] = (60, 140, 50)  # grass
    img[0:7] = (110, 120, 40)  # olive leaves on the lawn
    img[8:32, 8:32] = (180, 30, 30)  # a red frame
    img[26:32, 8:32] = (110, 120, 40)  # an olive part of the object, away from the votes
    img[14:26, 14:20] = (60, 140, 50)  # grass seen through the frame
    img[14:26, 20:26] = (110, 120, 40)  # olive, beside the votes
    img = np.clip(img + rng.normal(0, 4, img.shape), 0, 255).astype(np.uint8)
    res = np.zeros((40, 40), bool)
    res[8:32, 8:32] = True
    pixel = np.zeros((40, 40), bool)
    pixel[14:26:3, 14:26:3] = True
    sure = np.zeros((40, 40), bool)
    grass = np.zeros((40, 40), bool)
    grass[14:26, 14:20] = True
    olive = np.zeros((40, 40), bool)
    olive[14:26, 20:26] = True
    plain = _drop_pixel_floor(res, pixel, ~res, img, 0, sure, reach=2)
    margin = _drop_pixel_floor(res, pixel, ~res, img, 0, sure, reach=2, reach_ground=0.8)
    assert not plain[grass].any() and not margin[grass].any()
    assert plain[olive & ~pixel].mean() < 0.4 < 0.6 < margin[olive & ~pixel].mean()
    assert margin[res & ~grass & ~olive].all()


def _cylinder(n: int, r: float, z0: float, z1: float, c=(0.0, 0.0), seed: int = 0
              ) -> np.ndarray:
    rng = np.random.default_rng(seed)
    a, rr = rng.uniform(0, 2 * np.pi, n), r * np.sqrt(rng.uniform(0, 1, n))
    return np.c_[c[0] + rr * np.cos(a), c[1] + rr * np.sin(a), rng.uniform(z0, z1, n)]


def test_widening_joins_a_part_held_up_by_the_object_not_a_neighbour_on_the_support():
    """A bonsai's crown over its pot (a sparse trunk between) joins with a jump in extent and
    pulls the box off the convergence point, as a neighbour would; it floats above the pot's
    foot, where a neighbour stands on the support plane (the 58-view real bonsai, session 16)."""
    pot = _cylinder(1500, 0.15, 0.0, 0.2, seed=1)
    crown = _sphere(1500, r=0.25, c=(0.2, 0, 0.51), seed=2)  # lowest points at z 0.26
    neighbour = _cylinder(1500, 0.15, 0.0, 0.2, c=(0.35, 0), seed=3)  # on the support, beside
    up = np.array([0.0, 0.0, 1.0, 0.0])  # the support plane z = 0, normal towards the cameras
    target = np.array([0.0, 0.0, 0.1])
    base = dict(select="central", eps_scale=1.0, eps_step=0.25, eps_max_scale=4.0,
                settle_change=0.15, max_extent_growth=1.25)
    held, off = NoiseConfig(**base, part_above=0.25), NoiseConfig(**base)
    xyz = np.vstack([pot, crown])
    k_off, p_off = noise_filter(xyz, off, target, 2.0, up)
    assert (k_off >= 1500).sum() == 0 and "stopped_at_scale" in p_off  # refused as a neighbour
    k, p = noise_filter(xyz, held, target, 2.0, up)
    assert (k >= 1500).sum() > 1400 and (k < 1500).sum() > 1400 and p["parts_held_up_at"]
    assert (noise_filter(xyz, held, target, 2.0)[0] >= 1500).sum() == 0  # no plane: no rule
    # the held-up groups must be a part's size, not a neighbour's top (here: 2x the pot's)
    small = NoiseConfig(**base, part_above=0.25, part_min_points=2.0)
    assert (noise_filter(xyz, small, target, 2.0, up)[0] >= 1500).sum() == 0
    xyz2 = np.vstack([pot, neighbour])
    k2, p2 = noise_filter(xyz2, held, target, 2.0, up)
    assert (k2 >= 1500).sum() == 0 and (k2 < 1500).sum() > 1400 and "stopped_at_scale" in p2


def test_central_weight_standing_takes_the_object_at_the_centre_not_a_larger_neighbour():
    """``central_weight="standing"``: a far orbit frames a larger neighbour on the support
    (more points within the frame radius) beside the small object the cameras converge on
    (the tabletop's plant and a box, session 70); weighted by nearness the object is the main
    cluster. A crown floating over its pot stays the main cluster, as by count."""
    plant = _cylinder(300, 0.08, 0.0, 0.25, seed=1)
    box = _cylinder(900, 0.15, 0.0, 0.2, c=(0.5, 0), seed=2)  # on the support, beside
    up = np.array([0.0, 0.0, 1.0, 0.0])  # the support plane z = 0, normal towards the cameras
    target = np.array([0.0, 0.0, 0.12])
    base = dict(select="central", eps_scale=1.0, eps_step=0.25, eps_max_scale=4.0,
                settle_change=0.15, max_extent_growth=1.25, part_above=0.25)
    xyz = np.vstack([plant, box])
    k0, _ = noise_filter(xyz, NoiseConfig(**base), target, 0.6, up)
    assert (k0 >= 300).sum() > 850  # by count: the box is the main cluster
    k1, _ = noise_filter(xyz, NoiseConfig(**base, central_weight="standing"), target, 0.6, up)
    assert (k1 < 300).sum() > 280 and (k1 >= 300).sum() == 0
    # a crown over its pot: larger, off the convergence point, floating -- kept as by count
    pot = _cylinder(300, 0.08, 0.0, 0.2, seed=3)
    crown = _sphere(1500, r=0.3, c=(0.3, 0, 0.7), seed=4)  # lowest points at z 0.4
    xyz2 = np.vstack([pot, crown])
    t2 = np.array([0.0, 0.0, 0.1])
    kc, _ = noise_filter(xyz2, NoiseConfig(**base), t2, 0.7, up)
    kl, _ = noise_filter(xyz2, NoiseConfig(**base, central_weight="linear"), t2, 0.7, up)
    ks, _ = noise_filter(xyz2, NoiseConfig(**base, central_weight="standing"), t2, 0.7, up)
    assert (kl >= 300).sum() == 0  # by nearness alone the pot, without its crown
    assert (kc >= 300).sum() > 1400 and np.array_equal(np.sort(kc), np.sort(ks))
    with pytest.raises(ValueError, match="central_weight"):
        noise_filter(xyz, NoiseConfig(**base, central_weight="near"), target, 0.7, up)


def test_central_inner_takes_the_object_wholly_nearer_than_a_neighbour_standing_beside():
    """``central_inner``: a neighbour in the outer frame can outweigh the object even by
    nearness (the tabletop's far seed 5: a box of 272 points, nearest 0.42 frame radius, over
    a plant of 125 within 0.09-0.3) and the object then joins it by its reach. A cluster that
    lies wholly nearer the convergence point than the main one comes, stands beside it and
    holds at least ``part_min_points`` as many points is the main cluster. A crown floating
    over its pot keeps the pot from taking over (not beside)."""
    plant = _cylinder(300, 0.08, 0.0, 0.25, seed=1)
    box = _cylinder(1100, 0.1, 0.0, 0.2, c=(0.38, 0), seed=2)  # on the support, beside
    xyz = np.vstack([plant, box])
    up = np.array([0.0, 0.0, 1.0, 0.0])
    target = np.array([0.0, 0.0, 0.12])
    base = dict(select="central", eps_scale=1.0, eps_step=0.25, eps_max_scale=4.0,
                settle_change=0.15, max_extent_growth=1.25, part_above=0.25,
                central_weight="standing", merge_reach_scale=1.2)
    k0, _ = noise_filter(xyz, NoiseConfig(**base), target, 0.6, up)
    assert len(k0) == len(xyz)  # the box is the main cluster, the plant within its reach
    k1, p1 = noise_filter(xyz, NoiseConfig(**base, central_inner=True), target, 0.6, up)
    assert (k1 < 300).sum() == 300 and (k1 >= 300).sum() == 0 and p1["main_share"] == 1.0
    pot = _cylinder(300, 0.08, 0.0, 0.2, seed=3)
    crown = _sphere(1500, r=0.3, c=(0.3, 0, 0.7), seed=4)  # lowest points at z 0.4
    xyz2 = np.vstack([pot, crown])
    t2 = np.array([0.0, 0.0, 0.1])
    k2, _ = noise_filter(xyz2, NoiseConfig(**base, central_inner=True), t2, 0.7, up)
    assert len(k2) == len(xyz2)


def test_lookahead_takes_a_crown_whose_first_crumbs_were_refused_but_not_a_neighbour():
    """``lookahead``: a sparse crown can first join in crumbs (a trunk's few points) that move
    the extent past ``max_extent_growth`` but are too few to count as held up, which stopped
    the widening on the pot alone (the real bonsai with 37 of its photos: 177 of 466 points,
    7 stability flips). Judged against the same kept set, a wider eps that adds the crown is
    a part and is taken; a neighbour on the support beside the pot still is not."""
    up = np.array([0.0, 0.0, 1.0, 0.0])
    target = np.array([0.0, 0.0, 0.1])
    base = dict(select="central", eps_scale=1.0, eps_step=0.25, eps_max_scale=4.0,
                settle_change=0.15, max_extent_growth=1.25, part_above=0.25,
                central_weight="standing", merge_reach_scale=1.2, widen_unclustered=True)
    pot = _cylinder(600, 0.1, 0.0, 0.2, seed=1)
    crumbs = _cylinder(20, 0.03, 0.24, 0.30, c=(0.08, 0), seed=2)  # a trunk's first points
    crown = _sphere(600, r=0.25, c=(0.2, 0, 0.63), seed=3)  # lowest points at z 0.38
    xyz = np.vstack([pot, crumbs, crown])
    k0, p0 = noise_filter(xyz, NoiseConfig(**base), target, 0.7, up)
    assert len(k0) == 600 and "stopped_at_scale" in p0  # the pot alone
    k1, p1 = noise_filter(xyz, NoiseConfig(**base, lookahead=True), target, 0.7, up)
    assert len(k1) == len(xyz) and p1["looked_ahead_from"] == [p0["stopped_at_scale"]]
    assert p1["parts_held_up_at"]
    box = _cylinder(600, 0.12, 0.0, 0.2, c=(0.3, 0), seed=4)  # on the support, beside
    for extra in ({}, {"centre_absolute": True}):  # with it, centring steps are looked for too
        k2, p2 = noise_filter(np.vstack([pot, crumbs, box]),
                              NoiseConfig(**base, lookahead=True, **extra), target, 0.7, up)
        assert len(k2) == 600 and "looked_ahead_from" not in p2
    k3, _ = noise_filter(xyz, NoiseConfig(**base, lookahead=True, centre_absolute=True),
                         target, 0.7, up)
    assert len(k3) == len(xyz)


def test_centre_absolute_refuses_a_neighbour_that_only_grows_the_box_around_the_target():
    """``centre_absolute``: a jump in extent passes as a part when it brings the set's box
    centre nearer the convergence point -- relative to the box's half-diagonal. A neighbour
    beside a well-centred object doubles the box, so the relative offset can fall while the
    centre moves away (the toy car's far seed 3: 0.020 -> 0.034 m off, 0.132 -> 0.117
    relative; clutter chained in, IoU 0.72). The centre may drift in metres only by less than
    the relative offset falls: here 0.030 -> 0.047 m (x1.57) against 0.189 -> 0.176 (x0.93),
    refused."""
    up = np.array([0.0, 0.0, 1.0, 0.0])
    target = np.array([0.0, 0.0, 0.05])
    base = dict(select="central", eps_scale=1.0, eps_step=0.25, eps_max_scale=4.0,
                settle_change=0.15, max_extent_growth=1.25, part_above=0.25,
                central_weight="standing", merge_reach_scale=1.2, widen_unclustered=True)
    car = _cylinder(800, 0.12, 0.0, 0.1, c=(-0.03, 0), seed=1)  # 3 cm off the target
    cans = [_cylinder(200, 0.07, 0.0, 0.1, c=c, seed=2 + i)  # 4 cm beside it, two sides
            for i, c in enumerate([(0.2, 0), (-0.03, -0.23)])]
    xyz = np.vstack([car] + cans)
    k0, p0 = noise_filter(xyz, NoiseConfig(**base), target, 0.8, up)
    assert (k0 >= 800).sum() == 400 and p0["parts_joined_at"]  # taken as centring
    k1, p1 = noise_filter(xyz, NoiseConfig(**base, centre_absolute=True), target, 0.8, up)
    assert (k1 >= 800).sum() == 0 and (k1 < 800).sum() == 800 and "stopped_at_scale" in p1


def test_retreat_without_centring_keeps_the_other_half_when_groups_lie_apart():
    """``retreat_centring``: the retreat also went back before a jump taken after settling
    because it centred the set -- made for a neighbour that centred the set a little (the
    sparse toy car of seed 3 at 8 views), which ``centre_absolute`` now refuses at the step
    itself. Left on, it undid the bicycle's other half when a few of the bicycle's own groups
    stayed apart at the widest eps (seed 6 at 640x360: 17% apart, half the bicycle kept, IoU
    0.54). Off, the half that centres the set stays and the groups apart are still warned."""
    from ooi_seg_ros.seg.density import spacing
    cfg = NoiseConfig(select="central", eps_scale=1.0, eps_step=0.25, eps_max_scale=4.0,
                      settle_change=0.15, merge_reach_scale=1.2, retreat=True,
                      centre_absolute=True)
    for seed in (1, 2):
        a = _sphere(500, r=0.1, c=(-0.06, 0, 0), seed=seed)
        b = _sphere(500, r=0.1, c=(0.14 + 1.8 * spacing(a, 8), 0, 0), seed=seed + 5)
        groups = [_sphere(40, r=0.02, c=(0.04, y, 0), seed=seed + 9 + i)  # apart, in reach
                  for i, y in enumerate((0.25, -0.25))]
        xyz = np.vstack([a, b] + groups)
        k0, p0 = noise_filter(xyz, cfg, np.zeros(3), 0.1)
        assert len(k0) == 500 and (k0 < 500).all() and p0["retreated_from_scale"] == 2.0
        k1, p1 = noise_filter(xyz, replace(cfg, retreat_centring=False), np.zeros(3), 0.1)
        assert len(k1) == len(xyz) and p1["parts_joined_at"] == [2.0]
        assert "retreated_from_scale" not in p1 and "group(s) apart" in p1["warning"]


def test_rebase_on_switch_takes_the_new_main_clusters_extent_as_the_reference():
    """``rebase_on_switch``: a sparse object beside a dense neighbour is in fragments at the
    first eps, so the neighbour is the main cluster and the set settles on both (the object's
    fragments lie within the neighbour's reach); a wider eps makes the object one cluster that
    outweighs the neighbour by nearness and the set switches to it. The reference extent was
    the settled set's, so when the neighbour chains to the object at a wider eps still, its
    jump passed (the tabletop's far seed 1: plant and box, IoU 0.55). Rebased, it is refused."""
    plant = _cylinder(450, 0.18, 0.0, 0.3, seed=1)  # sparse: fragments at 1-1.5 spacings
    box = _cylinder(900, 0.12, 0.0, 0.2, c=(0.39, 0), seed=2)  # dense, 0.09 from the plant
    xyz = np.vstack([plant, box])
    up = np.array([0.0, 0.0, 1.0, 0.0])
    target = np.array([0.0, 0.0, 0.12])
    base = dict(select="central", eps_scale=1.0, eps_step=0.25, eps_max_scale=4.0,
                settle_change=0.15, max_extent_growth=1.25, part_above=0.25,
                central_weight="standing", widen_unclustered=True)
    k0, p0 = noise_filter(xyz, NoiseConfig(**base), target, 0.6, up)
    assert len(k0) == len(xyz) and "rebased_at" not in p0  # the box chained back in
    k1, p1 = noise_filter(xyz, NoiseConfig(**base, rebase_on_switch=True), target, 0.6, up)
    assert (k1 < 450).sum() == 450 and (k1 >= 450).sum() == 0
    assert p1["rebased_at"] and p1["stopped_at_scale"] > p1["rebased_at"][0]


def _box(n: int, lo, hi, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(lo, hi, size=(n, 3))


def test_widening_warns_when_groups_apart_from_the_main_one_are_kept_at_the_widest_eps():
    """A sparse cloud can chain the object to a neighbour before the widening settles (the
    toy car of ``sim:toycar:5`` at 30 views, IoU 0.38); the stage then keeps the groups the
    widest eps still leaves apart because they lie within the main cluster's reach, and no
    step is ever refused. That is reported, by the share those groups hold; a few crumbs
    are not."""
    bar = _box(3000, (-0.3, -0.025, 0.0), (0.3, 0.025, 0.05), seed=1)  # the main cluster
    target = np.array([0.0, 0.0, 0.025])
    base = dict(select="central", eps_scale=1.0, eps_step=0.25, eps_max_scale=4.0,
                settle_change=0.15, max_extent_growth=1.25, merge_reach_scale=1.2)
    cfg = NoiseConfig(**base)
    for share, warned in ((0.2, True), (0.03, False)):
        m = int(round(share * 3000 / (1 - share) / 2))  # points per group
        h = np.sqrt(m / 3000 * 0.6 * 0.05) / 2  # as dense as the bar
        groups = [_box(m, (-h, y - h, 0.0), (h, y + h, 0.05), seed=2 + i)
                  for i, y in enumerate((0.2, -0.2))]  # 0.2 from the bar, within its reach
        xyz = np.vstack([bar] + groups)
        keep, p = noise_filter(xyz, cfg, target, 2.0)
        assert p["eps_scale"] == 4.0 and p["chosen_clusters"] == 3 and len(keep) > 0.99 * len(xyz)
        assert p["main_share"] == pytest.approx(1 - share, abs=0.01)
        assert ("warning" in p) == warned
        if warned:
            assert "2 group(s)" in p["warning"] and "neighbouring object" in p["warning"]
        assert "warning" not in noise_filter(xyz, NoiseConfig(**base, warn_apart_share=0.0),
                                             target, 2.0)[1]
    # the object alone: nothing apart, no warning
    lone = noise_filter(bar, cfg, target, 2.0)[1]
    assert "warning" not in lone and lone["main_share"] == 1.0


def test_retreat_keeps_the_set_from_before_a_neighbour_chained_to_it_before_it_settled():
    """A denser capture can chain a neighbour to the object at the first widening step, before
    the set settles (the toy car of seed 1 at 120 views: IoU 0.40, warned). With ``retreat``
    the warning's signs (no step refused, groups apart at the widest eps) and a step before
    settling that moved the extent out past ``max_extent_growth`` x and off the convergence
    point make the stage keep the set from before that step -- and say so."""
    bar = _box(3000, (-0.3, -0.025, 0.0), (0.3, 0.025, 0.05), seed=1)  # the object
    target = np.array([0.0, 0.0, 0.025])
    sp = spacing(bar, 8)
    x0 = 0.3 + 1.1 * sp  # a neighbour 1.1 spacings beyond the bar's end: chained at 1.25
    neighbour = _box(3000, (x0, -0.025, 0.0), (x0 + 0.6, 0.025, 0.05), seed=5)
    h = np.sqrt(400 / 3000 * 0.6 * 0.05) / 2  # two groups apart, within the bar's reach
    groups = [_box(400, (-h, y - h, 0.0), (h, y + h, 0.05), seed=2 + i)
              for i, y in enumerate((0.2, -0.2))]
    xyz = np.vstack([bar, neighbour] + groups)
    base = dict(select="central", eps_scale=1.0, eps_step=0.25, eps_max_scale=4.0,
                settle_change=0.15, max_extent_growth=1.25, merge_reach_scale=1.2)
    k, p = noise_filter(xyz, NoiseConfig(**base), target, 0.4)
    assert ((k >= 3000) & (k < 6000)).sum() == 3000 and "neighbouring object" in p["warning"]
    k, p = noise_filter(xyz, NoiseConfig(**base, retreat=True), target, 0.4)
    assert ((k >= 3000) & (k < 6000)).sum() < 50 and (k < 3000).sum() > 0.9 * 3000
    assert p["retreated_from_scale"] == 1.25 and p["eps_scale"] == 1.0
    assert "kept instead" in p["warning"] and "1.25 spacings" in p["warning"]
    # the object alone, and the warning's case of groups apart with no jump: unchanged
    for cloud in (bar, np.vstack([bar] + groups)):
        a = noise_filter(cloud, NoiseConfig(**base), target, 0.4)
        b = noise_filter(cloud, NoiseConfig(**base, retreat=True), target, 0.4)
        assert np.array_equal(a[0], b[0]) and "retreated_from_scale" not in b[1]


def _tracks_cloud(lengths, errors):
    """A cloud of len(lengths) points whose point i is observed by views 0..lengths[i]-1."""
    lengths = np.asarray(lengths, int)
    ptr = np.r_[0, np.cumsum(lengths)].astype(np.int64)
    ov = np.concatenate([np.arange(k) for k in lengths]).astype(np.int32)
    n = len(lengths)
    return SfmCloud(np.random.default_rng(0).normal(size=(n, 3)), np.zeros((n, 3), np.uint8),
                    np.asarray(errors, float), ptr, ov, np.zeros((len(ov), 2), np.float32))


def test_residual_stage_drops_multi_view_points_that_fit_their_rays_worse():
    from ooi_seg_ros.seg.residual import ResidualConfig, dof_corrected_error, residual_filter
    rng = np.random.default_rng(1)
    lengths = np.r_[np.full(40, 2), rng.integers(3, 9, 60)]
    errors = rng.uniform(0.2, 0.3, 100)
    errors[:5] = 5.0  # 2-view points: no redundancy to judge by, kept whatever their error
    errors[40:46] = 1.5  # 3+-view points far over twice the median: dropped
    cloud = _tracks_cloud(lengths, errors)
    keep, p = residual_filter(cloud, ResidualConfig(enabled=True))
    assert set(range(100)) - set(keep.tolist()) == set(range(40, 46))
    assert p["dropped"] == 6 and p["multi_view_points"] == 60
    ce = dof_corrected_error(cloud)
    assert np.isnan(ce[:40]).all()  # 2-view points carry no test
    L = lengths[40:]  # the correction: a longer track's residual is a larger share of its noise
    assert np.allclose(ce[40:], errors[40:] / np.sqrt((2 * L - 3) / (2 * L)))
    assert p["threshold_error_dof"] == pytest.approx(2 * np.median(ce[40:]))
    # off, without observations (a PLY) or with too few long tracks: every point stays
    assert len(residual_filter(cloud, ResidualConfig(enabled=False))[0]) == 100
    ply = SfmCloud.from_points(cloud.xyz)
    assert len(residual_filter(ply, ResidualConfig(enabled=True))[0]) == 100
    few = _tracks_cloud(np.r_[np.full(40, 2), np.full(5, 3)], np.r_[np.full(44, 0.2), 9.0])
    keep, p = residual_filter(few, ResidualConfig(enabled=True))
    assert len(keep) == 45 and "skipped" in p


def test_colour_mismatch_is_the_median_difference_over_the_views_framing_a_point():
    from ooi_seg_ros.seg.residual import colour_mismatch
    views = _ring_views(n=6)
    for k, v in enumerate(views):  # a red scene, except view 0 which is green
        v.image = np.zeros((48, 64, 3), np.uint8)
        v.image[..., 1 if k == 0 else 0] = 200
    xyz = np.array([[0, 0, 0.5], [0, 0, 0.5], [0, 0, 100]])  # the last is framed by none
    rgb = np.array([[200, 0, 0], [0, 0, 200], [200, 0, 0]])
    mis = colour_mismatch(xyz, rgb, views)
    assert mis[0] == 0  # red in 5 of 6 views: the median difference is 0
    assert mis[1] == 200  # blue where every view shows red (or green)
    assert np.isnan(mis[2])


def test_projected_seeds_whose_pixel_is_far_from_their_point_colour_are_dropped():
    # ``refine.seed_colour`` (an option, off): a red bar on green ground; the points on the bar
    # carry its red, and those that project onto the ground (as a point on a thin part does
    # when its projection lands one pixel beside it) lose their seed; the rest keep theirs.
    from ooi_seg_ros.core.types import CameraIntrinsics, Pose
    from ooi_seg_ros.seg.refine import _colour_seeds
    cam = CameraIntrinsics(64, 48, 50.0, 50.0, 31.5, 23.5)
    img = np.zeros((48, 64, 3), np.uint8)
    img[:] = (40, 150, 40)
    img[:, 28:36] = (200, 30, 30)
    rng = np.random.default_rng(0)
    u = np.concatenate([rng.uniform(28.6, 34.4, 30), rng.uniform(40, 60, 6)])
    v = rng.uniform(5, 43, 36)
    z = 2.0
    xyz = np.stack([(u - cam.cx) * z / cam.fx, (v - cam.cy) * z / cam.fy, np.full(36, z)], 1)
    rgb = np.tile(np.float32([200, 30, 30]), (36, 1)) + rng.normal(0, 3, (36, 3)).astype(
        np.float32)
    view = View("a", 0, cam, Pose.identity(), img)
    fg, dropped = _colour_seeds(xyz, rgb, [view], {"a": np.ones((48, 64), bool)}, 3.0)
    assert dropped == 6
    assert len(fg[0]) == 30 and np.all((fg[0][:, 0] > 28) & (fg[0][:, 0] < 35))
    # a view with no mask gets no seeds; a factor large enough keeps every seed
    fg, dropped = _colour_seeds(xyz, rgb, [view], {}, 3.0)
    assert len(fg[0]) == 0 and dropped == 0
    fg, dropped = _colour_seeds(xyz, rgb, [view], {"a": np.ones((48, 64), bool)}, 1e6)
    assert dropped == 0 and len(fg[0]) == 36


def test_grow_scale_brings_back_a_thin_part_s_lone_points_once_not_a_neighbour():
    # an object's lone points (an aircraft's gear wheels, the edge of its T-tail): a few SfM
    # points a little past DBSCAN's eps from the kept set, noise at every eps the widening
    # tries. One hop of grow_scale spacings from the
    # chosen set (the pipeline applies it once, after the noise stage and its tie-break)
    # brings them back; a neighbour farther out stays out, and so does a neighbour's own
    # cluster within reach when only unclustered points may join
    from ooi_seg_ros.seg.noise import grow_selection
    body = _sphere(2000, r=0.3, c=(0, 0, 0), seed=1)
    sp = spacing(body, 8)
    lone = np.array([[0, 0, 1], [0, 0.5, 0.5], [0, -0.5, 0.5]], float)
    lone = lone / np.linalg.norm(lone, axis=1, keepdims=True) * (0.3 + 2.5 * sp)
    far = _sphere(300, r=0.1, c=(0.3 + 0.1 + 8 * sp, 0, 0), seed=3)
    near = _sphere(300, r=0.1, c=(-0.3 - 0.1 - 2.5 * sp, 0, 0), seed=4)
    xyz = np.vstack([body, lone, far, near])
    kw = dict(select="central", eps_scale=1.0, eps_step=0.25, eps_max_scale=2.0,
              settle_change=0.15, max_extent_growth=1.25)  # the widening stops short of them
    k0, p0 = noise_filter(xyz, NoiseConfig(grow_scale=3.0, **kw), np.zeros(3), 2.0)
    assert len(p0["eps_scales_tried"]) > 1 and "grown" not in p0  # the stage does not grow
    assert (k0 < 2000).sum() == 2000 and len(k0) == 2000
    cfg = NoiseConfig(grow_scale=3.0, **kw)
    sp_in = spacing(xyz, cfg.min_samples)
    g_all = grow_selection(xyz, k0, cfg, sp_in)
    g_unc = grow_selection(xyz, k0, cfg, sp_in, p0["eps"])
    lone_i, near_i = [2000, 2001, 2002], np.arange(2303, 2603)
    assert np.isin(lone_i, g_all).all() and np.isin(lone_i, g_unc).all()
    assert not np.isin(np.arange(2003, 2303), g_all).any()  # the far neighbour: out of reach
    assert np.isin(near_i, g_all).any() and not np.isin(near_i, g_unc).any()
    assert sorted(g_unc.tolist()) == sorted(k0.tolist() + lone_i)
    assert grow_selection(xyz, k0, NoiseConfig(), sp_in).tolist() == sorted(k0.tolist())


def test_colour_vote_tells_a_point_on_the_object_from_a_floater_beside_it():
    # every view shows a red object in its centre over a green background: a point at the
    # object projects onto red in every view framing it, a point off to the side onto green
    from ooi_seg_ros.seg.residual import colour_vote
    views = _ring_views(8, size=(64, 48))
    for v in views:
        img = np.zeros((48, 64, 3), np.uint8)
        img[:] = (40, 160, 40)
        img[18:30, 26:38] = (200, 30, 30)
        v.image = img
    obj = np.array([[200, 30, 30], [190, 40, 35], [210, 25, 20]], np.uint8)
    bg = np.array([[40, 160, 40], [50, 150, 45], [30, 170, 35], [120, 120, 120]], np.uint8)
    xyz = np.array([[0, 0, 0.5], [0.0, 0.0, 1.4], [0, 0, -50]], float)
    vote = colour_vote(xyz, obj, bg, views, k=2)
    assert vote[0] == 1.0 and vote[1] == 0.0 and np.isnan(vote[2])  # the last: no view frames it
    assert np.isnan(colour_vote(xyz, obj[:0], bg, views)).all()  # no reference colours


def test_parallax_guard_measures_the_displacement_of_a_raised_plane_in_a_neighbour():
    """plane_check.parallax_guard: two nadir cameras a baseline b apart at height D over the
    plane z = 0; the ray through view 0's centre meets the plane raised by h (guard x the
    OOI points' radius) at (0, 0, h), which view 1 sees fx b h / (D (D - h)) px from the
    plane's point. With the guard on, a neighbour whose parallax is under ``parallax_px``
    gives no floor votes; far enough apart it votes as before."""
    from ooi_seg_ros.core.geometry import look_at
    from ooi_seg_ros.core.types import CameraIntrinsics, View
    from ooi_seg_ros.seg.photo import PlaneCheckConfig, PlaneConsistency, PointSet
    W, H, f, D = 128, 96, 100.0, 2.0
    rng = np.random.default_rng(0)
    tex = ndimage.gaussian_filter(rng.uniform(0, 255, (200, 200)), 1.5)
    tex = 128 + (tex - tex.mean()) * (60 / tex.std())
    cam = CameraIntrinsics(W, H, f, f, (W - 1) / 2, (H - 1) / 2)

    def view(k, x):
        eye = np.array([x, 0.0, D])
        pose = look_at(eye, eye - np.array([0, 0, 1.0]), up=np.array([0, 1.0, 0]))
        d = undistorted_dirs(cam).reshape(-1, 3) @ pose.R.T
        P = eye + d * (-D / d[:, 2:3])  # where each pixel's ray meets the floor
        g = ndimage.map_coordinates(tex, [P[:, 1] * f / D + 100, P[:, 0] * f / D + 100],
                                    order=1).reshape(H, W)
        img = np.repeat(np.clip(g, 0, 255).astype(np.uint8)[..., None], 3, axis=2)
        return View(key=str(k), stamp_ns=k, camera=cam, pose=pose, image=img)

    ring = np.c_[0.5 * np.cos(np.linspace(0, 2 * np.pi, 360, endpoint=False)),
                 0.5 * np.sin(np.linspace(0, 2 * np.pi, 360, endpoint=False)),
                 np.full(360, 0.3)]
    box = (0, H, 0, W)
    for b in (0.2, 0.02):
        views = [view(0, 0.0), view(1, b)]
        cfg = PlaneCheckConfig(enabled=True, min_deg=0.1, max_deg=40.0, rank=1,
                               min_region=1, parallax_guard=0.5)
        pc = PlaneConsistency(views, np.array([0.0, 0.0, 1.0, 0.0]), np.zeros(3), cfg)
        pc.ooi_xyz = ring
        assert pc.ooi_radius() == pytest.approx(0.5)
        h = 0.5 * 0.5
        X, hit = pc.plane_points(0, box, 0)
        par = pc._parallax(1, PointSet(X, hit), pc._raised_points(0, box, None), box, (H, W))
        assert par[H // 2, W // 2] == pytest.approx(f * b * h / (D * (D - h)), rel=1e-3)
        guarded = pc.floor_map(0, box).mean()
        pc.cfg = PlaneCheckConfig(**{**cfg.__dict__, "parallax_guard": 0.0})
        free = pc.floor_map(0, box).mean()
        assert free > 0.5  # the texture lines up through the plane either way
        if b == 0.2:  # 1.43 px at the centre: every pixel's vote stands
            assert guarded == free
        else:  # 0.14 px: a surface h above the floor would match as well; no votes
            assert guarded == 0.0
