"""Stream converted shards into your own network (not DeliffasModel): a custom training loop.

    python examples/03_custom_training.py SHARDS [--steps 20]

SHARDS is a folder written by ``deliffas convert``. Each ``ShardDataset`` item is one frame with K
camera images (uint8), their masks, cameras, the frame's temporal normal maps (float16) and posed
surfaces. Here a tiny convolutional net maps the inner temporal normal maps to an RGB texture
sampled at the template's per-vertex uvs ... but anything works: the dataset only hands you arrays.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch
from torch import nn
from torch.utils.data import DataLoader

from deliffas.data.dataset import RandomCameraSampler, ShardDataset


class TinyNet(nn.Module):
    """Temporal normal maps (B, 3 (T + 1), S, S) -> a (B, 3, S, S) texture: a stand-in for your model."""

    def __init__(self, in_channels: int):
        super().__init__()
        self.net = nn.Sequential(nn.Conv2d(in_channels, 16, 3, padding=1), nn.ReLU(), nn.Conv2d(16, 3, 3, padding=1),
                                 nn.Sigmoid())

    def forward(self, normal_maps: torch.Tensor) -> torch.Tensor:
        return self.net(normal_maps)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("shards", type=Path)
    parser.add_argument("--steps", type=int, default=20)
    args = parser.parse_args(argv)

    dataset = ShardDataset(args.shards, split="train", cameras_per_item=2, temporal_window=2, protocol="all")
    loader = DataLoader(dataset, batch_size=None, sampler=RandomCameraSampler(dataset, 2, torch.Generator().manual_seed(0)))
    net = TinyNet(in_channels=9)
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    step = 0
    while step < args.steps:
        for item in loader:
            texture = net(item.normal_maps_inner.float()[None])  # (1, 3, S, S)
            # a toy objective: the texture's mean colour should match the foreground's mean colour
            mask = item.masks.float()[..., None] / 255.0  # (K, H, W, 1)
            target = (item.images.float() / 255.0 * mask).sum((0, 1, 2)) / mask.sum().clamp(min=1)
            loss = (texture.mean((0, 2, 3)) - target).abs().sum()
            opt.zero_grad()
            loss.backward()
            opt.step()
            step += 1
            if step % 5 == 0 or step == args.steps:
                print(f"step {step}: frame {int(item.frame)}, cameras {item.camera_ids.tolist()}, loss {loss.item():.4f}")
            if step == args.steps:
                break


if __name__ == "__main__":
    main()
