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


@pytest.mark.parametrize("page", ["README.md", "docs/controller.md", "docs/nodes.md", "docs/core.md",
                                  "docs/classes.md"])
def test_relative_links_resolve(page):
    path = ROOT / page
    for target in re.findall(r"\]\(([^)#:]+)(?:#[^)]*)?\)", path.read_text()):
        assert (path.parent / target).exists(), f"{page} links to missing {target}"


def test_readme_is_a_newcomers_page():
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= 300
    text = "\n".join(lines)
    assert "scripts/run" in text and "scripts/test" in text


def test_class_page_gives_every_class_its_simulated_range():
    """docs/classes.md's table is MECHANISMS': a user labelling by it labels what the model learns."""
    from inkdiag_core.faults import MECHANISMS, OK_SIGNAL_DRIVE_FACTOR, PARTICLE_LENGTH_FRACTION

    rows = {}
    for line in (ROOT / "docs" / "classes.md").read_text().splitlines():
        m = re.match(r"\| `(\w+)` \| (.*?) \| (.*?) \|", line)
        if m:
            rows[m.group(1)] = (m.group(2), m.group(3))
    assert set(rows) == {c.value for c in MECHANISMS}
    for cls, mech in MECHANISMS.items():
        state, severity = rows[cls.value]
        if mech.severity:
            scale = 1e6 if mech.kind == "chamber_bubble" else 1.0  # r_b in um on the page
            lo, hi = (float(x) for x in re.search(r"([\d.]+)-([\d.]+)", severity).groups())
            assert (lo, hi) == pytest.approx((mech.low * scale, mech.high * scale)), cls
        else:
            assert severity == "-", cls
    assert f"x {OK_SIGNAL_DRIVE_FACTOR:g}" in rows["ok_signal"][0]
    assert f"{PARTICLE_LENGTH_FRACTION:g} L_n" in rows["partially_blocked"][0]
