"""Image-quality metrics under the official DELIFFAS evaluation protocol (formats doc 3.10).

Protocol (D ``Projects/EvaluationScripts/Lpips.py``), per image (it reads saved 8-bit PNGs;
:class:`Evaluator` rounds both images to 8 bits first unless ``quantize_8bit=False``):

1. the prediction is resized to the ground-truth size (bilinear, as ``cv2.resize`` default);
2. the mask is thresholded at 0.5 and eroded with a 5 x 5 square (pixels outside the image do
   not erode, as OpenCV's default border);
3. **both** images are composited on white with that mask;
4. both are cropped to 600 (H) x 496 (W) centred on the bounding box of the non-white GT pixels,
   shifted to stay inside the image (clipped to the image when it is smaller);
5. PSNR = 10 log10(1 / MSE) (images in [0, 1]); SSIM as scikit-image
   ``structural_similarity(gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
   data_range=1, channel_axis=...)``; MSE and MAE; LPIPS (VGG, v0.1) when real weights exist.
   Per-image values are averaged over the sequence.

SSIM is computed here in float64 torch with exactly scikit-image's settings: Gaussian window
with sigma 1.5 truncated at 3.5 sigma (11 x 11), K1 = 0.01, K2 = 0.03, population covariances,
the SSIM map averaged over the pixels at least 5 from the border (skimage crops that border, so
its filter padding mode never matters), then over channels.

LPIPS needs the ImageNet VGG-16 *and* the LPIPS v0.1 linear layers (the ``lpips`` package's
``weights/v0.1/vgg.pth``, keys ``lin0.model.1.weight`` ... ``lin4.model.1.weight``); FID needs
Inception-v3 weights and is not implemented. When unavailable they are reported as ``None``
with a reason, never replaced: ``lpips_random_vgg16`` (an LPIPS-style distance on the seeded
random VGG-16 with uniform channel weights) is a clearly named substitute reported beside.
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from deliffas.models.vgg import (
    PerceptualWeightsUnavailable,
    VGG16Features,
    load_vgg16_weights,
    read_state_dict,
    vgg16_weight_candidates,
)

__all__ = [
    "CROP_HW",
    "ENV_LPIPS_WEIGHTS",
    "FID_UNAVAILABLE_REASON",
    "eval_mask",
    "composite_on_white",
    "crop_window",
    "prepare_pair",
    "mse",
    "mae",
    "psnr",
    "ssim",
    "LPIPS",
    "load_lpips_linear_weights",
    "perceptual_metrics_status",
    "ImageMetrics",
    "Evaluator",
]

logger = logging.getLogger(__name__)

#: Crop size (H, W) of the official protocol.
CROP_HW = (600, 496)
#: Environment variable naming the LPIPS v0.1 VGG linear-layer file.
ENV_LPIPS_WEIGHTS = "DELIFFAS_LPIPS_WEIGHTS"
FID_UNAVAILABLE_REASON = "FID needs Inception-v3 ImageNet weights (pt_inception-2015-12-05); not found"
#: LPIPS VGG layers and their channels.
_LPIPS_LAYERS = ("relu1_2", "relu2_2", "relu3_3", "relu4_3", "relu5_3")
_LPIPS_CHANNELS = (64, 128, 256, 512, 512)
_WHITE_TOL = 0.5 / 255.0


def _check_image(name: str, x: torch.Tensor) -> None:
    if x.dim() != 3 or x.shape[0] != 3:
        raise ValueError(f"{name}: expected shape (3, H, W), got {tuple(x.shape)}")


def eval_mask(mask: torch.Tensor, threshold: float = 0.5, erode: int = 5) -> torch.Tensor:
    """Protocol mask: ``mask > threshold`` eroded with an ``erode`` x ``erode`` square.

    Args:
        mask: (H, W) float in [0, 1] (or bool).
        threshold: binarisation threshold.
        erode: side of the square structuring element (odd); 1 = no erosion.

    Returns:
        (H, W) bool. Pixels beyond the image border count as foreground (OpenCV default).
    """
    if mask.dim() != 2:
        raise ValueError(f"mask: expected shape (H, W), got {tuple(mask.shape)}")
    binary = mask.to(torch.float32) > threshold
    if erode <= 1:
        return binary
    if erode % 2 == 0:
        raise ValueError(f"eval_mask: erode must be odd, got {erode}")
    background = (~binary).to(torch.float32)[None, None]  # (1, 1, H, W)
    grown = F.max_pool2d(background, kernel_size=erode, stride=1, padding=erode // 2)  # pads with -inf
    return grown[0, 0] < 0.5


def composite_on_white(image: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Keep ``image`` where ``mask`` and white elsewhere: (3, H, W), (H, W) bool -> (3, H, W)."""
    _check_image("image", image)
    return torch.where(mask[None], image, torch.ones_like(image))


def crop_window(gt_composited: torch.Tensor, crop_hw: tuple[int, int] = CROP_HW) -> tuple[int, int, int, int]:
    """Protocol crop: ``crop_hw`` centred on the bounding box of non-white GT pixels, kept inside.

    Args:
        gt_composited: (3, H, W) ground truth on white, in [0, 1].
        crop_hw: (h, w) crop size; clipped to the image when larger.

    Returns:
        (top, left, height, width). A fully white GT centres the crop on the image.
    """
    _check_image("gt_composited", gt_composited)
    height, width = gt_composited.shape[1:]
    non_white = (gt_composited < 1.0 - _WHITE_TOL).any(dim=0)  # (H, W)
    if non_white.any():
        rows = non_white.any(dim=1).nonzero().squeeze(1)
        cols = non_white.any(dim=0).nonzero().squeeze(1)
        cy, cx = (int(rows[0]) + int(rows[-1])) // 2, (int(cols[0]) + int(cols[-1])) // 2
    else:
        cy, cx = height // 2, width // 2
    ch, cw = min(crop_hw[0], height), min(crop_hw[1], width)
    top = min(max(cy - ch // 2, 0), height - ch)
    left = min(max(cx - cw // 2, 0), width - cw)
    return top, left, ch, cw


def prepare_pair(
    pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor, crop_hw: tuple[int, int] = CROP_HW
) -> tuple[torch.Tensor, torch.Tensor]:
    """Apply protocol steps 1-4 (resize, mask, composite, crop) to one image pair.

    Args:
        pred: (3, H', W') float in [0, 1], rendered image (resized to the GT size if different).
        gt: (3, H, W) float in [0, 1], ground truth.
        mask: (H, W) float in [0, 1], ground-truth foreground mask.
        crop_hw: crop size (H, W).

    Returns:
        (pred_crop, gt_crop), each (3, h, w) float.
    """
    _check_image("pred", pred)
    _check_image("gt", gt)
    if tuple(mask.shape) != tuple(gt.shape[1:]):
        raise ValueError(f"mask: expected shape {tuple(gt.shape[1:])}, got {tuple(mask.shape)}")
    if pred.shape != gt.shape:
        pred = F.interpolate(pred[None], size=gt.shape[1:], mode="bilinear", align_corners=False)[0]
    pred = pred.to(gt.dtype)
    m = eval_mask(mask).to(gt.device)
    pred_c, gt_c = composite_on_white(pred, m), composite_on_white(gt, m)
    top, left, h, w = crop_window(gt_c, crop_hw)
    return pred_c[:, top : top + h, left : left + w], gt_c[:, top : top + h, left : left + w]


def mse(pred: torch.Tensor, gt: torch.Tensor) -> float:
    """Mean squared error over all values (float64)."""
    return float(((pred.double() - gt.double()) ** 2).mean())


def mae(pred: torch.Tensor, gt: torch.Tensor) -> float:
    """Mean absolute error over all values (float64)."""
    return float((pred.double() - gt.double()).abs().mean())


def psnr(pred: torch.Tensor, gt: torch.Tensor, max_db: float | None = None) -> float:
    """PSNR = 10 log10(1 / MSE) of images in [0, 1].

    Identical images have MSE 0 and PSNR ``inf`` (the original's formula; an average including
    one is inf). Pass ``max_db`` to cap instead.
    """
    if pred.shape != gt.shape:
        raise ValueError(f"psnr: pred {tuple(pred.shape)} and gt {tuple(gt.shape)} differ")
    err = mse(pred, gt)
    value = math.inf if err == 0.0 else 10.0 * math.log10(1.0 / err)
    return value if max_db is None else min(value, max_db)


def _gaussian_window(sigma: float = 1.5, truncate: float = 3.5) -> torch.Tensor:
    """1-D Gaussian as ``scipy.ndimage.gaussian_filter1d``: radius int(truncate sigma + 0.5), float64."""
    radius = int(truncate * sigma + 0.5)
    x = torch.arange(-radius, radius + 1, dtype=torch.float64)
    w = torch.exp(-0.5 * (x / sigma) ** 2)
    return w / w.sum()


def ssim(pred: torch.Tensor, gt: torch.Tensor, data_range: float = 1.0) -> float:
    """Mean SSIM equal to scikit-image's ``structural_similarity`` with ``gaussian_weights=True,
    sigma=1.5, use_sample_covariance=False, data_range=data_range`` over channel axis 0.

    Args:
        pred: (3, H, W) float, H and W >= 11.
        gt: (3, H, W) float.
        data_range: value range (1 for [0, 1] images).

    Returns:
        Mean over channels of the mean SSIM map (border of 5 pixels excluded).
    """
    if pred.shape != gt.shape or pred.dim() != 3:
        raise ValueError(f"ssim: expected two (C, H, W) images of equal shape, got {tuple(pred.shape)}, {tuple(gt.shape)}")
    window = _gaussian_window().to(pred.device)
    k = window.numel()
    if pred.shape[1] < k or pred.shape[2] < k:
        raise ValueError(f"ssim: images must be at least {k} x {k}, got {tuple(pred.shape)}")
    channels = pred.shape[0]
    wx = window.view(1, 1, 1, k).repeat(channels, 1, 1, 1)
    wy = window.view(1, 1, k, 1).repeat(channels, 1, 1, 1)

    def blur(z: torch.Tensor) -> torch.Tensor:  # valid separable filter: (1, C, H, W) -> (1, C, H-10, W-10)
        return F.conv2d(F.conv2d(z, wx, groups=channels), wy, groups=channels)

    x = pred.double()[None]
    y = gt.double()[None]
    ux, uy = blur(x), blur(y)
    vx = blur(x * x) - ux * ux
    vy = blur(y * y) - uy * uy
    vxy = blur(x * y) - ux * uy
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    s = ((2 * ux * uy + c1) * (2 * vxy + c2)) / ((ux * ux + uy * uy + c1) * (vx + vy + c2))
    return float(s.mean(dim=(2, 3)).mean())


class LPIPS(nn.Module):
    """LPIPS distance (Zhang et al. 2018, v0.1) on a VGG-16 trunk.

    Inputs in [0, 1] are mapped to [-1, 1], shifted/scaled as LPIPS' ``ScalingLayer``, passed
    through VGG-16 (relu1_2, relu2_2, relu3_3, relu4_3, relu5_3); activations are unit-normalised
    over channels, their squared differences weighted per channel (1 x 1 "lin" layers), averaged
    over space and summed over layers.

    Args:
        backbone: VGG-16 trunk (ImageNet weights for real LPIPS).
        channel_weights: five (C_l,) non-negative tensors (the LPIPS v0.1 lin layers), or None
            for uniform weights 1 / C_l (the substitute distance; not LPIPS).
    """

    def __init__(self, backbone: VGG16Features, channel_weights: list[torch.Tensor] | None = None) -> None:
        super().__init__()
        self.backbone = backbone
        for p in self.backbone.parameters():
            p.requires_grad_(False)
        self.backbone.eval()
        if channel_weights is None:
            channel_weights = [torch.full((c,), 1.0 / c) for c in _LPIPS_CHANNELS]
        if len(channel_weights) != len(_LPIPS_CHANNELS) or any(
            w.shape != (c,) for w, c in zip(channel_weights, _LPIPS_CHANNELS)
        ):
            raise ValueError(f"LPIPS: expected channel weights of sizes {_LPIPS_CHANNELS}")
        for i, w in enumerate(channel_weights):
            self.register_buffer(f"lin{i}", w.detach().float().clone())
        self.register_buffer("shift", torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("scale", torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1), persistent=False)

    def forward(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """Distance per image pair: x, y (B, 3, H, W) in [0, 1] -> (B,)."""
        if x.dim() != 4 or x.shape[1] != 3 or x.shape != y.shape:
            raise ValueError(f"LPIPS: expected two (B, 3, H, W) batches, got {tuple(x.shape)}, {tuple(y.shape)}")
        fx = self.backbone(((2 * x - 1) - self.shift) / self.scale, _LPIPS_LAYERS)
        fy = self.backbone(((2 * y - 1) - self.shift) / self.scale, _LPIPS_LAYERS)
        total = x.new_zeros(x.shape[0])
        for i, name in enumerate(_LPIPS_LAYERS):
            a = fx[name] / (fx[name].pow(2).sum(dim=1, keepdim=True).sqrt() + 1e-10)
            b = fy[name] / (fy[name].pow(2).sum(dim=1, keepdim=True).sqrt() + 1e-10)
            weighted = ((a - b) ** 2 * getattr(self, f"lin{i}").view(1, -1, 1, 1)).sum(dim=1)  # (B, h, w)
            total = total + weighted.mean(dim=(1, 2))
        return total


def _lpips_candidates(path: str | os.PathLike | None) -> list[Path]:
    if path is not None:
        return [Path(path)]
    env = os.environ.get(ENV_LPIPS_WEIGHTS)
    return [Path(env)] if env else []


def load_lpips_linear_weights(path: str | os.PathLike) -> list[torch.Tensor]:
    """Read LPIPS v0.1 VGG lin layers (``lin{i}.model.1.weight`` of shape (1, C_l, 1, 1)).

    Args:
        path: ``.pth`` (read with ``weights_only=True``) or ``.safetensors`` file.

    Returns:
        Five (C_l,) tensors.

    Raises:
        ValueError: naming the file and key when the layout differs.
    """
    state = read_state_dict(path)
    weights = []
    for i, c in enumerate(_LPIPS_CHANNELS):
        key = f"lin{i}.model.1.weight"
        if key not in state:
            raise ValueError(f"{path}: missing key {key} (expected the lpips v0.1 vgg.pth layout)")
        w = state[key]
        if tuple(w.shape) != (1, c, 1, 1):
            raise ValueError(f"{path}: {key}: expected shape (1, {c}, 1, 1), got {tuple(w.shape)}")
        weights.append(w.reshape(c).float())
    return weights


def perceptual_metrics_status(
    vgg16_path: str | os.PathLike | None = None,
    lpips_path: str | os.PathLike | None = None,
    inception_path: str | os.PathLike | None = None,
) -> dict[str, str | None]:
    """Which perceptual metrics can be computed, without loading any network.

    Args:
        vgg16_path: ImageNet VGG-16 file (else ``$DELIFFAS_VGG16_WEIGHTS``, torch hub cache).
        lpips_path: LPIPS v0.1 VGG lin-layer file (else ``$DELIFFAS_LPIPS_WEIGHTS``).
        inception_path: Inception-v3 FID weights (FID is not implemented; reported unavailable).

    Returns:
        ``{"lpips": <weight files> | None, "lpips_reason": None | str, "fid": None,
        "fid_reason": str}``.
    """
    vgg = next((p for p in vgg16_weight_candidates(vgg16_path) if p.is_file()), None)
    lin_candidates = _lpips_candidates(lpips_path)
    lin = next((p for p in lin_candidates if p.is_file()), None)
    missing = []
    if vgg is None:
        looked = ", ".join(str(p) for p in vgg16_weight_candidates(vgg16_path))
        missing.append(f"VGG-16 ImageNet weights (looked at {looked})")
    if lin is None:
        looked = ", ".join(str(p) for p in lin_candidates) or f"no path given and ${ENV_LPIPS_WEIGHTS} unset"
        missing.append(f"LPIPS v0.1 VGG linear layers lin0..lin4 ({looked})")
    status: dict[str, str | None] = {
        "lpips": None if missing else f"vgg16={vgg}; lin={lin}",
        "lpips_reason": ("LPIPS needs " + " and ".join(missing) + "; not found") if missing else None,
        "fid": None,
        "fid_reason": FID_UNAVAILABLE_REASON,
    }
    if inception_path is not None:
        status["fid_reason"] = (
            f"FID is not implemented in deliffas (Inception-v3 weights path {inception_path} given but unused)"
        )
    return status


@dataclass(frozen=True)
class ImageMetrics:
    """Metrics of one image pair after the protocol's mask/composite/crop.

    Attributes:
        psnr: dB (inf for identical crops). ssim: scikit-image-equivalent mean SSIM.
        mse, mae: over all values of the crops in [0, 1].
        lpips: real LPIPS (VGG, v0.1) or None when its weights are unavailable.
        lpips_random_vgg16: substitute distance (random VGG-16, uniform channel weights); not LPIPS.
    """

    psnr: float
    ssim: float
    mse: float
    mae: float
    lpips: float | None
    lpips_random_vgg16: float


class Evaluator:
    """Accumulates protocol metrics over a sequence of images.

    Args:
        vgg16_path: ImageNet VGG-16 weight file (see :func:`perceptual_metrics_status`).
        lpips_path: LPIPS v0.1 VGG lin-layer file.
        inception_path: FID weights (FID not implemented; always reported unavailable).
        substitute_seed: seed of the random VGG-16 of ``lpips_random_vgg16``.
        crop_hw: protocol crop (H, W).
        device: where the perceptual networks run.
        quantize_8bit: round both images to 8 bits first (the protocol scores saved PNGs).
    """

    def __init__(
        self,
        vgg16_path: str | os.PathLike | None = None,
        lpips_path: str | os.PathLike | None = None,
        inception_path: str | os.PathLike | None = None,
        substitute_seed: int = 0,
        crop_hw: tuple[int, int] = CROP_HW,
        device: str | torch.device = "cpu",
        quantize_8bit: bool = True,
    ) -> None:
        self.crop_hw = crop_hw
        self.quantize_8bit = quantize_8bit
        self.device = torch.device(device)
        self.status = perceptual_metrics_status(vgg16_path, lpips_path, inception_path)
        self.lpips_net: LPIPS | None = None
        if self.status["lpips"] is not None:
            try:
                backbone, _ = load_vgg16_weights("vgg16-imagenet", path=vgg16_path)
                lin_path = next(p for p in _lpips_candidates(lpips_path) if p.is_file())
                self.lpips_net = LPIPS(backbone, load_lpips_linear_weights(lin_path)).to(self.device)
            except (PerceptualWeightsUnavailable, ValueError) as exc:
                self.status["lpips"] = None
                self.status["lpips_reason"] = f"LPIPS weights could not be loaded: {exc}"
        random_backbone, self.substitute_record = load_vgg16_weights("vgg16-random", seed=substitute_seed)
        self.substitute_net = LPIPS(random_backbone, None).to(self.device)
        self.records: list[ImageMetrics] = []

    @torch.no_grad()
    def add(self, pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> ImageMetrics:
        """Score one image: pred (3, H', W'), gt (3, H, W) in [0, 1], mask (H, W) in [0, 1]."""
        if self.quantize_8bit:
            pred = torch.round(pred.clamp(0, 1) * 255) / 255
            gt = torch.round(gt.clamp(0, 1) * 255) / 255
        p, g = prepare_pair(pred, gt, mask, self.crop_hw)
        pb, gb = p[None].float().to(self.device), g[None].float().to(self.device)
        lp = None if self.lpips_net is None else float(self.lpips_net(pb, gb)[0])
        m = ImageMetrics(
            psnr=psnr(p, g),
            ssim=ssim(p, g),
            mse=mse(p, g),
            mae=mae(p, g),
            lpips=lp,
            lpips_random_vgg16=float(self.substitute_net(pb, gb)[0]),
        )
        self.records.append(m)
        return m

    def summary(self) -> dict:
        """Averages over the images added so far, with the availability of LPIPS/FID.

        Returns:
            ``{"num_images", "psnr", "ssim", "mse", "mae", "lpips", "lpips_reason", "fid",
            "fid_reason", "lpips_random_vgg16", "lpips_random_vgg16_backbone"}``; ``lpips`` and
            ``fid`` are None when unavailable, with the reason beside.
        """
        n = len(self.records)

        def mean(key: str) -> float | None:
            if n == 0:
                return None
            return float(sum(getattr(r, key) for r in self.records) / n)

        return {
            "num_images": n,
            "psnr": mean("psnr"),
            "ssim": mean("ssim"),
            "mse": mean("mse"),
            "mae": mean("mae"),
            "lpips": mean("lpips") if self.lpips_net is not None else None,
            "lpips_reason": self.status["lpips_reason"],
            "fid": None,
            "fid_reason": self.status["fid_reason"],
            "lpips_random_vgg16": mean("lpips_random_vgg16"),
            "lpips_random_vgg16_backbone": self.substitute_record.to_dict(),
        }

    def per_image(self) -> list[dict]:
        """The per-image records as dicts."""
        return [asdict(r) for r in self.records]
