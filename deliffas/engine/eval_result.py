"""What :func:`deliffas.engine.evaluate.evaluate` returns (:class:`EvalResult`), with ``to_json``, the form of
``deliffas eval --json`` and of the evaluation rows the recipes, the demo and ``auto-capacity`` write.

Light (stdlib only), so readers of results import no torch.
"""

from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass
from typing import Any, KeysView, Mapping

__all__ = ["EvalResult", "ForegroundMetrics", "OfficialMetrics"]


@dataclass(frozen=True)
class OfficialMetrics:
    """The official protocol's means (white composite, 600x496 crop); a metric without its weights is None
    with the reason beside it. JSON: these keys at the top level of the result, ``protocol`` as
    ``metric_protocol``."""

    protocol: str
    psnr: float | None
    ssim: float | None
    mse: float | None
    mae: float | None
    lpips: float | None
    lpips_reason: str | None
    fid: float | None
    fid_reason: str | None
    fid_images: int | None
    flip: float | None
    flip_reason: str | None
    flip_protocol: str
    lpips_random_vgg16: float | None
    lpips_random_vgg16_backbone: Mapping[str, Any]

    @classmethod
    def from_summary(cls, summary: Mapping[str, Any]) -> OfficialMetrics:
        """From :meth:`deliffas.models.metrics.Evaluator.summary`."""
        return cls(**{f.name: summary[f.name] for f in dataclasses.fields(cls)})

    def to_json(self) -> dict:
        data = dataclasses.asdict(self)
        return {"metric_protocol": data.pop("protocol"), **data}


@dataclass(frozen=True)
class ForegroundMetrics:
    """The headline block: PSNR, SSIM, FLIP and LPIPS in the person's padded box, and the masked PSNR."""

    protocol: str
    psnr: float | None
    ssim: float | None
    masked_psnr: float | None
    masked_protocol: str
    lpips: float | None
    lpips_reason: str | None
    flip: float | None
    flip_reason: str | None

    def to_json(self) -> dict:
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class EvalResult:
    """One evaluation of a run on a split: what was evaluated, the metrics with their protocols, and the timing.

    ``to_json`` gives the keys of ``deliffas eval --json``: these fields, ``official``'s flattened into the
    top level (``OfficialMetrics``), ``foreground`` as an object.
    """

    run: str
    split: str
    is_test_split: bool
    protocol: str
    """The frames protocol (``paper`` = every 10th frame, ``all``), not the metrics' (``metric_protocols``)."""
    headline: str
    metric_protocols: Mapping[str, str]
    model: str | None
    preset: str | None
    num_parameters: int
    frames: int
    cameras: tuple[int, ...]
    images: int
    resolution: tuple[int, int]
    """Width, height of the evaluated images."""
    official: OfficialMetrics
    foreground: ForegroundMetrics
    warnings: tuple[str, ...]
    grid: str | None
    stage_ms: Mapping[str, float]
    """ms per image of ``uv``, ``sample``, ``mlp``; ``cnn`` per frame (shared by the frame's cameras)."""
    fps: float | None
    """Images per second of a single-view render (the stages' sum)."""
    fps_shared_cnn: float | None
    """Images per second measured, the frame's U-Net shared by its cameras."""
    device: str
    uv: str
    render_path: str
    perceptual_backbone: Mapping[str, Any] | None

    def to_json(self) -> dict:
        """The JSON-ready dict (``deliffas eval --json``; the evaluation rows of reports and recipes)."""
        return {"run": self.run, "split": self.split, "is_test_split": self.is_test_split, "protocol": self.protocol,
                "headline": self.headline, "metric_protocols": dict(self.metric_protocols), "model": self.model,
                "preset": self.preset, "num_parameters": self.num_parameters, "frames": self.frames,
                "cameras": list(self.cameras), "images": self.images, "resolution": list(self.resolution),
                **self.official.to_json(), "foreground": self.foreground.to_json(), "warnings": list(self.warnings),
                "grid": self.grid, "stage_ms": dict(self.stage_ms), "fps": self.fps,
                "fps_shared_cnn": self.fps_shared_cnn, "device": self.device, "uv": self.uv,
                "render_path": self.render_path,
                "perceptual_backbone": None if self.perceptual_backbone is None else dict(self.perceptual_backbone)}

    def keys(self) -> KeysView[str]:
        """Deprecated (removed in the next release): dict-style reading of the ``to_json`` keys, for callers
        written against the dict ``evaluate`` returned before; use the fields or ``to_json()``."""
        warnings.warn("reading an EvalResult as a dict is deprecated; use its fields or to_json()",
                      DeprecationWarning, stacklevel=2)
        return self.to_json().keys()

    def __getitem__(self, key: str) -> Any:
        """Deprecated, as :meth:`keys`."""
        warnings.warn("reading an EvalResult as a dict is deprecated; use its fields or to_json()",
                      DeprecationWarning, stacklevel=2)
        return self.to_json()[key]
