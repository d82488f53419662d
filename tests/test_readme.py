"""The README is a front page: at most 12 KB, and short sentences in its prose.

:func:`prose_sentences` is the measure. ``tests/test_docs.py`` applies the same bar to every page of the docs.
"""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
MAX_README_BYTES = 12 * 1024
MAX_MEAN_WORDS = 25

_FENCE = re.compile(r"^(?P<fence>`{3,}|~{3,}).*?^(?P=fence)[ \t]*$", re.MULTILINE | re.DOTALL)
_COMMENT = re.compile(r"<!--.*?-->", re.DOTALL)
_IMAGE = re.compile(r"!\[[^\]]*\]\([^)]*\)")
_LINK = re.compile(r"\[([^\]]*)\]\([^)]*\)")
_REFERENCE = re.compile(r"\{[a-z:-]+\}`([^`<]*?)(?:\s*<[^>]*>)?`")
_LABEL = re.compile(r"^\([\w-]+\)=[ \t]*$", re.MULTILINE)
_SENTENCE_END = re.compile(r"(?<=[.!?])(?:\s+|$)")


def prose(markdown: str) -> str:
    """The prose of a Markdown page: fenced code and directives, tables, headings, images, link targets, MyST labels
    and HTML comments taken out; a link keeps its text, a role its title."""
    text = _COMMENT.sub(" ", _FENCE.sub("\n", markdown))
    lines = [line for line in text.splitlines() if not line.lstrip().startswith(("|", "#"))]
    text = _LABEL.sub("", "\n".join(lines))
    text = _LINK.sub(r"\1", _IMAGE.sub(" ", text))
    return _REFERENCE.sub(r"\1", text)


def prose_sentences(markdown: str) -> list[int]:
    """The word count of every sentence of the page's prose: a sentence ends at ``.``, ``!`` or ``?`` followed by
    white space or the end; a word is a run of non-space characters."""
    sentences = _SENTENCE_END.split(prose(markdown))
    return [len(words) for words in (sentence.split() for sentence in sentences) if words]


def mean_words_per_sentence(markdown: str) -> float:
    """The mean words per sentence of the page's prose (0 for a page without prose)."""
    counts = prose_sentences(markdown)
    return sum(counts) / len(counts) if counts else 0.0


def test_readme_is_at_most_12_kb():
    size = len(README.read_bytes())
    assert size <= MAX_README_BYTES, f"README.md is {size} bytes: move detail into docs/ (at most {MAX_README_BYTES})"


def test_readme_sentences_are_short():
    mean = mean_words_per_sentence(README.read_text())
    assert mean <= MAX_MEAN_WORDS, f"README.md: {mean:.1f} words per sentence (at most {MAX_MEAN_WORDS}): split them"


def test_the_measure_counts_prose_only():
    """Code, tables, headings, images and link targets are not prose; each sentence end starts a new sentence."""
    page = "\n".join(
        [
            "# A heading of many words that is not a sentence at all",
            "One two three. Four five!",
            "```bash",
            "python -m pytest this is code. It is not prose.",
            "```",
            "| a | table | row. |",
            "![an image with a long alt text](figures/x.png)",
            "See [the docs](https://example.org/a.very.long/link.target) now?",
            "(a-label)=",
            "A {ref}`titled role <a-label>` here",
        ]
    )
    assert prose_sentences(page) == [3, 2, 4, 4]
    assert mean_words_per_sentence(page) == 13 / 4
    assert mean_words_per_sentence("```\ncode only\n```\n") == 0.0


def test_the_measure_fails_a_long_sentence():
    """A page of one 30-word sentence is over the bar; the same words in three sentences are under it."""
    words = " ".join(f"w{i}" for i in range(30))
    assert mean_words_per_sentence(words + ".") > MAX_MEAN_WORDS
    split = words.split()
    assert mean_words_per_sentence(". ".join(" ".join(split[i : i + 10]) for i in range(0, 30, 10))) <= 10
