"""The documentation site as a reader gets it (``make docs`` builds it into build/site).

The site is built once here, into a temporary folder, and its HTML is read back: every local
link and image points to a file of the site, and no raw Sphinx role (``:func:`x```) shows in
the text. The build is not strict here, so that these checks report what they find rather than
mkdocs' first warning; ``make docs`` is the strict build.
"""

from __future__ import annotations

import os
import posixpath
import re
import subprocess
import sys
from collections.abc import Iterator
from html.parser import HTMLParser
from pathlib import Path
from urllib.parse import unquote, urlsplit

import pytest

ROOT = Path(__file__).parents[1]
BIN = Path(sys.prefix) / "bin"  # not tests/procs.py's: this module starts no federation
PACKAGE_FOLDERS = ("agent", "common", "envs", "server")
ROLE = re.compile(r":(?:py:)?(?:func|class|mod|meth|attr|data|exc|obj|const):")
"""A Sphinx role's marker, as it shows when nothing rendered it."""


def _link_package(docs: Path) -> None:
    """The links make docs makes: the reference reads fedhpg.* from build/docs/fedhpg."""
    package = docs / "fedhpg"
    package.mkdir(parents=True, exist_ok=True)
    for name in (*PACKAGE_FOLDERS, "__init__.py"):
        link = package / name
        if not link.is_symlink():
            source = ROOT / "fedhpg" / name if name == "__init__.py" else ROOT / name
            link.symlink_to(os.path.relpath(source, package))


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Path:
    _link_package(ROOT / "build" / "docs")
    out = tmp_path_factory.mktemp("site")
    built = subprocess.run(
        [str(BIN / "mkdocs"), "build", "--no-strict", "--site-dir", str(out)],
        cwd=ROOT,
        env={**os.environ, "NO_MKDOCS_2_WARNING": "1"},
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert built.returncode == 0, built.stderr[-3000:]
    return out


class _Page(HTMLParser):
    """A page's link and image targets, and its text outside code."""

    def __init__(self) -> None:
        super().__init__(convert_charrefs=True)
        self.targets: list[str] = []
        self.text: list[str] = []
        self._code = 0

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        named = dict(attrs)
        if tag == "a" and named.get("href"):
            self.targets.append(named["href"] or "")
        if tag == "img" and named.get("src"):
            self.targets.append(named["src"] or "")
        if tag in {"code", "pre", "script", "style"}:
            self._code += 1

    def handle_endtag(self, tag: str) -> None:
        if tag in {"code", "pre", "script", "style"} and self._code:
            self._code -= 1

    def handle_data(self, data: str) -> None:
        if not self._code:
            self.text.append(data)


def _pages(site: Path) -> Iterator[tuple[Path, _Page]]:
    for html in sorted(site.rglob("*.html")):
        page = _Page()
        page.feed(html.read_text(encoding="utf-8"))
        yield html, page


def _local_file(site: Path, html: Path, target: str) -> Path | None:
    """The file of the site a link resolves to (None for another site, mail, data or an
    anchor of the same page)."""
    parts = urlsplit(target)
    if parts.scheme or parts.netloc or not parts.path:
        return None
    path = unquote(parts.path)
    if path.startswith("/"):
        resolved = posixpath.normpath(path.lstrip("/"))
    else:
        here = html.parent.relative_to(site).as_posix()
        resolved = posixpath.normpath(posixpath.join(here, path))
    file = site / resolved
    return file / "index.html" if path.endswith("/") or file.is_dir() else file


def test_every_local_link_and_image_of_the_site_exists(site: Path) -> None:
    broken = []
    for html, page in _pages(site):
        for target in page.targets:
            file = _local_file(site, html, target)
            if file is not None and not file.is_file():
                broken.append(f"{html.relative_to(site)}: {target}")
    assert not broken, "links or images to nothing:\n" + "\n".join(sorted(set(broken)))


def test_no_raw_sphinx_role_shows_on_the_site(site: Path) -> None:
    raw = []
    for html, page in _pages(site):
        text = "".join(page.text)
        for match in ROLE.finditer(text):
            shown = " ".join(text[match.start() : match.end() + 40].split())
            raw.append(f"{html.relative_to(site)}: {shown}…")
    assert not raw, f"{len(raw)} raw roles:\n" + "\n".join(raw)


def _docs_build_command(makefile: str) -> str:
    recipe = makefile.split("\ndocs:", 1)[1].split("\n\n", 1)[0]
    return next(line for line in recipe.splitlines() if "mkdocs build" in line)


def test_make_docs_is_strict_and_not_quiet() -> None:
    """mkdocs 1.6's --quiet drops warnings before --strict counts them: with both, a broken
    link or image builds without a word."""
    command = _docs_build_command((ROOT / "Makefile").read_text(encoding="utf-8")).split()
    assert "--strict" in command and not {"--quiet", "-q"} & set(command), command
