"""Cameras: concatenation and resizing."""

import torch

from metegs.cameras import Cameras


def test_cat_keeps_views_in_order_and_drops_partial_optional_fields():
    a = Cameras.create(torch.eye(4)[None].repeat(2, 1, 1), 10, 11, 5, 6, 20, 12, exposure_time_s=0.01)
    b = Cameras.create(torch.eye(4)[None], 30, 31, 7, 8, 40, 24)
    both = Cameras.cat([a, b])
    assert len(both) == 3
    assert both.fx.tolist() == [10, 10, 30] and both.width.tolist() == [20, 20, 40]
    assert both.exposure_time_s is None  # b has none
    assert torch.allclose(Cameras.cat([a, a]).exposure_time_s, torch.full((4,), 0.01))


def test_resized_scales_intrinsics_with_the_image():
    cam = Cameras.create(torch.eye(4)[None], 100, 120, 50, 40, 200, 160).resized(50, 40)
    assert cam.fx.tolist() == [25] and cam.fy.tolist() == [30] and cam.cx.tolist() == [12.5] and cam.cy.tolist() == [10]
