"""Image-quality metrics: the official DELIFFAS protocol, the foreground protocol and the perceptual scores.

**Official protocol** (formats doc 3.10, D ``Projects/EvaluationScripts/Lpips.py``), per image (it
reads saved 8-bit PNGs; :class:`Evaluator` rounds both images to 8 bits first unless
``quantize_8bit=False``):

1. the prediction is resized to the ground-truth size (bilinear, as ``cv2.resize`` default);
2. the mask is thresholded at 0.5 and eroded with a 5 x 5 square (pixels outside the image do
   not erode, as OpenCV's default border);
3. **both** images are composited on white with that mask;
4. both are cropped to 600 (H) x 496 (W) centred on the bounding box of the non-white GT pixels,
   shifted to stay inside the image (clipped to the image when it is smaller);
5. PSNR, SSIM (``deliffas.models.image_metrics``), MSE and MAE; LPIPS (VGG, v0.1) when real weights
   exist; FLIP. Per-image values are averaged over the sequence; FID is over the set of crops.

At small images that crop is mostly shared white background: a blurry blob scores 25 dB. The
**foreground protocol** (``deliffas.models.foreground``) is reported beside it: PSNR, SSIM, LPIPS
and FLIP inside the person's padded mask box (prediction as rendered, ground truth over black) and
PSNR over the mask pixels. :data:`METRICS` lists every per-image metric with its protocol.

Perceptual scores are never replaced by stand-ins: LPIPS needs the ImageNet VGG-16 and the lpips
v0.1 linear layers, FID pytorch-fid's Inception weights (``deliffas.models.fid``); absent, each is
``None`` with the reason. FLIP (``deliffas.models.flip``) needs no ImageNet weights.
``lpips_random_vgg16`` (an LPIPS-style distance on the seeded random VGG-16 with uniform channel
weights) is a clearly named substitute reported beside LPIPS.
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import asdict, dataclass
from typing import Callable

import numpy as np
import torch
import torch.nn.functional as F

from deliffas.models.fid import FIDInceptionV3, fid_from_features, inception_candidates, load_fid_inception
from deliffas.models.flip import FLIP_PROTOCOL, flip_error, flip_status
from deliffas.models.foreground import align_prediction, fg_psnr, fg_ssim, foreground_pair, masked_psnr
from deliffas.models.image_metrics import mae, mse, psnr, ssim
from deliffas.models.lpips import ENV_LPIPS_WEIGHTS, LPIPS, load_lpips_linear_weights, lpips_candidates
from deliffas.models.vgg import PerceptualWeightsUnavailable, load_vgg16_weights, vgg16_weight_candidates

__all__ = [
    "CROP_HW",
    "ENV_LPIPS_WEIGHTS",
    "FID_UNAVAILABLE_REASON",
    "OFFICIAL_PROTOCOL",
    "FOREGROUND_PROTOCOL",
    "MASKED_PROTOCOL",
    "METRICS",
    "MetricSpec",
    "eval_mask",
    "composite_on_white",
    "crop_window",
    "prepare_pair",
    "official_psnr",
    "official_ssim",
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
FID_UNAVAILABLE_REASON = ("FID needs pytorch-fid's Inception-v3 weights (pt_inception-2015-12-05-6726825d.pth): "
                          "pass --inception-path, set $DELIFFAS_INCEPTION_WEIGHTS or put the file in the torch hub "
                          "cache's checkpoints/; not found")
OFFICIAL_PROTOCOL = ("official: 8-bit, eroded mask (5x5), both images composited on white, 600x496 crop centred "
                     "on the person (clipped to the image)")
FOREGROUND_PROTOCOL = ("foreground: padded mask bounding box (10% of its longer side, >= 4 px), prediction as "
                       "rendered vs ground truth over black, 8-bit")
MASKED_PROTOCOL = "masked: mean over the ground-truth mask pixels (mask > 0.5) only, 8-bit"
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
    pred = align_prediction(pred, gt, mask)
    m = eval_mask(mask).to(gt.device)
    pred_c, gt_c = composite_on_white(pred, m), composite_on_white(gt, m)
    top, left, h, w = crop_window(gt_c, crop_hw)
    return pred_c[:, top : top + h, left : left + w], gt_c[:, top : top + h, left : left + w]


def _on_pairs(pair: Callable, metric: Callable, doc: str) -> Callable[[torch.Tensor, torch.Tensor, torch.Tensor], float]:
    """``(pred, gt, mask) -> metric(*pair(pred, gt, mask))``: a metric under a protocol's crop."""

    def scored(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> float:
        return metric(*pair(pred, gt, mask))

    scored.__doc__ = doc
    return scored


official_psnr = _on_pairs(prepare_pair, psnr, "PSNR (dB) under the official protocol (:func:`prepare_pair`).")
official_ssim = _on_pairs(prepare_pair, ssim, "SSIM under the official protocol (:func:`prepare_pair`).")
_official_flip = _on_pairs(prepare_pair, flip_error, "Mean LDR-FLIP under the official protocol.")
_fg_flip = _on_pairs(foreground_pair, flip_error, "Mean LDR-FLIP inside the padded foreground box.")


@dataclass(frozen=True)
class MetricSpec:
    """One per-image metric of :data:`METRICS`."""

    key: str
    """Its key in the eval JSON (``foreground.<name>`` for the foreground block)."""
    fn: Callable[[torch.Tensor, torch.Tensor, torch.Tensor], float]
    """``(pred (3, H, W), gt (3, H, W), mask (H, W)) -> float``, images in [0, 1]."""
    protocol: str
    """Which pixels it scores and how (``OFFICIAL_PROTOCOL``, ``FOREGROUND_PROTOCOL``, ``MASKED_PROTOCOL``)."""
    higher_is_better: bool
    """The direction of "better"."""


METRICS: tuple[MetricSpec, ...] = (
    MetricSpec("psnr", official_psnr, OFFICIAL_PROTOCOL, True),
    MetricSpec("ssim", official_ssim, OFFICIAL_PROTOCOL, True),
    MetricSpec("flip", _official_flip, OFFICIAL_PROTOCOL + "; " + FLIP_PROTOCOL, False),
    MetricSpec("foreground.psnr", fg_psnr, FOREGROUND_PROTOCOL, True),
    MetricSpec("foreground.ssim", fg_ssim, FOREGROUND_PROTOCOL, True),
    MetricSpec("foreground.masked_psnr", masked_psnr, MASKED_PROTOCOL, True),
    MetricSpec("foreground.flip", _fg_flip, FOREGROUND_PROTOCOL + "; " + FLIP_PROTOCOL, False),
)
"""Per-image metrics and their protocols (LPIPS, which needs weights, is computed by :class:`Evaluator`)."""


def perceptual_metrics_status(
    vgg16_path: str | os.PathLike | None = None,
    lpips_path: str | os.PathLike | None = None,
    inception_path: str | os.PathLike | None = None,
) -> dict[str, str | None]:
    """Which perceptual metrics can be computed, without loading any network.

    Args:
        vgg16_path: ImageNet VGG-16 file (else ``$DELIFFAS_VGG16_WEIGHTS``, torch hub cache).
        lpips_path: LPIPS v0.1 VGG lin-layer file (else ``$DELIFFAS_LPIPS_WEIGHTS``, the lpips package).
        inception_path: pytorch-fid's Inception-v3 file (else ``$DELIFFAS_INCEPTION_WEIGHTS``, torch hub cache).

    Returns:
        ``{"lpips": <weight files> | None, "lpips_reason": None | str, "fid": <file> | None,
        "fid_reason": None | str, "flip_reason": None | str}``.
    """
    vgg = next((p for p in vgg16_weight_candidates(vgg16_path) if p.is_file()), None)
    lin_candidates = lpips_candidates(lpips_path)
    lin = next((p for p in lin_candidates if p.is_file()), None)
    missing = []
    if vgg is None:
        looked = ", ".join(str(p) for p in vgg16_weight_candidates(vgg16_path))
        missing.append(f"VGG-16 ImageNet weights (looked at {looked})")
    if lin is None:
        looked = ", ".join(str(p) for p in lin_candidates) or f"no path given and ${ENV_LPIPS_WEIGHTS} unset"
        missing.append(f"LPIPS v0.1 VGG linear layers lin0..lin4 ({looked})")
    inception = next((p for p in inception_candidates(inception_path) if p.is_file()), None)
    fid_reason = None
    if inception is None:
        fid_reason = (FID_UNAVAILABLE_REASON if inception_path is None
                      else f"FID weights not found at {inception_path} (pytorch-fid's pt_inception-2015-12-05 file)")
    return {
        "lpips": None if missing else f"vgg16={vgg}; lin={lin}",
        "lpips_reason": ("LPIPS needs " + " and ".join(missing) + "; not found") if missing else None,
        "fid": None if inception is None else str(inception),
        "fid_reason": fid_reason,
        "flip_reason": flip_status(),
    }


@dataclass(frozen=True)
class ImageMetrics:
    """Metrics of one image pair.

    Attributes:
        psnr: dB (inf for identical crops), official protocol. ssim: scikit-image-equivalent mean SSIM.
        mse, mae: over all values of the official crops in [0, 1].
        lpips: real LPIPS (VGG, v0.1) on the official crop, or None when its weights are unavailable.
        lpips_random_vgg16: substitute distance (random VGG-16, uniform channel weights); not LPIPS.
        flip: mean LDR-FLIP on the official crop (None without flip-evaluator).
        fg_psnr, fg_ssim: inside the padded foreground box (``FOREGROUND_PROTOCOL``).
        masked_psnr: over the mask pixels (``MASKED_PROTOCOL``).
        fg_lpips: LPIPS inside the foreground box, or None.
        fg_flip: mean LDR-FLIP inside the foreground box, or None.
    """

    psnr: float
    ssim: float
    mse: float
    mae: float
    lpips: float | None
    lpips_random_vgg16: float
    flip: float | None = None
    fg_psnr: float = math.nan
    fg_ssim: float = math.nan
    masked_psnr: float = math.nan
    fg_lpips: float | None = None
    fg_flip: float | None = None


class Evaluator:
    """Accumulates official and foreground metrics over a sequence of images.

    Args:
        vgg16_path: ImageNet VGG-16 weight file (see :func:`perceptual_metrics_status`).
        lpips_path: LPIPS v0.1 VGG lin-layer file.
        inception_path: pytorch-fid's Inception-v3 weight file (FID over the official crops).
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
                lin_path = next(p for p in lpips_candidates(lpips_path) if p.is_file())
                self.lpips_net = LPIPS(backbone, load_lpips_linear_weights(lin_path)).to(self.device)
            except (PerceptualWeightsUnavailable, ValueError) as exc:
                self.status["lpips"] = None
                self.status["lpips_reason"] = f"LPIPS weights could not be loaded: {exc}"
        self.fid_net: FIDInceptionV3 | None = None
        if self.status["fid"] is not None:
            try:
                self.fid_net = load_fid_inception(self.status["fid"]).to(self.device)
            except (ValueError, OSError) as exc:
                self.status["fid"] = None
                self.status["fid_reason"] = f"FID weights could not be loaded: {exc}"
        self._fid_features: tuple[list[np.ndarray], list[np.ndarray]] = ([], [])
        random_backbone, self.substitute_record = load_vgg16_weights("vgg16-random", seed=substitute_seed)
        self.substitute_net = LPIPS(random_backbone, None).to(self.device)
        self.records: list[ImageMetrics] = []

    def _lpips(self, p: torch.Tensor, g: torch.Tensor) -> float | None:
        if self.lpips_net is None:
            return None
        return float(self.lpips_net(p[None].float().to(self.device), g[None].float().to(self.device))[0])

    @torch.no_grad()
    def add(self, pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> ImageMetrics:
        """Score one image: pred (3, H', W') as rendered, gt (3, H, W) over black (the training target),
        both in [0, 1], mask (H, W) in [0, 1]."""
        if self.quantize_8bit:
            pred = torch.round(pred.clamp(0, 1) * 255) / 255
            gt = torch.round(gt.clamp(0, 1) * 255) / 255
        p, g = prepare_pair(pred, gt, mask, self.crop_hw)
        fp, fg = foreground_pair(pred, gt, mask)
        pb, gb = p[None].float().to(self.device), g[None].float().to(self.device)
        flip_ok = self.status["flip_reason"] is None
        if self.fid_net is not None:
            self._fid_features[0].append(self.fid_net(pb).cpu().double().numpy())
            self._fid_features[1].append(self.fid_net(gb).cpu().double().numpy())
        m = ImageMetrics(
            psnr=psnr(p, g),
            ssim=ssim(p, g),
            mse=mse(p, g),
            mae=mae(p, g),
            lpips=self._lpips(p, g),
            lpips_random_vgg16=float(self.substitute_net(pb, gb)[0]),
            flip=flip_error(p, g) if flip_ok else None,
            fg_psnr=psnr(fp, fg),
            fg_ssim=ssim(fp, fg),
            masked_psnr=masked_psnr(pred, gt, mask),
            fg_lpips=self._lpips(fp, fg),
            fg_flip=flip_error(fp, fg) if flip_ok else None,
        )
        self.records.append(m)
        return m

    def _fid(self) -> tuple[float | None, str | None]:
        if self.fid_net is None:
            return None, self.status["fid_reason"]
        n = len(self._fid_features[0])
        if n < 2:
            return None, f"FID needs at least 2 images, got {n}"
        value = fid_from_features(np.concatenate(self._fid_features[0]), np.concatenate(self._fid_features[1]))
        return value, None

    def summary(self) -> dict:
        """Averages over the images added so far, each with its protocol, and the availability of LPIPS/FID/FLIP.

        Returns:
            ``{"num_images", "psnr", "ssim", "mse", "mae", "lpips", "lpips_reason", "fid", "fid_reason",
            "fid_images", "flip", "flip_reason", "lpips_random_vgg16", "lpips_random_vgg16_backbone",
            "protocol", "foreground": {"protocol", "psnr", "ssim", "masked_psnr", "masked_protocol",
            "lpips", "lpips_reason", "flip", "flip_reason"}, "flip_protocol"}``; unavailable metrics
            are None with the reason beside.
        """
        n = len(self.records)

        def mean(key: str) -> float | None:
            values = [getattr(r, key) for r in self.records]
            if n == 0 or any(v is None for v in values):
                return None
            return float(sum(values) / n)

        fid, fid_reason = self._fid()
        lpips_on = self.lpips_net is not None
        return {
            "num_images": n,
            "protocol": OFFICIAL_PROTOCOL,
            "psnr": mean("psnr"),
            "ssim": mean("ssim"),
            "mse": mean("mse"),
            "mae": mean("mae"),
            "lpips": mean("lpips") if lpips_on else None,
            "lpips_reason": self.status["lpips_reason"],
            "fid": fid,
            "fid_reason": fid_reason,
            "fid_images": n if fid is not None else None,
            "flip": mean("flip"),
            "flip_reason": self.status["flip_reason"],
            "flip_protocol": FLIP_PROTOCOL,
            "lpips_random_vgg16": mean("lpips_random_vgg16"),
            "lpips_random_vgg16_backbone": self.substitute_record.to_dict(),
            "foreground": {
                "protocol": FOREGROUND_PROTOCOL,
                "psnr": mean("fg_psnr"),
                "ssim": mean("fg_ssim"),
                "masked_psnr": mean("masked_psnr"),
                "masked_protocol": MASKED_PROTOCOL,
                "lpips": mean("fg_lpips") if lpips_on else None,
                "lpips_reason": self.status["lpips_reason"],
                "flip": mean("fg_flip"),
                "flip_reason": self.status["flip_reason"],
            },
        }

    def per_image(self) -> list[dict]:
        """The per-image records as dicts."""
        return [asdict(r) for r in self.records]
