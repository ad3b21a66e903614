"""FastConfig: how the real-time path renders (one frozen record; nothing here reads the environment)."""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

if TYPE_CHECKING:
    import torch

__all__ = ["FastConfig", "Dtype"]

Dtype = Literal["auto", "float32", "bfloat16"]


@dataclass(frozen=True)
class FastConfig:
    """How the CPU fast path renders (``deliffas.fast.frame``); None where a config takes one = the plain path.

    The CLI maps the ``DELIFFAS_FAST_*`` environment variables onto it (``deliffas.cli.fast_env``)."""

    rasterize: bool = True
    """uvs by rasterisation (False: the open3d ray caster, as the plain path)."""
    dtype: Dtype = "auto"
    """The MLP's dtype: "auto" = bf16 where the CPU has native bf16, else fp32."""
    fused: bool = True
    """Sampling, encodings and the whole MLP in one C pass (``FastShader.shade_fused``): its hidden layers in bf16
    when ``dtype`` resolves to bf16 and the kernel has native bf16 dot products, else in fp32; False = the
    per-stage path (inputs, then the MLP in ``dtype``)."""
    pe_table: bool = True
    """The fused fp32 pass takes the first layer's encoded part from per-coordinate tables
    (``FastShader.encoding_table``: within 1e-4 of the exact pass, about 95 dB); False = the exact encoding."""
    project_features: bool = True
    """The fused fp32 pass samples the feature layer's feature part from maps projected once per frame's features
    (``FastShader.projected_maps``: the same sums in another order, within 1e-6) instead of sampling the features
    and multiplying; False = the features (cheaper where each frame's features are shaded once, as in a video)."""
    in_flight: int = 0
    """Frames ``render_stream`` renders at once: 0 = auto (one per CPU core, at most 2), 1 = sequentially."""

    def __post_init__(self) -> None:
        if self.dtype not in ("auto", "float32", "bfloat16"):
            raise ValueError(f"FastConfig: dtype must be auto, float32 or bfloat16, got {self.dtype!r}")
        if not isinstance(self.in_flight, int) or self.in_flight < 0:
            raise ValueError(f"FastConfig: in_flight must be an int >= 0 (0 = auto), got {self.in_flight!r}")

    def frames_in_flight(self) -> int:
        """The resolved number of frames in flight (>= 1)."""
        return self.in_flight or max(1, min(2, os.cpu_count() or 1))

    def torch_dtype(self) -> torch.dtype:
        """The resolved MLP dtype."""
        import torch  # imported here: the CLI reads the configs holding a FastConfig without torch (--help)

        from deliffas.fast.shade import native_bf16  # local: torch, as above

        name = self.dtype if self.dtype != "auto" else ("bfloat16" if native_bf16() else "float32")
        return torch.bfloat16 if name == "bfloat16" else torch.float32
