"""The environment variables of the CPU fast path, mapped onto a FastConfig at the CLI's edge.

``DELIFFAS_FAST_RENDER=0``: the plain path (no FastConfig). ``DELIFFAS_RENDER_DTYPE=float32|bfloat16``:
``FastConfig.dtype``. ``DELIFFAS_FUSED_SHADE``, ``DELIFFAS_PE_TABLE``, ``DELIFFAS_PROJECT_FEATURES`` (``0`` off,
``1`` on): the flags of the same names. ``DELIFFAS_FRAMES_IN_FLIGHT=N`` (N >= 1): ``FastConfig.in_flight``.
A variable that is unset leaves the command's default. The raw values come from
``deliffas.environment.fast_path_values``; this module checks them.
"""

from __future__ import annotations

import dataclasses
from typing import Mapping

from deliffas.environment import fast_path_values
from deliffas.fast.config import FastConfig

__all__ = ["FAST_ENV", "fast_from_env"]

FAST_ENV = {"fused": "DELIFFAS_FUSED_SHADE", "pe_table": "DELIFFAS_PE_TABLE",
            "project_features": "DELIFFAS_PROJECT_FEATURES"}
"""FastConfig flag -> the environment variable that sets it ("0" off, "1" on)."""


def fast_from_env(base: FastConfig | None, environ: Mapping[str, str] | None = None) -> FastConfig | None:
    """``base`` with the fast path's environment variables applied (module docstring); None = the plain path.

    Args:
        base: the command's FastConfig (None: the plain path).
        environ: the variables (None = ``os.environ``).
    """
    values = fast_path_values(environ)
    if base is None or values.get("DELIFFAS_FAST_RENDER", "").strip() == "0":
        return None
    changes: dict[str, object] = {}
    for field, name in FAST_ENV.items():
        value = values.get(name, "").strip()
        if value:
            if value not in ("0", "1"):
                raise ValueError(f"${name}: expected 0 or 1, got {value!r} (unset it for the default)")
            changes[field] = value == "1"
    dtype = values.get("DELIFFAS_RENDER_DTYPE", "").strip()
    if dtype:
        if dtype not in ("float32", "bfloat16"):
            raise ValueError(f"$DELIFFAS_RENDER_DTYPE: expected float32 or bfloat16, got {dtype!r}")
        changes["dtype"] = dtype
    in_flight = values.get("DELIFFAS_FRAMES_IN_FLIGHT", "").strip()
    if in_flight:
        if not in_flight.isdigit() or int(in_flight) < 1:
            raise ValueError(f"$DELIFFAS_FRAMES_IN_FLIGHT: expected an integer >= 1, got {in_flight!r}")
        changes["in_flight"] = int(in_flight)
    return dataclasses.replace(base, **changes)
