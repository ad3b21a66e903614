"""VGG-16 convolutional trunk with torchvision's state-dict layout, and its weight loading.

The network is ``features`` of torchvision's ``vgg16`` (configuration "D": 13 conv 3x3 + ReLU,
5 max-pools), written in plain torch so that torchvision is not needed; state-dict keys are
exactly torchvision's (``features.0.weight``, ``features.0.bias``, ``features.2.weight``, ...), so
the official ImageNet file ``vgg16-397923af.pth`` loads as is (its ``classifier.*`` keys are
ignored).

Two backbones (:func:`load_vgg16_weights`):

* ``"vgg16-imagenet"``: the ImageNet weights, read from a file: the ``path`` argument, else
  ``$DELIFFAS_VGG16_WEIGHTS``, else the torch hub cache
  (``torch.hub.get_dir()/checkpoints/vgg16-397923af.pth``, i.e. ``$TORCH_HOME/hub/...`` or
  ``~/.cache/torch/hub/...``; a ``.safetensors`` file of the same stem is accepted too). ``.pth``
  files are read with ``torch.load(weights_only=True)`` (no code execution). When no file is
  found, :class:`PerceptualWeightsUnavailable` is raised: we never fall back silently.
* ``"vgg16-random"``: a seeded random initialisation (Kaiming-normal, fan_out, ReLU gain, for the
  conv weights; zero biases), drawn in layer order from a CPU ``torch.Generator`` seeded with
  ``seed``: identical across runs and machines for a seed. Random deep features are still a
  usable perceptual loss (Liu et al., "Generic Perceptual Loss for Modeling Structured Output
  Dependencies", CVPR 2021); it is the explicit offline option, recorded as such.

Every load returns a :class:`BackboneRecord` saying which backbone was used, for run records.
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import asdict, dataclass
from pathlib import Path
from collections.abc import Mapping
from typing import Literal

import torch
from torch import nn

from deliffas import environment

__all__ = [
    "VGG16_CFG",
    "VGG16_LAYERS",
    "VGG16_HUB_FILENAME",
    "ENV_VGG16_WEIGHTS",
    "PerceptualWeightsUnavailable",
    "BackboneRecord",
    "VGG16Features",
    "vgg16_state_dict_shapes",
    "read_state_dict",
    "vgg16_weight_candidates",
    "load_vgg16_weights",
    "random_vgg16",
]

logger = logging.getLogger(__name__)

#: torchvision's vgg16 configuration "D": conv output channels, "M" = 2x2 max-pool.
VGG16_CFG: tuple[int | str, ...] = (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512, "M")
#: Index in ``features`` of each named ReLU output (torchvision indices).
VGG16_LAYERS: dict[str, int] = {
    "relu1_1": 1, "relu1_2": 3,
    "relu2_1": 6, "relu2_2": 8,
    "relu3_1": 11, "relu3_2": 13, "relu3_3": 15,
    "relu4_1": 18, "relu4_2": 20, "relu4_3": 22,
    "relu5_1": 25, "relu5_2": 27, "relu5_3": 29,
}  # fmt: skip
#: File name of torchvision's ImageNet VGG-16 weights in the torch hub cache.
VGG16_HUB_FILENAME = "vgg16-397923af.pth"
#: Environment variable naming a VGG-16 ImageNet weight file (.pth or .safetensors).
ENV_VGG16_WEIGHTS = environment.ENV_VGG16_WEIGHTS

BackboneName = Literal["vgg16-imagenet", "vgg16-random"]


class PerceptualWeightsUnavailable(FileNotFoundError):
    """Pretrained weights were asked for but no weight file was found (message lists where we looked)."""


@dataclass(frozen=True)
class BackboneRecord:
    """Which backbone a loss or metric used, to be written into run records.

    Attributes:
        name: ``"vgg16-imagenet"`` or ``"vgg16-random"``.
        path: weight file read (imagenet), else None.
        seed: generator seed (random), else None.
        init: how the weights were made (file, or the random initialisation scheme).
    """

    name: BackboneName
    path: str | None = None
    seed: int | None = None
    init: str = ""

    def to_dict(self) -> dict:
        """JSON-ready dict of the record."""
        return asdict(self)


class VGG16Features(nn.Module):
    """VGG-16 ``features`` trunk: (B, 3, H, W) ImageNet-normalised images -> named ReLU outputs.

    ``self.features`` is an ``nn.Sequential`` with torchvision's indices (conv at 0, 2, 5, 7, ...,
    ReLU right after each conv, max-pools at 4, 9, 16, 23, 30), so its state dict has torchvision's
    keys. The ReLUs are not in-place, so captured activations stay valid for autograd.
    """

    def __init__(self) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        prev = 3
        for v in VGG16_CFG:
            if v == "M":
                layers.append(nn.MaxPool2d(kernel_size=2, stride=2))
            else:
                assert isinstance(v, int)
                layers += [nn.Conv2d(prev, v, kernel_size=3, padding=1), nn.ReLU()]
                prev = v
        self.features = nn.Sequential(*layers)

    def forward(
        self, x: torch.Tensor, layers: tuple[str, ...] = ("relu1_2", "relu2_2", "relu3_3", "relu4_3")
    ) -> dict[str, torch.Tensor]:
        """Activations at the requested ReLU layers; stops after the deepest one.

        Args:
            x: (B, 3, H, W) float, ImageNet mean/std-normalised RGB.
            layers: names from :data:`VGG16_LAYERS`.

        Returns:
            name -> (B, C_l, H / 2^k, W / 2^k) activations.
        """
        unknown = [name for name in layers if name not in VGG16_LAYERS]
        if unknown:
            raise ValueError(f"VGG16Features: unknown layers {unknown}; known: {sorted(VGG16_LAYERS)}")
        if x.dim() != 4 or x.shape[1] != 3:
            raise ValueError(f"VGG16Features: x: expected shape (B, 3, H, W), got {tuple(x.shape)}")
        wanted = {VGG16_LAYERS[name]: name for name in layers}
        last = max(wanted)
        out: dict[str, torch.Tensor] = {}
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in wanted:
                out[wanted[i]] = x
            if i == last:
                break
        return out


def vgg16_state_dict_shapes() -> dict[str, tuple[int, ...]]:
    """Expected ``features.*`` keys and shapes of a torchvision VGG-16 state dict."""
    return {k: tuple(v.shape) for k, v in VGG16Features().state_dict().items()}


def read_state_dict(path: str | os.PathLike) -> dict[str, torch.Tensor]:
    """Read a tensor dict from ``.safetensors`` or a ``.pth``/``.pt`` file without unpickling code.

    Args:
        path: weight file.

    Returns:
        name -> tensor, on CPU.

    Raises:
        ValueError: naming the file when it cannot be read as a flat tensor dict.
    """
    path = Path(path)
    try:
        if path.suffix == ".safetensors":
            from safetensors.torch import load_file

            state = load_file(str(path), device="cpu")
        else:
            state = torch.load(str(path), map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - re-raised with the file named
        raise ValueError(f"{path}: cannot read weights ({type(exc).__name__}: {exc})") from exc
    if isinstance(state, Mapping) and "state_dict" in state and isinstance(state["state_dict"], Mapping):
        state = state["state_dict"]
    if not isinstance(state, Mapping) or not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise ValueError(f"{path}: expected a flat dict of tensors, got {type(state).__name__}")
    return dict(state)


def _load_features(model: VGG16Features, state: Mapping[str, torch.Tensor], source: str) -> None:
    expected = vgg16_state_dict_shapes()
    features = {k: v for k, v in state.items() if k.startswith("features.")}
    missing = sorted(set(expected) - set(features))
    unexpected = sorted(set(features) - set(expected))
    if missing or unexpected:
        raise ValueError(
            f"{source}: not a torchvision VGG-16 state dict (missing {missing[:4]}, unexpected {unexpected[:4]})"
        )
    for key, shape in expected.items():
        if tuple(features[key].shape) != shape:
            raise ValueError(f"{source}: {key}: expected shape {shape}, got {tuple(features[key].shape)}")
    ignored = [k for k in state if not k.startswith("features.")]
    if ignored:
        logger.debug("%s: ignoring %d non-feature keys (e.g. %s)", source, len(ignored), ignored[0])
    model.load_state_dict({k: v.float() for k, v in features.items()}, strict=True)


def vgg16_weight_candidates(path: str | os.PathLike | None = None) -> list[Path]:
    """Files searched for ImageNet VGG-16 weights, in order (see module docstring)."""
    if path is not None:
        return [Path(path)]
    candidates: list[Path] = []
    env = environment.weights_file(ENV_VGG16_WEIGHTS)
    if env:
        candidates.append(Path(env))
    hub = Path(torch.hub.get_dir()) / "checkpoints" / VGG16_HUB_FILENAME
    candidates += [hub, hub.with_suffix(".safetensors")]
    return candidates


def _freeze(model: nn.Module) -> None:
    model.eval()
    for p in model.parameters():
        p.requires_grad_(False)


def random_vgg16(seed: int = 0) -> VGG16Features:
    """A VGG-16 trunk with the documented seeded random initialisation (frozen, eval mode).

    Conv weights ~ N(0, 2 / fan_out) with fan_out = C_out * 3 * 3 (Kaiming-normal, mode fan_out,
    ReLU gain), drawn layer by layer from ``torch.Generator().manual_seed(seed)`` on CPU; biases 0.
    """
    model = VGG16Features()
    gen = torch.Generator(device="cpu").manual_seed(int(seed))
    with torch.no_grad():
        for m in model.features:
            if isinstance(m, nn.Conv2d):
                fan_out = m.out_channels * m.kernel_size[0] * m.kernel_size[1]
                std = math.sqrt(2.0 / fan_out)
                m.weight.copy_(torch.randn(m.weight.shape, generator=gen, dtype=torch.float32) * std)
                assert m.bias is not None
                m.bias.zero_()
    _freeze(model)
    return model


def load_vgg16_weights(
    source: BackboneName = "vgg16-imagenet",
    *,
    path: str | os.PathLike | None = None,
    seed: int = 0,
) -> tuple[VGG16Features, BackboneRecord]:
    """Build a frozen VGG-16 trunk (eval mode, ``requires_grad`` False) from the named source.

    Args:
        source: ``"vgg16-imagenet"`` (a weight file) or ``"vgg16-random"`` (seeded init).
        path: explicit ImageNet weight file (``.pth`` or ``.safetensors``); when given, it is the
            only place looked at. Otherwise ``$DELIFFAS_VGG16_WEIGHTS`` and the torch hub cache.
        seed: generator seed of ``"vgg16-random"``.

    Returns:
        (model on CPU, record of the backbone used).

    Raises:
        PerceptualWeightsUnavailable: ImageNet weights asked for, no file found.
        ValueError: unknown source, or a weight file that is unreadable or has wrong keys/shapes.
    """
    if source == "vgg16-random":
        model = random_vgg16(seed)
        record = BackboneRecord(
            name="vgg16-random", seed=int(seed), init="kaiming_normal fan_out relu, zero bias, torch.Generator(cpu)"
        )
        logger.info("perceptual backbone: VGG-16 with seeded random weights (seed %d)", seed)
        return model, record
    if source != "vgg16-imagenet":
        raise ValueError(f"load_vgg16_weights: source must be 'vgg16-imagenet' or 'vgg16-random', got {source!r}")
    candidates = vgg16_weight_candidates(path)
    found = next((c for c in candidates if c.is_file()), None)
    if found is None:
        looked = "\n  ".join(str(c) for c in candidates)
        raise PerceptualWeightsUnavailable(
            "VGG-16 ImageNet weights not found. Looked at:\n  "
            f"{looked}\n"
            f"Put torchvision's {VGG16_HUB_FILENAME} (or a .safetensors copy) at one of these paths, "
            f"pass its path, or set ${ENV_VGG16_WEIGHTS}. Without internet, `--perceptual vgg16-random` "
            "is the explicit offline option (seeded random VGG-16 features; recorded as such)."
        )
    model = VGG16Features()
    _load_features(model, read_state_dict(found), str(found))
    _freeze(model)
    logger.info("perceptual backbone: VGG-16 ImageNet weights from %s", found)
    return model, BackboneRecord(name="vgg16-imagenet", path=str(found), init="file")
