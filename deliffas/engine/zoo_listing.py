"""The model zoo's listing behind ``deliffas zoo``: every model and preset, and the ``.avatar`` files of a folder."""

from __future__ import annotations

from deliffas.engine.avatar import list_avatars
from deliffas.engine.zoo_config import ZooConfig
from deliffas.models.deliffas import DeliffasModel
from deliffas.models.zoo import get_config, list_models, list_presets

__all__ = ["ZooConfig", "zoo_listing"]


def zoo_listing(config: ZooConfig) -> dict:
    """``{"models": [...], "avatars": [...] | None}``: one row per model and preset (model, preset, atlas_res, mlp
    ``DEPTHxWIDTH``, features, parameters: None for ``paper`` unless ``config.count_paper``), and
    :func:`deliffas.engine.avatar.list_avatars` of ``config.folder`` (None without a folder)."""
    rows = []
    for name in list_models():
        for preset in list_presets(name):
            cfg = get_config(name, preset)
            params = DeliffasModel(cfg).num_parameters() if preset != "paper" or config.count_paper else None
            rows.append({"model": name, "preset": preset, "atlas_res": cfg.atlas_res,
                         "mlp": f"{cfg.mlp.depth}x{cfg.mlp.width}", "features": cfg.feature_channels,
                         "parameters": params})
    return {"models": rows, "avatars": list_avatars(config.folder) if config.folder is not None else None}
