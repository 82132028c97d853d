"""docs/failures.md, the catalogue of bad inputs: every test it names exists, and it
holds at least 40 rows (each a bad input with its test)."""

import re

from tests.conftest import REPO

CATALOGUE = REPO / "docs" / "failures.md"
REFERENCE = re.compile(r"`((?:[\w/]+\.py)?)::(\w+)`")


def rows():
    """The catalogue's table rows (neither headers nor rules): list of str."""
    return [
        line
        for line in CATALOGUE.read_text().splitlines()
        if line.startswith("| ") and not line.startswith(("| Input", "| ---"))
    ]


def test_every_test_named_in_the_failures_catalogue_exists():
    missing = []
    for row in rows():
        refs = REFERENCE.findall(row)
        assert refs, f"a row without a test: {row[:80]}"
        path = None
        for file, name in refs:
            path = file or path  # "::name" continues the file named before it
            source = (REPO / "tests" / path).read_text()
            if not re.search(rf"^def {name}\(", source, re.M):
                missing.append(f"tests/{path}::{name}")
    assert missing == []


def test_the_failures_catalogue_lists_at_least_40_bad_inputs():
    assert len(rows()) >= 40
