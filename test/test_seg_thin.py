"""The thin-bridge pass (``seg.thin``): spokes across a wheel's hole join the mask, texture
seen through a hole does not."""

import numpy as np
import pytest
from scipy import ndimage

from ooi_seg_ros.seg.thin import BridgeConfig, line_response, thin_bridges

cv2 = pytest.importorskip("cv2")

SIZE = 200
CENTRE = (100, 100)


def _lawn(seed: int, streaks: bool = False) -> np.ndarray:
    """Green texture: smoothed noise, optionally stretched into horizontal streaks."""
    rng = np.random.default_rng(seed)
    n = rng.normal(0.0, 1.0, (SIZE, SIZE)).astype(np.float32)
    sig = (0.6, 4.0) if streaks else (1.2, 1.2)
    n = ndimage.gaussian_filter(n, sig)
    n /= n.std()
    img = np.zeros((SIZE, SIZE, 3), np.float32)
    img[..., 0] = 60 + 12 * n
    img[..., 1] = 130 + 25 * n
    img[..., 2] = 40 + 10 * n
    return img


def _wheel(img: np.ndarray, spokes: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Draws a tyre, a hub and ``spokes`` grey spokes 1 px wide (anti-aliased); returns the
    image (uint8), the mask a refinement would leave (tyre and hub, no spokes) and the
    spokes' pixels (drawn at least half covered)."""
    yy, xx = np.mgrid[0:SIZE, 0:SIZE]
    r = np.hypot(yy - CENTRE[1], xx - CENTRE[0])
    tyre = (r >= 62) & (r <= 72)
    hub = r <= 5
    out = img.copy()
    out[tyre] = (30, 30, 30)
    out[hub] = (150, 150, 150)
    # spokes: a 4x canvas, one line 4 px wide = 1 px at the image's size
    big = np.zeros((SIZE * 4, SIZE * 4), np.uint8)
    for k in range(spokes):
        a = 2 * np.pi * (k + 0.37) / spokes
        p0 = (int(4 * (CENTRE[0] + 4 * np.cos(a))), int(4 * (CENTRE[1] + 4 * np.sin(a))))
        p1 = (int(4 * (CENTRE[0] + 63 * np.cos(a))), int(4 * (CENTRE[1] + 63 * np.sin(a))))
        cv2.line(big, p0, p1, 255, 4)
    cover = big.reshape(SIZE, 4, SIZE, 4).mean(axis=(1, 3)) / 255.0
    spoke = (cover >= 0.5) & ~tyre & ~hub
    grey = np.array([170, 170, 170], np.float32)
    c = cover[..., None] * (~tyre & ~hub)[..., None]
    out = out * (1 - c) + grey * c
    return np.clip(out, 0, 255).astype(np.uint8), tyre | hub, spoke


def test_spokes_across_a_wheel_join_the_mask_and_the_lawn_between_them_does_not():
    img, mask, spoke = _wheel(_lawn(0), spokes=16)
    add, stats = thin_bridges(img, mask, BridgeConfig(enabled=True))
    assert stats["holes"] == 1
    assert stats["bridges"] >= 12
    assert not (add & mask).any()
    found = (add & ndimage.binary_dilation(spoke)).sum()
    assert (add & spoke).sum() >= 0.6 * spoke.sum()
    # what is added lies on a spoke (or on its half-covered edge pixel)
    assert found >= 0.95 * add.sum()


def test_streaky_texture_seen_through_a_hole_adds_nothing_without_spokes():
    for streaks in (False, True):
        img, mask, _ = _wheel(_lawn(1, streaks), spokes=0)
        add, stats = thin_bridges(img, mask, BridgeConfig(enabled=True))
        assert stats["holes"] == 1
        assert add.sum() <= 0.002 * (ndimage.binary_fill_holes(mask) & ~mask).sum()


def test_streaks_do_not_hide_spokes_of_other_directions():
    img, mask, spoke = _wheel(_lawn(2, streaks=True), spokes=16)
    add, _ = thin_bridges(img, mask, BridgeConfig(enabled=True))
    assert (add & spoke).sum() >= 0.4 * spoke.sum()
    assert (add & ndimage.binary_dilation(spoke)).sum() >= 0.9 * add.sum()


def test_no_hole_no_work():
    img, mask, _ = _wheel(_lawn(3), spokes=8)
    solid = ndimage.binary_fill_holes(mask)
    add, stats = thin_bridges(img, solid, BridgeConfig(enabled=True))
    assert not add.any() and stats["holes"] == 0
    add, stats = thin_bridges(img, np.zeros_like(mask), BridgeConfig(enabled=True))
    assert not add.any()


def test_line_response_is_a_ridge_not_an_edge():
    img = np.zeros((41, 41, 3), np.uint8)
    img[:, 21:] = 200  # an edge
    img[10, :] = 120  # a horizontal line across both halves
    r = line_response(img, length=9, offset=2, orientations=12)
    assert r.shape == (12, 41, 41)
    # on the vertical edge, away from the line: no response in any direction
    assert r[:, 25:35, 19:23].max() < 1e-3
    # on the line: the horizontal direction (bin 0) responds
    assert r[0, 10, 5] > 50 and r[0, 10, 5] == r[:, 10, 5].max()


def test_an_option_out_of_range_is_refused_with_its_name():
    from ooi_seg_ros.seg.thin import check_config
    check_config(BridgeConfig(enabled=True))
    for kw, name in (({"length": 1}, "length"), ({"support": 0.0}, "support"),
                     ({"q_low": 99.0, "q_high": 90.0}, "q_low"),
                     ({"orientations": 2}, "orientations"), ({"min_inliers": 1.5}, "min_inliers")):
        with pytest.raises(ValueError, match=f"refine.bridges.{name}"):
            check_config(BridgeConfig(enabled=True, **kw))
