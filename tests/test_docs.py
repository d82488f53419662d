"""The docs site: every public name has an API entry, every autodoc target imports, and every page meets the
README's bar on sentences (:func:`test_readme.mean_words_per_sentence`). No Sphinx run is needed: the directives
are read from the page sources. The build itself is ``python -m sphinx -W --keep-going -b html docs <out>``."""

from __future__ import annotations

import importlib
import re
from pathlib import Path

import pytest
from test_readme import MAX_MEAN_WORDS, mean_words_per_sentence

import sb3_mtte

DOCS = Path(__file__).resolve().parents[1] / "docs"
NOT_PAGES = ("records", "results", "figures", "_build")
"""Folders of docs/ that hold data, drawn tables or build output, not pages."""

_DIRECTIVE = re.compile(
    r"^[ \t]*(?:\.\. (?:auto|py:)(?P<rst>\w+)::|```\{(?:auto|py:)(?P<myst>\w+)\})"
    r"[ \t]+(?P<target>\S+)[ \t]*$",
    re.MULTILINE,
)
_OPTION = re.compile(r"[ \t]+:(?P<name>[\w-]+):")
_INCLUDE = re.compile(r"^```\{include\}[ \t]+(?P<path>\S+)[ \t]*$", re.MULTILINE)


def pages() -> list[Path]:
    """Every Markdown page of the docs site."""
    return sorted(p for p in DOCS.rglob("*.md") if not set(p.relative_to(DOCS).parts[:-1]) & set(NOT_PAGES))


def autodoc_entries(text: str) -> list[tuple[str, str, bool]]:
    """(directive, target, indexed) of every API entry of a page: an autodoc directive or a hand-written ``py:``
    one, reST (``.. autoclass:: x``, ``.. py:data:: x``) or MyST (```` ```{autoclass} x ````); ``indexed`` is False
    for an entry with ``:no-index:``."""
    entries = []
    for match in _DIRECTIVE.finditer(text):
        options = []
        for line in text[match.end() :].splitlines()[1:]:
            option = _OPTION.match(line)
            if option is None:
                break
            options.append(option["name"])
        directive = match["rst"] or match["myst"]
        entries.append((directive, match["target"], not {"no-index", "noindex"} & set(options)))
    return entries


def documented_public_names(texts: list[str]) -> set[str]:
    """The names ``x`` of ``sb3_mtte.x`` that an indexed autodoc entry documents."""
    targets = {target for text in texts for _, target, indexed in autodoc_entries(text) if indexed}
    return {target.removeprefix("sb3_mtte.") for target in targets if target.count(".") == 1}


def resolve(target: str) -> object:
    """The object a dotted autodoc target names: the longest importable module prefix, then attributes."""
    parts = target.split(".")
    for split in range(len(parts), 0, -1):
        try:
            value = importlib.import_module(".".join(parts[:split]))
        except ImportError:
            continue
        for name in parts[split:]:
            value = getattr(value, name)
        return value
    raise ImportError(f"no module of {target!r} imports")


def measured_files() -> list[Path]:
    """The pages, and the files outside docs/figures that pages include (the changelog)."""
    included = set()
    for page in pages():
        for match in _INCLUDE.finditer(page.read_text()):
            path = (page.parent / match["path"]).resolve()
            if "figures" not in path.relative_to(DOCS.parent).parts:
                included.add(path)
    return [*pages(), *sorted(included)]


def test_every_public_name_has_an_api_entry():
    missing = sorted(set(sb3_mtte.__all__) - documented_public_names([p.read_text() for p in pages()]))
    assert not missing, f"no autodoc entry `sb3_mtte.<name>` in docs/api/ for {missing}: add one"


def test_every_autodoc_target_imports():
    """A renamed or moved class breaks the build; this finds it without Sphinx."""
    broken = []
    for page in pages():
        for _, target, _ in autodoc_entries(page.read_text()):
            try:
                resolve(target)
            except (ImportError, AttributeError) as error:
                broken.append(f"{page.relative_to(DOCS)}: {target} ({error})")
    assert not broken, "autodoc targets that do not import:\n" + "\n".join(broken)


def test_the_api_check_finds_a_missing_name():
    """Parsing: reST and MyST directives count, an entry with ``:no-index:`` does not, nor a submodule's path."""
    text = "\n".join(
        [
            "```{eval-rst}",
            ".. autoclass:: sb3_mtte.MTSAC",
            "   :members:",
            "",
            ".. autoclass:: sb3_mtte.MTSACTE",
            "   :no-index:",
            "",
            ".. autofunction:: sb3_mtte.envs.make_env_fns",
            "```",
            "```{autofunction} sb3_mtte.make_mt_env",
            "```",
            ".. py:data:: sb3_mtte.__version__",
            "   :type: str",
        ]
    )
    assert documented_public_names([text]) == {"MTSAC", "make_mt_env", "__version__"}
    assert [indexed for _, _, indexed in autodoc_entries(text)] == [True, False, True, True, True]
    with pytest.raises(AttributeError):
        resolve("sb3_mtte.envs.no_such_name")


def test_the_measured_files_are_the_pages_and_the_changelog():
    names = {str(path.relative_to(DOCS.parent)) for path in measured_files()}
    assert {"docs/index.md", "docs/results.md", "docs/api/index.md", "CHANGELOG.md"} <= names
    assert not any(name.startswith(("docs/records/", "docs/figures/", "docs/results/")) for name in names)


@pytest.mark.parametrize("path", measured_files(), ids=lambda path: str(path.relative_to(DOCS.parent)))
def test_page_sentences_are_short(path):
    mean = mean_words_per_sentence(path.read_text())
    assert mean <= MAX_MEAN_WORDS, f"{path.name}: {mean:.1f} words per sentence (at most {MAX_MEAN_WORDS}): split them"
