"""bench.edit helpers: the pseudo-GT carry and the weighted IoU."""

import numpy as np

from bench.edit import gt_carry, weighted_iou


def test_gt_carry_same_camera_is_identity_and_occlusion_is_void():
    h, w = 8, 16
    depth = np.full((h, w), 2.0, np.float32)
    to_a, visible = gt_carry(depth, depth, np.eye(4), np.eye(4))
    assert np.array_equal(to_a.reshape(h, w), np.arange(h * w).reshape(h, w)) and visible.all()
    occluder = depth.copy()
    occluder[2, 5] = 1.0  # A sees something nearer along that ray: that B pixel is void
    depth_b = depth.copy()
    depth_b[3, 7] = 0.0  # unknown GT range: void
    _, visible = gt_carry(depth_b, occluder, np.eye(4), np.eye(4))
    assert not visible[2, 5] and not visible[3, 7] and visible.sum() == h * w - 2


def test_weighted_iou_counts_valid_pixels_with_cos_latitude():
    h, w = 4, 8
    gt = np.zeros((h, w), bool)
    gt[1, :4] = True
    pred = gt.copy()
    assert weighted_iou(pred, gt, np.ones((h, w), bool)) == 1.0
    pred[2, :4] = True  # rows 1 and 2 have the same weight (symmetric about the equator)
    assert abs(weighted_iou(pred, gt, np.ones((h, w), bool)) - 0.5) < 1e-9
    valid = np.ones((h, w), bool)
    valid[2] = False  # the extra row is void: not counted
    assert weighted_iou(pred, gt, valid) == 1.0
    assert weighted_iou(np.zeros((h, w), bool), np.zeros((h, w), bool), valid) == 1.0
