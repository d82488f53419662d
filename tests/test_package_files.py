"""The files every package has: the licence setup.cfg names, a changelog entry and a citation for this version."""

from __future__ import annotations

import configparser
from pathlib import Path

import yaml

from sb3_mtte.version import __version__

ROOT = Path(__file__).resolve().parent.parent


def test_the_license_file_is_the_license_setup_cfg_names() -> None:
    config = configparser.ConfigParser()
    config.read(ROOT / "setup.cfg")
    assert config["metadata"]["license"] == "MIT"
    text = (ROOT / "LICENSE").read_text()
    assert text.startswith("MIT License") and "sb3-mtte contributors" in text


def test_the_changelog_starts_with_this_version() -> None:
    headings = [line for line in (ROOT / "CHANGELOG.md").read_text().splitlines() if line.startswith("## ")]
    assert headings and headings[0].split()[1] == __version__


def test_the_citation_names_this_version_and_the_paper() -> None:
    citation = yaml.safe_load((ROOT / "CITATION.cff").read_text())
    assert citation["cff-version"] == "1.2.0" and citation["type"] == "software"
    assert citation["version"] == __version__ and citation["license"] == "MIT"
    titles = [reference["title"] for reference in citation["references"]]
    assert "Multi-Task Reinforcement Learning with Task Representation Method" in titles
