"""The docs agree with the code: generated parameter tables, links, the README's size."""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_parameter_reference_is_what_the_nodes_declare():
    paramdoc = pytest.importorskip("inkdiag_ros.paramdoc")
    text = (ROOT / "docs" / "parameters.md").read_text()
    assert text == paramdoc.render(), "docs/parameters.md is stale: python -m inkdiag_ros.paramdoc --write docs/parameters.md"


def test_parameter_reference_lists_every_declared_parameter_with_its_default():
    paramdoc = pytest.importorskip("inkdiag_ros.paramdoc")
    text = paramdoc.render()
    for _node, module, _ in paramdoc.NODES:
        for name, default, *_ in __import__(module, fromlist=["PARAMS"]).PARAMS:
            assert re.search(rf"\| `{re.escape(name)}` \| \w+(\[\])? \| {re.escape(paramdoc._fmt(default))} \|", text), name


def test_shipped_params_file_sets_only_declared_parameters(tmp_path):
    paramdoc = pytest.importorskip("inkdiag_ros.paramdoc")
    shipped = paramdoc.shipped_config()
    assert {"printhead_sim", "fdi", "fe", "record_baseline"} <= set(shipped)
    paramdoc.render()  # raises on a parameter the node does not declare


@pytest.mark.parametrize("page", ["README.md", "docs/controller.md", "docs/nodes.md", "docs/core.md"])
def test_relative_links_resolve(page):
    path = ROOT / page
    for target in re.findall(r"\]\(([^)#:]+)(?:#[^)]*)?\)", path.read_text()):
        assert (path.parent / target).exists(), f"{page} links to missing {target}"


def test_readme_is_a_newcomers_page():
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= 300
    text = "\n".join(lines)
    assert "scripts/run" in text and "scripts/test" in text
