"""MkDocs hook of the documentation site: README.md is its home page, with its links made site-relative.

The README is written for the repository (``docs/geometry.md``, ``site/api/io.html`` after
``make docs``, ``examples/``); the site's pages live in ``docs/``. One source for both: the home page
``index.md`` is generated from the README at build time (mkdocs.yml loads this hook), and its links are
rewritten so ``mkdocs build --strict`` checks them like any page's:

* ``docs/X`` -> ``X`` (a page or picture of the site);
* ``site/P.html`` -> ``P.md`` (a page of the built site itself: ``site/index.html``, ``site/api/io.html``);
* other repository paths (``examples/``, ``CHANGELOG.md``) are not in the site: the link becomes its text.
"""

from __future__ import annotations

import re
from pathlib import Path

from mkdocs.structure.files import File, Files

HOME = "index.md"
LINK = re.compile(r"(?P<bang>!?)\[(?P<text>[^\]]*)\]\((?P<target>[^)\s]+)\)")
"""An inline Markdown link or image: ``[text](target)``, ``![alt](target)``."""


def site_target(target: str) -> str | None:
    """Where a README link target points in the site; None when it is outside the site."""
    if re.match(r"^[a-z][a-z0-9+.-]*:|^#", target):  # http:, mailto:, an anchor of this page
        return target
    path, _, anchor = target.partition("#")
    suffix = f"#{anchor}" if anchor else ""
    if path.startswith("docs/"):
        return path.removeprefix("docs/") + suffix
    built = re.fullmatch(r"site/(?P<page>.+)\.html", path)
    if built:
        return f"{built['page']}.md{suffix}"
    return None


def readme_as_home(markdown: str) -> str:
    """The README's Markdown with its links rewritten for the site."""
    def rewrite(match: re.Match) -> str:
        target = site_target(match["target"])
        if target is None:
            return match["text"]
        return f"{match['bang']}[{match['text']}]({target})"
    return LINK.sub(rewrite, markdown)


def on_files(files: Files, config) -> Files:
    """Adds the home page, generated from README.md next to mkdocs.yml."""
    if files.get_file_from_path(HOME) is not None:
        raise ValueError(f"docs/{HOME} exists, but the home page is generated from README.md "
                         "(scripts/mkdocs_readme_home.py): remove one of them")
    readme = Path(config.config_file_path).parent / "README.md"
    files.append(File.generated(config, HOME, content=readme_as_home(readme.read_text(encoding="utf-8"))))
    return files
