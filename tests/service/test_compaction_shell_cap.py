"""A count cap below the environment shell's size still gives a scene that covers its references' views."""

import io

import numpy as np
from PIL import Image

from rasterizer.render import render
from service.encoder import OnnxEncoder
from service.inputs import RENDER_CUT_SIGMA
from service.pipeline import PipelineOptions, build_scene

from ._support import panorama


def test_cap_below_the_shell_widens_the_discs_it_keeps(model_path):
    """The cap thins the shell; each disc kept covers the ones dropped beside it, so a render at a reference
    (as the service renders: plain composite, cut footprints) shows the upload, not black gaps."""
    enc = OnnxEncoder(model_path, threads=1)
    a, b = (np.asarray(Image.open(io.BytesIO(panorama(height=enc.height, seed=s, shift=8 * s)))) for s in (1, 2))
    c2w_b = np.eye(4)
    c2w_b[0, 3] = 0.5
    full = build_scene(enc, a, b, np.eye(4), c2w_b, PipelineOptions.from_dict({}))
    assert full.info["shell"] > 400  # the cap below thins it at least fourfold
    cap = 100
    scene = build_scene(enc, a, b, np.eye(4), c2w_b, PipelineOptions.from_dict({"compaction": {"max_count": cap}}))
    assert len(scene.gaussians) == cap and scene.info["shell"] == cap
    target = np.asarray(Image.fromarray(a).resize((128, 64), Image.BILINEAR), np.float32) / 255.0
    out = render(scene.gaussians, np.eye(4), width=128, near=0.1 * scene.info["near"], normalize=False,
                 cut_sigma=RENDER_CUT_SIGMA, backdrop=scene.info["shell"])
    assert np.isfinite(out.colour).all()
    assert out.alpha.mean() > 0.95  # every disc at its lattice size covered about a seventh
    assert np.abs(np.clip(out.colour, 0, 1) - target).mean() < 0.2  # the upload, blurred; black is ~0.5 away
