"""A synthetic capture at the recipes' quick sizes, converted once per session and shared by the recipe tests."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pytest


@dataclass(frozen=True)
class TinyRecipeCapture:
    """``subject``: synthetic DynaCap subject folder; ``shards``: its default conversion (procedural
    template, 30 mm shell); ``sizes``: the ``RecipeSizes.quick()`` both were made with."""

    subject: Path
    shards: Path
    sizes: object


@pytest.fixture(scope="session")
def tiny_recipe_capture(tmp_path_factory) -> TinyRecipeCapture:
    from recipes.common import RecipeSizes, prepare_capture, prepare_shards

    root = tmp_path_factory.mktemp("recipe_capture")
    sizes = RecipeSizes.quick()
    subject = prepare_capture(root, sizes, seed=0, jobs=1)  # in-process: no worker start-up
    shards = prepare_shards(root, subject, sizes, jobs=1)
    return TinyRecipeCapture(subject=subject, shards=shards, sizes=sizes)
