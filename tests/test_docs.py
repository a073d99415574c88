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
    """docs/classes.md's table is MECHANISMS' (and reports/sim.md's frequencies): a user labelling by it
    labels what the model learns."""
    from inkdiag_core.faults import MECHANISMS, OK_SIGNAL_DRIVE_FACTOR, PARTICLE_LENGTH_FRACTION

    rows = {}
    for line in (ROOT / "docs" / "classes.md").read_text().splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 5 and re.fullmatch(r"`\w+`", cells[0]):
            rows[cells[0].strip("`")] = cells[1:]
    assert set(rows) == {c.value for c in MECHANISMS}
    sim = {}  # the default head's mean dominant frequency per class ("ours" column), kHz
    for line in (ROOT / "reports" / "sim.md").read_text().splitlines():
        m = re.match(r"\| (\w+) \| [\d.]+ \| ([\d.]+) \+-", line)
        if m:
            sim[m.group(1)] = float(m.group(2))
    assert set(sim) == set(rows)
    symbols = {"empty": "m", "nozzle_bubble": "phi", "chamber_bubble": "r_b", "particle": "beta", "dried": "k"}
    for cls, mech in MECHANISMS.items():
        state, severity, scales, freq = rows[cls.value]
        if mech.severity:
            m = re.fullmatch(r"(\w+) ([\d.]+)-([\d.]+)( um)?", severity)
            assert m, (cls, severity)
            assert m.group(1) == symbols[mech.kind] and f" {m.group(1)} " in f" {mech.severity} ", cls
            scale = 1e6 if mech.kind == "chamber_bubble" else 1.0  # r_b in um on the page
            assert bool(m.group(4)) == (mech.kind == "chamber_bubble"), cls
            assert (float(m.group(2)), float(m.group(3))) == pytest.approx((mech.low * scale, mech.high * scale)), cls
        else:
            assert severity == "-", cls
        # the one mechanism whose severity is absolute, not relative to the head
        assert scales.startswith("**no") == (mech.kind == "chamber_bubble"), cls
        f = re.fullmatch(r"([\d.]+) (kHz|MHz)", freq)
        assert f, (cls, freq)
        khz = float(f.group(1)) * (1e3 if f.group(2) == "MHz" else 1.0)
        assert khz == pytest.approx(sim[cls.value], abs=5.0 if f.group(2) == "MHz" else 0.5), cls
    assert re.search(r"drive amplitude x ([\d.]+)", rows["ok_signal"][0]).group(1) == f"{OK_SIGNAL_DRIVE_FACTOR:g}"
    assert re.search(r"over ([\d.]+) L_n", rows["partially_blocked"][0]).group(1) == f"{PARTICLE_LENGTH_FRACTION:g}"


def test_restrictor_figures_quoted_in_the_docs_are_the_reports():
    """docs/cli.md and docs/calibration.md quote reports/restrictor.md's medians with and without blocked traces."""
    text = (ROOT / "reports" / "restrictor.md").read_text()
    found = re.findall(r"\w+ ([+-]\d+\.\d) % \(RMS (\d+\.\d) %, healthy traces alone ([+-]\d+\.\d) %, RMS (\d+\.\d) %\)",
                       text)
    assert len(found) == 5, found
    blocked, blocked_rms, alone, alone_rms = ([float(row[i]) for row in found] for i in range(4))

    def span(v, signed=True):
        return f"{min(v):+.1f} to {max(v):+.1f} %" if signed else f"{min(v):.1f}-{max(v):.1f} %"

    cli = " ".join((ROOT / "docs" / "cli.md").read_text().split())
    assert f"healthy traces alone {span(alone)}, with 50 blocked traces {span(blocked)}" in cli
    cal = " ".join((ROOT / "docs" / "calibration.md").read_text().split())
    assert (f"median error {span(blocked)} on the five heads, RMS {span(blocked_rms, False)}, against healthy traces "
            f"alone {span(alone)}, RMS {span(alone_rms, False)}") in cal
    four, h5 = alone_rms[:4], alone_rms[4]  # the training spread's reason (default h20 h16 h12, then h5)
    assert f"(RMS {span(four, False)} over 12 recordings of four heads, {h5:.1f} % on h5:" in cal


def test_actuator_figures_quoted_in_the_docs_are_the_reports():
    """docs/calibration.md quotes reports/actuator.md: what each assumed-actuator spread and --empty give."""
    rows, head, ratio = [], None, None
    for line in (ROOT / "reports" / "actuator.md").read_text().splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) != 8 or not re.fullmatch(r"[\d.]+", cells[3]):
            continue
        head, ratio = cells[0] or head, float(cells[1]) if cells[1] else ratio
        rows.append((head, ratio, cells[2], *map(float, cells[3:6])))
    assert len(rows) == 3 * 5 * 4, len(rows)

    def pick(col, ratios, how):
        return [r[col] for r in rows if r[1] in ratios and how(r[2])]

    def span(v):
        return f"{min(v):.1f}-{max(v):.1f} %".replace("100.0 %", "100 %")

    base, wide, empty = (lambda h: h == "assumed, spread 0.085"), (lambda h: h.startswith("assumed") and
                                                                   h != "assumed, spread 0.085"), (lambda h: "empty" in h)
    cal = " ".join((ROOT / "docs" / "calibration.md").read_text().split())
    near = pick(4, (0.9, 1.0, 1.12), lambda h: h.startswith("assumed")) + pick(5, (0.9, 1.0, 1.12),
                                                                               lambda h: h.startswith("assumed"))
    assert f"at 0.9-1.12 every spread labels both empty classes {span(near)} right" in cal
    assert f"fails whichever ({span(pick(4, (0.8,), base))} at 0.085, {span(pick(4, (0.8,), wide))} wider;" in cal
    assert f"fails at 0.085 ({', '.join(f'{v:.1f}' for v in pick(5, (0.72,), base))} %) and passes wider " \
           f"({span(pick(5, (0.72,), wide))})" in cal
    assert f"at every ratio ({span(pick(4, (0.72, 0.8, 0.9, 1.0, 1.12), empty) + pick(5, (0.72, 0.8, 0.9, 1.0, 1.12), empty))}, " \
           f"FI {span(pick(3, (0.72, 0.8, 0.9, 1.0, 1.12), empty))}" in cal
