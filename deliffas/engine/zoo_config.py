"""What ``deliffas zoo`` lists (:class:`ZooConfig`); light, so the CLI reads it without torch."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from deliffas.options import opt

__all__ = ["ZooConfig"]


@dataclass(frozen=True)
class ZooConfig:
    """The model zoo's listing (:func:`deliffas.engine.zoo_listing.zoo_listing`)."""

    action: Literal["list"] = opt(help="what to do", flag="")
    folder: Path | None = opt(None, help="also list the .avatar files found under this folder (name, model, preset, "
                                         "size)", flag="", nargs="?", default_text="none")
    json: bool = opt(False, help="print JSON")
    count_paper: bool = opt(False, help="also build the paper-size models to count parameters (otherwise their counts "
                                        "are null)")
