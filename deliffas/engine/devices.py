"""The one place a device name becomes a ``torch.device``, refusing devices this machine does not have.

Every engine command (train, eval, render, view, export) resolves ``--device`` here, so ``--device
cuda`` on a machine without CUDA is the same clear error everywhere instead of a silent fall-back to
the CPU in one command and a crash in the next.
"""

from __future__ import annotations

import os
import re

import torch

from deliffas import environment

__all__ = ["DeviceError", "resolve_device", "DEVICE_PATTERN", "cpu_threads"]

DEVICE_PATTERN = re.compile(r"^(cpu|cuda|cuda:\d+)$")
"""Device names deliffas accepts: ``cpu``, ``cuda`` (the current GPU) or ``cuda:N``."""


class DeviceError(ValueError):
    """A device name that is malformed or names a device this machine does not have."""


def resolve_device(name: str | torch.device) -> torch.device:
    """``name`` as a ``torch.device``, checked against what this machine has.

    Raises:
        DeviceError: not ``cpu``, ``cuda`` or ``cuda:N``; CUDA asked for but not available (the message
            says what torch sees); ``cuda:N`` past the last GPU.
    """
    text = str(name)
    if not DEVICE_PATTERN.match(text):
        raise DeviceError(f"device: expected cpu, cuda or cuda:N, got {text!r}")
    device = torch.device(text)
    if device.type == "cuda":
        if not torch.cuda.is_available():
            build = f"torch {torch.__version__}" + ("" if torch.version.cuda else ", a build without CUDA")
            raise DeviceError(f"device {text!r}: CUDA is not available on this machine ({build}); use --device cpu")
        count = torch.cuda.device_count()
        if device.index is not None and device.index >= count:
            raise DeviceError(f"device {text!r}: this machine has {count} CUDA device(s) (cuda:0..cuda:{count - 1})")
    return device


def cpu_threads(ranks: int = 1, workers: int = 0) -> int:
    """Intra-op threads for one of ``ranks`` CPU training processes that each feed ``workers`` DataLoader
    workers: the cores left to it (at least 1), and no more than ``OMP_NUM_THREADS`` where that is set, so that
    runs started side by side with ``OMP_NUM_THREADS=1`` keep one thread each (oversubscribed OpenMP threads
    spin and can make a step many times slower)."""
    share = max(1, (os.cpu_count() or 1) // ranks - workers)
    asked = environment.omp_threads()
    return share if asked is None else min(share, asked)
