"""The graph's ``matches`` output against the same geometry in numpy (rasterizer.geometry)."""

import numpy as np
import pytest
import torch

from export.config import make_config
from export.model import OmniSplatEncoder
from rasterizer import geometry as geo
from rasterizer.edit import correspondences as corr
from rasterizer.scene_folder import load_scene
from rasterizer.sweep import INPUT_NAMES, OUTPUT_NAMES, default_near_far, sweep_inputs
from rasterizer.yin_yang import resize_erp


@pytest.fixture(scope="module", params=[False, True], ids=["yinyang", "erp"])
def run(request, m3d_dir):
    cfg = make_config("quality", erp_encoder=request.param, height=128, width=256, num_planes=8)
    scene = load_scene(m3d_dir)
    fa, fb = scene.frames["00"], scene.frames["02"]
    near, far = default_near_far(fa.c2w, fb.c2w)
    si = sweep_inputs(fa.c2w, fb.c2w, near=near, far=far, num_planes=cfg.num_planes, feature_size=cfg.feature_size,
                      erp_encoder=cfg.erp_encoder)
    img = lambda f: np.ascontiguousarray(resize_erp(f.image(), cfg.height, cfg.width).transpose(2, 0, 1)[None])
    feeds = {"erp_a": img(fa), "erp_b": img(fb), **{k: np.array(si[k]) for k in INPUT_NAMES[2:]}}
    with torch.no_grad():
        out = OmniSplatEncoder(cfg).eval()(*[torch.from_numpy(feeds[k]) for k in INPUT_NAMES])
    return cfg, dict(zip(OUTPUT_NAMES, (t.numpy() for t in out))), (fa.c2w, fb.c2w)


def test_match_is_the_pixel_point_seen_from_the_other_camera(run):
    cfg, out, c2ws = run
    m, rng = out["matches"], out["range_maps"]
    g_count, h, w = rng.shape[1:]
    assert m.shape == (2, g_count, h, w, len(corr.CHANNELS))
    for v in range(2):
        for g, kind in enumerate(cfg.grids):
            d = geo.grid_directions(kind, h, w)
            world = d * rng[v, g][..., None] @ c2ws[v][:3, :3].T + c2ws[v][:3, 3]
            p = geo.world_to_camera(world, c2ws[1 - v])
            got = m[v, g]
            if kind == "erp":
                col, row = geo.project_to_grid("erp", p, h, w)
                assert np.all(got[..., 0] == 0)
                dc = np.abs(np.mod(col - got[..., 1] + w / 2, w) - w / 2)
            else:
                # the graph picks Yin by its domain, the numpy side by the same test: compare in the picked grid
                yang = got[..., 0] > 0.5
                assert np.array_equal(yang, ~geo.in_grid_domain("yin", p))
                col = np.where(yang, *geo.project_to_grid("yang", p, h, w)[:1], geo.project_to_grid("yin", p, h, w)[0])
                row = np.where(yang, geo.project_to_grid("yang", p, h, w)[1], geo.project_to_grid("yin", p, h, w)[1])
                dc = np.abs(col - got[..., 1])
            assert np.percentile(dc, 99.9) < 0.05 and np.percentile(np.abs(row - got[..., 2]), 99.9) < 0.05
            assert set(np.unique(got[..., 4])) <= {0.0, 1.0, 2.0}
            np.testing.assert_allclose(got[..., 3], out["confidence"][v, g], atol=1e-6)
    # poles and the seam have matches too, and most of the scene is consistent
    assert np.all(np.isfinite(m))
    assert (m[..., 4] == corr.OK).mean() > 0.7


def test_erp_matches_land_near_gt_projection(run, m3d_dir):
    """Read on an ERP of view A: most consistent matches within 2 ERP pixels of the GT-depth projection."""
    cfg, out, c2ws = run
    scene = load_scene(m3d_dir)
    he = 64
    em = corr.erp_matches(out["matches"], 0, cfg.grids, he)
    depth = scene.frames["00"].depth()[::8, ::8]
    d = geo.grid_directions("erp", he, 2 * he)
    p = geo.world_to_camera(d * depth[..., None] @ c2ws[0][:3, :3].T + c2ws[0][:3, 3], c2ws[1])
    col, row = geo.project_to_grid("erp", p, he, 2 * he)
    err = np.hypot(np.abs(np.mod(col - em.col + he, 2 * he) - he), row - em.row)
    ok = em.valid & (depth > 0)
    assert ok.mean() > 0.7
    assert np.median(err[ok]) < 1.0
    assert np.median(err[~em.valid]) > np.median(err[ok])  # the flag picks the worse matches
