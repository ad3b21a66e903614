"""What a rendered image's error is made of: pixel classes and spatial-frequency bands (pure numpy).

:class:`ErrorBudget` accumulates, over images, the squared error of a prediction against its ground
truth (both on black, ``(H, W, 3)`` in [0, 1]) split two ways:

* **by pixel class** (:func:`pixel_classes`): the person's pixels (mask > 0.5) whose ray meets the
  inner surface (``inner``), meets only the outer shell (``peeled``: garment beyond the body), meets
  neither surface (``no_ray``: the shell misses the person there), and the ``boundary`` band (within
  ``boundary_px`` of the mask's edge, whatever the ray); plus ``background`` (mask <= 0.5), which the
  foreground metrics count and the masked ones do not;
* **by spatial-frequency band** (:func:`frequency_bands`): the error image split by differences of
  Gaussians into octaves of detail (finest first), measured on the interior classes only so the edge
  of the silhouette does not leak into every band; the ground truth's own energy in each band is
  reported beside it (what detail the images carry there).

Each class's share of the masked squared error says where more data, capacity or geometry would pay.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

__all__ = ["PIXEL_CLASSES", "BAND_SIGMAS", "pixel_classes", "frequency_bands", "ErrorBudget"]

PIXEL_CLASSES: tuple[str, ...] = ("inner", "peeled", "no_ray", "boundary", "background")
"""Pixel classes, in report order (see the module docstring)."""

BAND_SIGMAS: tuple[float, ...] = (1.0, 2.0, 4.0)
"""Gaussian sigmas (px) separating the bands: detail finer than ~2 px, 2-4, 4-8 px, and coarser."""


def pixel_classes(mask: np.ndarray, ray_pixels: np.ndarray, peeled: np.ndarray, boundary_px: float = 2.0
                  ) -> np.ndarray:
    """Class index (into ``PIXEL_CLASSES``) of every pixel: (H, W) uint8.

    Args:
        mask: (H, W) foreground coverage in [0, 1].
        ray_pixels: (N,) flat pixel indices of the shaded rays.
        peeled: (N,) bool, the ray misses the inner surface (its inner uv is the outer exit).
        boundary_px: pixels of the person closer than this to the mask's edge are ``boundary``.
    """
    fg = mask > 0.5
    out = np.full(mask.shape, PIXEL_CLASSES.index("no_ray"), np.uint8)
    flat = out.reshape(-1)
    flat[ray_pixels] = np.where(peeled, PIXEL_CLASSES.index("peeled"), PIXEL_CLASSES.index("inner"))
    inside = cv2.distanceTransform(fg.astype(np.uint8), cv2.DIST_L2, 3)
    out[fg & (inside <= boundary_px)] = PIXEL_CLASSES.index("boundary")
    out[~fg] = PIXEL_CLASSES.index("background")
    return out


def frequency_bands(image: np.ndarray, sigmas: tuple[float, ...] = BAND_SIGMAS) -> list[np.ndarray]:
    """``image`` (H, W, C) split into len(sigmas) + 1 bands (finest first) that sum to it exactly:
    ``image - G_s0``, ``G_s0 - G_s1``, ..., ``G_slast`` (G_s: Gaussian blur of sigma s px)."""
    blurred = [image] + [cv2.GaussianBlur(image, (0, 0), s, borderType=cv2.BORDER_REFLECT) for s in sigmas]
    return [blurred[i] - blurred[i + 1] for i in range(len(sigmas))] + [blurred[-1]]


@dataclass
class ErrorBudget:
    """Squared error and pixel counts per class and per band, summed over the images added."""

    sigmas: tuple[float, ...] = BAND_SIGMAS
    boundary_px: float = 2.0
    class_sq: np.ndarray = field(default_factory=lambda: np.zeros(len(PIXEL_CLASSES)))
    class_px: np.ndarray = field(default_factory=lambda: np.zeros(len(PIXEL_CLASSES)))
    band_err: np.ndarray = field(default_factory=lambda: np.zeros(len(BAND_SIGMAS) + 1))
    band_gt: np.ndarray = field(default_factory=lambda: np.zeros(len(BAND_SIGMAS) + 1))
    interior_px: float = 0.0

    def add(self, pred: np.ndarray, gt: np.ndarray, mask: np.ndarray, ray_pixels: np.ndarray,
            peeled: np.ndarray) -> None:
        """One image: pred, gt (H, W, 3) on black in [0, 1]; mask (H, W); the rays as :func:`pixel_classes`."""
        cls = pixel_classes(mask, ray_pixels, peeled, self.boundary_px)
        sq = np.square(pred.astype(np.float64) - gt).sum(-1)  # (H, W), summed over channels
        self.class_sq += np.bincount(cls.ravel(), sq.ravel(), len(PIXEL_CLASSES))
        self.class_px += np.bincount(cls.ravel(), minlength=len(PIXEL_CLASSES))
        interior = np.isin(cls, [PIXEL_CLASSES.index(c) for c in ("inner", "peeled", "no_ray")])
        err_bands = frequency_bands((pred - gt).astype(np.float32), self.sigmas)
        gt_bands = frequency_bands(gt.astype(np.float32), self.sigmas)
        self.band_err += [float(np.square(b[interior]).sum()) for b in err_bands]
        self.band_gt += [float(np.square(b[interior]).sum()) for b in gt_bands]
        self.interior_px += float(interior.sum())

    def summary(self) -> dict:
        """JSON-ready: per class its share of pixels and of the masked squared error, MSE and PSNR; per band
        the error's and the ground truth's mean square (per value) on the interior, and the error's share."""
        masked = [i for i, c in enumerate(PIXEL_CLASSES) if c != "background"]
        masked_sq, masked_px = self.class_sq[masked].sum(), self.class_px[masked].sum()
        classes = {}
        for i, name in enumerate(PIXEL_CLASSES):
            px, sq = self.class_px[i], self.class_sq[i]
            mse = sq / (3 * px) if px else None
            classes[name] = {
                "pixels": int(px),
                "pixel_share": float(px / masked_px) if masked_px and name != "background" else None,
                "error_share": float(sq / masked_sq) if masked_sq and name != "background" else None,
                "mse": None if mse is None else float(mse),
                "psnr": None if not mse else float(10 * np.log10(1.0 / mse)),
            }
        n = 3 * max(self.interior_px, 1.0)
        total = self.band_err.sum()
        names = _band_names(self.sigmas)
        bands = {name: {"error_ms": float(e / n), "gt_ms": float(g / n), "error_share": float(e / total) if total else None}
                 for name, e, g in zip(names, self.band_err, self.band_gt)}
        mse = masked_sq / (3 * masked_px) if masked_px else None
        return {"masked_mse": None if mse is None else float(mse),
                "masked_psnr": None if not mse else float(10 * np.log10(1.0 / mse)),
                "classes": classes, "bands": bands, "band_sigmas_px": list(self.sigmas)}


def _band_names(sigmas: tuple[float, ...]) -> list[str]:
    """Readable band names: detail scales in pixels (a Gaussian of sigma s keeps scales above ~2 s)."""
    edges = [2 * s for s in sigmas]
    names = [f"< {edges[0]:g} px"]
    names += [f"{a:g}-{b:g} px" for a, b in zip(edges, edges[1:])]
    return names + [f"> {edges[-1]:g} px (and the mean)"]
