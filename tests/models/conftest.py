"""Shared fixtures of the model tests: device, an isolated weight search path, fake VGG files."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch

# Convolution kernels of torchvision's vgg16 ``features`` written out independently of
# deliffas.models.vgg: index -> (out, in). The loader must accept exactly this layout.
TORCHVISION_VGG16_CONVS = {
    0: (64, 3), 2: (64, 64), 5: (128, 64), 7: (128, 128),
    10: (256, 128), 12: (256, 256), 14: (256, 256),
    17: (512, 256), 19: (512, 512), 21: (512, 512),
    24: (512, 512), 26: (512, 512), 28: (512, 512),
}  # fmt: skip


@pytest.fixture(scope="session")
def torchvision_vgg16_convs() -> dict[int, tuple[int, int]]:
    """torchvision vgg16 ``features`` conv index -> (out, in) channels, written independently."""
    return dict(TORCHVISION_VGG16_CONVS)


@pytest.fixture
def device() -> torch.device:
    """Test device: ``$DELIFFAS_TEST_DEVICE`` (default cpu)."""
    return torch.device(os.environ.get("DELIFFAS_TEST_DEVICE", "cpu"))


@pytest.fixture
def no_weights(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> Path:
    """An environment where no pretrained weights can be found: empty TORCH_HOME, no env paths."""
    home = tmp_path / "torch_home"
    home.mkdir()
    monkeypatch.setenv("TORCH_HOME", str(home))
    monkeypatch.delenv("DELIFFAS_VGG16_WEIGHTS", raising=False)
    monkeypatch.delenv("DELIFFAS_LPIPS_WEIGHTS", raising=False)
    monkeypatch.delenv("DELIFFAS_INCEPTION_WEIGHTS", raising=False)
    return home


def make_torchvision_vgg16_state(seed: int = 123) -> dict[str, torch.Tensor]:
    """Random tensors with torchvision's vgg16 key layout (classifier keys small: they are ignored)."""
    gen = torch.Generator().manual_seed(seed)
    state: dict[str, torch.Tensor] = {}
    for idx, (c_out, c_in) in TORCHVISION_VGG16_CONVS.items():
        state[f"features.{idx}.weight"] = torch.randn(c_out, c_in, 3, 3, generator=gen) * 0.02
        state[f"features.{idx}.bias"] = torch.randn(c_out, generator=gen) * 0.01
    state["classifier.0.weight"] = torch.randn(4, 8, generator=gen)
    state["classifier.0.bias"] = torch.randn(4, generator=gen)
    return state


@pytest.fixture(scope="session")
def vgg_files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, object]:
    """A fake ImageNet VGG-16 file in both formats: {"state", "pth", "safetensors"}."""
    from safetensors.torch import save_file

    root = tmp_path_factory.mktemp("vgg")
    state = make_torchvision_vgg16_state()
    pth = root / "vgg16-397923af.pth"
    torch.save(state, pth)
    st = root / "vgg16.safetensors"
    save_file(state, str(st))
    return {"state": state, "pth": pth, "safetensors": st}


@pytest.fixture(scope="session")
def random_backbone():
    """The seeded random VGG-16 (seed 0) and its record, built once."""
    from deliffas.models.vgg import load_vgg16_weights

    return load_vgg16_weights("vgg16-random", seed=0)
