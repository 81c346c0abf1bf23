"""The documentation site as a reader gets it (``make docs`` builds it into build/site).

The site is built once here, into a temporary folder (or FEDHPG_SITE names one already built),
and its HTML is read back: every local link and image (figures included) points to a file of
the site and, with an anchor, to an id of that page; links to other sites are counted, never
fetched; no raw Sphinx role (``:func:`x```) or unrendered cross-reference shows in the text.
The build is not strict here, so that these checks report everything they find rather than
mkdocs' first warning; ``make docs`` is the strict build.
"""

from __future__ import annotations

import os
import posixpath
import re
import subprocess
import sys
from html.parser import HTMLParser
from pathlib import Path
from typing import ClassVar
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
    """The built site: FEDHPG_SITE names one already built (``make docs``'s build/site),
    else the docs are built here."""
    if os.environ.get("FEDHPG_SITE"):
        built_site = Path(os.environ["FEDHPG_SITE"]).resolve()
        assert (built_site / "index.html").is_file(), f"no site in {built_site}"
        return built_site
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
    """A page's link and image targets, the ids a link can point to, and its text."""

    TARGETS: ClassVar[dict[str, tuple[str, ...]]] = {
        "a": ("href",),
        "link": ("href",),
        "img": ("src",),
        "source": ("src",),
        "script": ("src",),
    }

    def __init__(self) -> None:
        super().__init__(convert_charrefs=True)
        self.targets: list[str] = []
        self.ids: set[str] = set()
        self.text: list[str] = []
        """The page's text, code included (a role's name is code once rendered)."""
        self.code_at: list[tuple[int, int]] = []
        """Where ``text``'s code lies, as (start, end) offsets in its join."""
        self._length = 0
        self.unrendered: list[str] = []
        """Elements the build should have replaced (mkdocs-autorefs' ``<autoref>``)."""
        self._code = 0

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        named = {key: value for key, value in attrs if value is not None}
        for attribute in self.TARGETS.get(tag, ()):
            if named.get(attribute):
                self.targets.append(named[attribute])
        if tag in {"img", "source"} and named.get("srcset"):
            self.targets += [item.split()[0] for item in named["srcset"].split(",") if item]
        if "id" in named:
            self.ids.add(named["id"])
        if tag == "a" and "name" in named:
            self.ids.add(named["name"])
        if tag in {"autoref", "autoref-optional"}:
            self.unrendered.append(self.get_starttag_text() or tag)
        if tag in {"code", "pre", "script", "style"}:
            self._code += 1

    def handle_endtag(self, tag: str) -> None:
        if tag in {"code", "pre", "script", "style"} and self._code:
            self._code -= 1

    def handle_data(self, data: str) -> None:
        if self._code:
            self.code_at.append((self._length, self._length + len(data)))
        self.text.append(data)
        self._length += len(data)

    def in_code(self, offset: int) -> bool:
        return any(start <= offset < end for start, end in self.code_at)


def _parse(site: Path) -> dict[Path, _Page]:
    parsed = {}
    for html in sorted(site.rglob("*.html")):
        page = _Page()
        page.feed(html.read_text(encoding="utf-8"))
        parsed[html] = page
    return parsed


@pytest.fixture(scope="module")
def pages(site: Path) -> dict[Path, _Page]:
    """Every HTML page of the site, parsed once."""
    parsed = _parse(site)
    assert parsed, f"no pages in {site}"
    return parsed


def _external(target: str) -> bool:
    return urlsplit(target).scheme in {"http", "https"}


def _local_file(site: Path, html: Path, target: str) -> Path | None:
    """The file of the site a link resolves to: ``html`` itself for an anchor of the same
    page, None for another site, mail or data."""
    parts = urlsplit(target)
    if parts.scheme or parts.netloc:
        return None
    if not parts.path:
        return html
    path = unquote(parts.path)
    if path.startswith("/"):
        resolved = posixpath.normpath(path.lstrip("/"))
    else:
        here = html.parent.relative_to(site).as_posix()
        resolved = posixpath.normpath(posixpath.join(here, path))
    file = site / resolved
    return file / "index.html" if path.endswith("/") or file.is_dir() else file


def _broken(site: Path, pages: dict[Path, _Page]) -> tuple[list[str], int]:
    """Each local link or image to no file, or to an anchor its page does not have, as
    "page: target (why)"; and how many links go to other sites (counted, never fetched)."""
    broken, external = set(), 0
    for html, page in pages.items():
        for target in page.targets:
            if _external(target):
                external += 1
                continue
            file = _local_file(site, html, target)
            if file is None:
                continue
            where = f"{html.relative_to(site)}: {target}"
            fragment = unquote(urlsplit(target).fragment)
            if not file.is_file():
                broken.add(f"{where} (no such file)")
            elif fragment and file in pages and fragment not in pages[file].ids:
                broken.add(f"{where} (no such anchor)")
    return sorted(broken), external


def _raw_roles(site: Path, pages: dict[Path, _Page]) -> list[str]:
    """Each Sphinx role shown as text, and each cross-reference left unrendered, as
    "page: snippet"."""
    raw = []
    for html, page in pages.items():
        text = "".join(page.text)
        for match in ROLE.finditer(text):
            if page.in_code(match.start()):
                continue  # a role quoted as code, as in this module's docstring
            shown = " ".join(text[match.start() : match.end() + 40].split())
            raw.append(f"{html.relative_to(site)}: {shown}…")
        raw += [f"{html.relative_to(site)}: {tag} (not rendered)" for tag in page.unrendered]
    return raw


def test_every_local_link_and_image_of_the_site_exists(
    site: Path, pages: dict[Path, _Page]
) -> None:
    broken, external = _broken(site, pages)
    assert not broken, (
        f"{len(broken)} links or images to nothing ({external} links to other sites, "
        "not fetched):\n" + "\n".join(broken)
    )


def test_links_to_other_sites_name_a_host(site: Path, pages: dict[Path, _Page]) -> None:
    """Links to other sites are not fetched (the tests run offline): each names a host."""
    hostless = [
        f"{html.relative_to(site)}: {target}"
        for html, page in pages.items() for target in page.targets
        if _external(target) and not urlsplit(target).netloc
    ]  # fmt: skip
    assert not hostless, "links to another site without a host:\n" + "\n".join(hostless)


def test_no_raw_sphinx_role_shows_on_the_site(site: Path, pages: dict[Path, _Page]) -> None:
    raw = _raw_roles(site, pages)
    assert not raw, f"{len(raw)} raw roles:\n" + "\n".join(raw)


def test_the_checks_find_what_they_look_for(tmp_path: Path) -> None:
    """On a site of two pages: a missing page, image and anchor, a raw role, an unrendered
    cross-reference; a role quoted as code, a present anchor and another site pass."""
    (tmp_path / "guide").mkdir()
    (tmp_path / "figure.png").write_bytes(b"")
    (tmp_path / "guide" / "index.html").write_text(
        '<h2 id="usage">Usage</h2><p>Quoted: <code>:func:`run`</code></p>', encoding="utf-8"
    )
    (tmp_path / "index.html").write_text(
        '<a href="guide/#usage">ok</a> <a href="guide/#nowhere">anchor</a>'
        ' <a href="missing/">page</a> <a href="#top" id="top">self</a>'
        ' <img src="figure.png"> <figure><img src="figures/none.png"></figure>'
        ' <a href="https://example.org/x">away</a>'
        "<p>See :func:<code>run</code> and"
        ' <autoref identifier="a.b" optional><code>b</code></autoref>.</p>',
        encoding="utf-8",
    )
    pages = _parse(tmp_path)
    assert _broken(tmp_path, pages) == (
        [
            "index.html: figures/none.png (no such file)",
            "index.html: guide/#nowhere (no such anchor)",
            "index.html: missing/ (no such file)",
        ],
        1,
    )
    assert _raw_roles(tmp_path, pages) == [
        "index.html: :func:run and b.…",
        'index.html: <autoref identifier="a.b" optional> (not rendered)',
    ]


def _docs_build_command(makefile: str) -> str:
    recipe = makefile.split("\ndocs:", 1)[1].split("\n\n", 1)[0]
    return next(line for line in recipe.splitlines() if "mkdocs build" in line)


def test_make_docs_is_strict_and_not_quiet() -> None:
    """mkdocs 1.6's --quiet drops warnings before --strict counts them: with both, a broken
    link or image builds without a word."""
    command = _docs_build_command((ROOT / "Makefile").read_text(encoding="utf-8")).split()
    assert "--strict" in command and not {"--quiet", "-q"} & set(command), command
