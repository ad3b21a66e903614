"""Resource bounds: rendering and training are chunked so that peak memory stays under stated bounds.

A fresh subprocess (``memory_probe.py``) builds the paper preset's networks (U-Net widths 16..512,
MLP 8 x 256) at a reduced atlas side S = 256 and measures the growth of its peak resident set
(/proc/self/status VmHWM, reset through /proc/self/clear_refs before each phase) over the resident
set before the phase. The bounds (docs/reliability.md, with the paper-size numbers they imply):

render_frame (no grad), P pixels, N shaded rays, chunk c, feature maps F bytes:
    growth <= 2 F + 320 B * P + 4 KiB * c + 64 B * N + 16 MiB
train_step (Adam; its state already allocated), ray_chunk c, atlas S, two U-Nets:
    growth <= param bytes (gradients) + 2 * 1.5 KiB * S^2 + 16 KiB * c + 256 B * N + 64 B * P + 16 MiB

Also checked: chunking is what bounds them (the unchunked shading / training step grows with all
N rays, beyond the chunked one).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from reliability_support import COUNTS

pytestmark = pytest.mark.timeout(600)

from deliffas.engine.memory import (KIB, MIB, PEAK_PROBE_ENV, RENDER_BYTES_PER_CHUNK_RAY, RENDER_BYTES_PER_PIXEL,
                                   RENDER_BYTES_PER_RAY, SLACK, TRAIN_BYTES_PER_TEXEL, render_peak_bound,
                                   train_peak_bound)

RENDER = [470, 642, 2.0, ["16384", "all"]]
"""Half the paper frame (940 x 1285), zoomed so ~45 % of the pixels are shaded rays, chunk 16k."""
TRAIN = [256, 235, 321, 3.0, ["4096", "all"]]
"""Atlas S = 256 (paper 1024) with the paper widths; one 235 x 321 image with ~40 k rays; chunk 4096."""


@pytest.fixture(scope="module")
def probe(rel_reference) -> dict:
    if not Path("/proc/self/clear_refs").exists():
        pytest.skip("needs Linux /proc/self/clear_refs to reset the peak resident set")
    spec = {"shards": str(rel_reference), "render": RENDER, "train": TRAIN}
    env = dict(os.environ, **PEAK_PROBE_ENV)
    res = subprocess.run([sys.executable, str(Path(__file__).with_name("memory_probe.py")), json.dumps(spec)],
                         capture_output=True, text=True, timeout=540, env=env)
    assert res.returncode == 0, res.stderr[-3000:]
    out = json.loads(res.stdout.strip().splitlines()[-1])
    print("\n[memory] " + json.dumps(out))
    return out


@pytest.mark.slow
def test_render_frame_peak_stays_under_the_bound(probe):
    r = probe["render"]
    chunk, rays = r["render_chunk"], r["rays"]
    assert rays > 4 * chunk, "the frame must hold several chunks of rays"
    assert r["encode"] <= 2 * r["features_bytes"] + SLACK
    assert r["cast"] <= RENDER_BYTES_PER_PIXEL * r["pixels"] + SLACK
    bound = render_peak_bound(r["features_bytes"], r["pixels"], chunk, rays)
    assert r["render"] <= bound, f"render_frame grew {r['render'] / MIB:.0f} MiB > bound {bound / MIB:.0f} MiB"
    # the shading stage alone: bounded by the chunk, and growing with all rays when not chunked
    shade_bound = RENDER_BYTES_PER_CHUNK_RAY * chunk + RENDER_BYTES_PER_RAY * rays + SLACK
    assert r["shade"][str(chunk)] <= shade_bound
    assert r["shade"]["all"] - r["shade"][str(chunk)] >= 256 * (rays - chunk), "chunking does not bound shading"
    COUNTS["memory: bounds checked"] += 4


@pytest.mark.slow
def test_train_step_peak_stays_under_the_bound_with_a_ray_chunk(probe):
    t = probe["train"]
    chunk, rays = int(TRAIN[-1][0]), t["rays"]
    assert rays > 4 * chunk
    assert t["unet_fwd_bwd"] <= TRAIN_BYTES_PER_TEXEL * t["atlas_res"] ** 2 + SLACK
    bound = train_peak_bound(t["param_bytes"], t["atlas_res"], chunk, rays, t["pixels"])
    grown = t["train_step"][str(chunk)]
    assert grown <= bound, f"train_step grew {grown / MIB:.0f} MiB > bound {bound / MIB:.0f} MiB"
    unchunked = t["train_step"]["all"]
    assert unchunked - grown >= 2 * KIB * (rays - chunk), "ray_chunk does not bound the training step"
    COUNTS["memory: bounds checked"] += 3


def test_chunked_training_step_equals_unchunked(rel_reference):
    """ray_chunk and mlp_block change memory and speed, not the gradient (SGD: the update is the gradient)."""
    import copy

    import torch

    from deliffas.engine.data_bridge import evaluation_samples
    from deliffas.engine.train import TrainConfig, resolve_model_config, train_step
    from deliffas.models import DeliffasModel
    from deliffas.models.losses import PerceptualLoss, SaturationTerm

    samples, info = evaluation_samples(str(rel_reference), "all", max_frames=1, with_rays=True, protocol="all")
    sample = next(iter(samples))
    perceptual = PerceptualLoss.from_source("vgg16-random", seed=0)
    for variant in ("two_surface", "single_surface"):
        cfg = resolve_model_config(TrainConfig(shards="-", out="-", model=variant, preset="tiny"), info["atlas_res"],
                                   info["temporal_window"])
        torch.manual_seed(0)
        model0 = DeliffasModel(cfg)
        # margin 1e-3: the saturation penalty is non-zero on untrained U-Nets
        for weight, saturation in ((0.0, None), (0.5, None), (0.0, SaturationTerm(1.0, 1e-3))):
            updates, outs = [], []
            for chunk, block in ((None, None), (97, None), (None, 97)):
                model = copy.deepcopy(model0)
                opt = torch.optim.SGD(model.parameters(), lr=1.0)
                outs.append(train_step(model, sample, opt, torch.device("cpu"), perceptual if weight else None, weight,
                                       generator=torch.Generator().manual_seed(0), ray_chunk=chunk,
                                       saturation=saturation, mlp_block=block))
                updates.append({k: v - model0.state_dict()[k] for k, v in model.state_dict().items()
                                if v.is_floating_point()})
            for other, update in zip(outs[1:], updates[1:]):
                assert outs[0]["loss"] == pytest.approx(other["loss"], rel=1e-5)
                assert outs[0]["psnr_rays"] == pytest.approx(other["psnr_rays"], rel=1e-5)
                if saturation is not None:
                    assert outs[0]["saturation"] > 0 and outs[0]["saturation"] == pytest.approx(other["saturation"])
                for k in updates[0]:
                    scale = float(updates[0][k].abs().max()) + 1e-12
                    # 1e-9: float32 summation noise on the smallest updates (2e-6 with the saturation term)
                    assert float((updates[0][k] - update[k]).abs().max()) <= 1e-4 * scale + 1e-9, (variant, weight, k)
    with pytest.raises(ValueError, match="ray_chunk"):
        train_step(model0, sample, torch.optim.SGD(model0.parameters(), lr=1.0), torch.device("cpu"), ray_chunk=0)
    with pytest.raises(ValueError, match="mlp_block"):
        train_step(model0, sample, torch.optim.SGD(model0.parameters(), lr=1.0), torch.device("cpu"), mlp_block=0)
