"""Every environment variable deliffas reads, and the one module that reads them.

:data:`VARIABLES` holds one :class:`Variable` row per variable (name, effect, default, the module that uses it);
docs/architecture.md shows it as a table (:func:`variables_markdown`). The functions below read the variables,
each from ``environ`` (a mapping; None = ``os.environ`` at call time, so tests pass a plain dict). They return
what the variable says and leave the fallbacks that need other libraries (the compilers on PATH, the torch hub
cache) to their callers. Two modules also *write* defaults for third-party libraries (``os.environ.setdefault``
in ``deliffas.cli.handlers`` and ``deliffas.data.ingest.detect``); those are not read here.

A shared leaf: importable from any layer, importing only the standard library.
"""

from __future__ import annotations

import os
import shlex
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping

__all__ = ["ENV_INCEPTION_WEIGHTS", "ENV_LPIPS_WEIGHTS", "ENV_VGG16_WEIGHTS", "NATIVE_ENV", "VARIABLES",
           "WEIGHTS_VARIABLES", "Variable", "c_compiler", "cache_root", "distributed", "local_rank", "native_disabled",
           "omp_threads", "onednn_isa_cap", "variables_markdown", "weights_file", "world_size"]

NATIVE_ENV = "DELIFFAS_NATIVE"
"""Environment variable: "0" disables every compiled kernel."""
ENV_VGG16_WEIGHTS = "DELIFFAS_VGG16_WEIGHTS"
"""Environment variable naming a VGG-16 ImageNet weight file (.pth or .safetensors)."""
ENV_LPIPS_WEIGHTS = "DELIFFAS_LPIPS_WEIGHTS"
"""Environment variable naming the LPIPS v0.1 VGG linear-layer file."""
ENV_INCEPTION_WEIGHTS = "DELIFFAS_INCEPTION_WEIGHTS"
"""Environment variable naming pytorch-fid's Inception-v3 weight file."""
WEIGHTS_VARIABLES = (ENV_VGG16_WEIGHTS, ENV_LPIPS_WEIGHTS, ENV_INCEPTION_WEIGHTS)
"""The variables :func:`weights_file` reads."""


@dataclass(frozen=True)
class Variable:
    """One environment variable: its name, what it does, its default (as the docs say it) and who reads it."""

    name: str
    effect: str
    default: str
    reader: str
    """The module that uses the value (through a function of this module)."""


VARIABLES: tuple[Variable, ...] = (
    Variable(NATIVE_ENV, "`0` never compiles the C kernels: every caller uses its pure-torch fallback",
             "`1` (compile at first use)", "deliffas.native"),
    Variable("CC", "the C compiler command for the kernels (split as a shell would)",
             "the first of `cc`, `gcc`, `clang` on PATH", "deliffas.native"),
    Variable("DELIFFAS_CACHE", "the folder where loading an `.avatar` unpacks its template files",
             "`$XDG_CACHE_HOME/deliffas`", "deliffas.engine.avatar"),
    Variable("XDG_CACHE_HOME", "the cache folder under which `deliffas/` is used when `DELIFFAS_CACHE` is unset",
             "`~/.cache`", "deliffas.engine.avatar"),
    Variable(ENV_VGG16_WEIGHTS, "the ImageNet VGG-16 weight file (`.pth` or `.safetensors`), looked at first",
             "the torch hub cache", "deliffas.models.vgg"),
    Variable(ENV_LPIPS_WEIGHTS, "the LPIPS v0.1 VGG linear-layer file, looked at first",
             "the installed `lpips` package's `weights/v0.1/vgg.pth`", "deliffas.models.lpips"),
    Variable(ENV_INCEPTION_WEIGHTS, "pytorch-fid's Inception-v3 weight file for FID, looked at first",
             "the torch hub cache", "deliffas.models.fid"),
    Variable("ONEDNN_MAX_CPU_ISA", "oneDNN's instruction-set cap (oneDNN's own variable); below AVX-512 the "
             "U-Net's lane-filling convolutions assume 8 float32 lanes", "`ALL`", "deliffas.models.unet_prepack"),
    Variable("DNNL_MAX_CPU_ISA", "the older name of `ONEDNN_MAX_CPU_ISA`, used when that is unset", "`ALL`",
             "deliffas.models.unet_prepack"),
    Variable("OMP_NUM_THREADS", "OpenMP's own variable; caps `deliffas train`'s intra-op threads on a CPU (start runs "
             "side by side with `1` each)", "the cores its data workers leave", "deliffas.engine.devices"),
    Variable("WORLD_SIZE", "the number of training processes (set by `torchrun`); above 1 starts the process group",
             "`1`", "deliffas.engine.train"),
    Variable("LOCAL_RANK", "the process's GPU on its machine (set by `torchrun`), with more than one process",
             "`0`", "deliffas.engine.train"),
)
"""Every environment variable the package reads, one row each."""


def _environ(environ: Mapping[str, str] | None) -> Mapping[str, str]:
    return os.environ if environ is None else environ


def native_disabled(environ: Mapping[str, str] | None = None) -> bool:
    """True when ``$DELIFFAS_NATIVE`` is ``0`` (surrounding spaces ignored): compile no C kernel.

    Args:
        environ: the variables (None = ``os.environ``).
    """
    return _environ(environ).get(NATIVE_ENV, "1").strip() == "0"


def c_compiler(environ: Mapping[str, str] | None = None) -> list[str] | None:
    """``$CC`` split as a shell would (a command and its flags); None when it is unset or blank.

    Args:
        environ: the variables (None = ``os.environ``).
    """
    return shlex.split(_environ(environ).get("CC", "")) or None


def cache_root(environ: Mapping[str, str] | None = None) -> Path:
    """Where unpacked template files live: ``$DELIFFAS_CACHE``, ``$XDG_CACHE_HOME/deliffas`` or ``~/.cache/deliffas``
    (an empty variable counts as unset).

    Args:
        environ: the variables (None = ``os.environ``).
    """
    env = _environ(environ)
    if env.get("DELIFFAS_CACHE"):
        return Path(env["DELIFFAS_CACHE"])
    return Path(env.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "deliffas"


def weights_file(name: str, environ: Mapping[str, str] | None = None) -> str | None:
    """The weight file a variable of :data:`WEIGHTS_VARIABLES` names; None when it is unset or empty.

    Args:
        name: ``DELIFFAS_VGG16_WEIGHTS``, ``DELIFFAS_LPIPS_WEIGHTS`` or ``DELIFFAS_INCEPTION_WEIGHTS``.
        environ: the variables (None = ``os.environ``).

    Raises:
        ValueError: ``name`` is not one of them.
    """
    if name not in WEIGHTS_VARIABLES:
        raise ValueError(f"{name!r} is not a weights variable (expected one of {', '.join(WEIGHTS_VARIABLES)})")
    return _environ(environ).get(name) or None


def onednn_isa_cap(environ: Mapping[str, str] | None = None) -> str:
    """oneDNN's instruction-set cap, upper case: ``$ONEDNN_MAX_CPU_ISA``, else ``$DNNL_MAX_CPU_ISA``, else ``ALL``.

    Args:
        environ: the variables (None = ``os.environ``).
    """
    env = _environ(environ)
    return (env.get("ONEDNN_MAX_CPU_ISA") or env.get("DNNL_MAX_CPU_ISA") or "ALL").upper()


def omp_threads(environ: Mapping[str, str] | None = None) -> int | None:
    """``$OMP_NUM_THREADS`` as a thread count, None when unset or not a positive integer (OpenMP then ignores it).

    Args:
        environ: the variables (None = ``os.environ``).
    """
    value = _environ(environ).get("OMP_NUM_THREADS", "").strip()
    return int(value) if value.isdigit() and int(value) > 0 else None


def world_size(environ: Mapping[str, str] | None = None) -> int:
    """``$WORLD_SIZE`` (set by torchrun), 1 when unset.

    Args:
        environ: the variables (None = ``os.environ``).

    Raises:
        ValueError: the value is not an integer.
    """
    return int(_environ(environ).get("WORLD_SIZE", "1"))


def local_rank(environ: Mapping[str, str] | None = None) -> int:
    """``$LOCAL_RANK`` (set by torchrun), 0 when unset.

    Args:
        environ: the variables (None = ``os.environ``).

    Raises:
        ValueError: the value is not an integer.
    """
    return int(_environ(environ).get("LOCAL_RANK", "0"))


def distributed(environ: Mapping[str, str] | None = None) -> tuple[int, int]:
    """(world size, local rank): :func:`world_size` and :func:`local_rank`.

    Args:
        environ: the variables (None = ``os.environ``).
    """
    return world_size(environ), local_rank(environ)


def variables_markdown() -> str:
    """:data:`VARIABLES` as a Markdown table (variable, effect, default), as docs/architecture.md shows it."""
    rows = ["| variable | effect | default |", "|---|---|---|"]
    rows += [f"| `{v.name}` | {v.effect} | {v.default} |" for v in VARIABLES]
    return "\n".join(rows) + "\n"
