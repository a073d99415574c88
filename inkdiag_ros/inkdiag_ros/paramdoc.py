"""The nodes' parameter reference, generated from their own declarations.

Each node module declares its parameters once, as ``PARAMS`` (name, default,
description, type, range); this module renders them, with the values of the
shipped ``config/inkdiag.yaml``, as ``docs/parameters.md``. A test checks that
the committed file is what this renders, so the docs cannot drift from the code.

    python -m inkdiag_ros.paramdoc --write docs/parameters.md
    python -m inkdiag_ros.paramdoc --check docs/parameters.md
"""

from __future__ import annotations

import argparse
import importlib
import re
import sys
from importlib import resources
from pathlib import Path

#: (node name, module, one line on what the node is for), in the order of the graph.
NODES = (
    ("printhead_sim", "inkdiag_ros.printhead_sim", "the simulated printhead (stands in for a printer controller)"),
    ("record_baseline", "inkdiag_ros.baseline_node",
     "records every nozzle's healthy baseline while the head is known to jet, writes the file, exits"),
    ("fdi", "inkdiag_ros.fdi_node", "fault detection and isolation of every trace frame"),
    ("fe", "inkdiag_ros.fe_node", "f_m estimation of the drying nozzles"),
)

_KIND = {bool: "bool", int: "int", float: "float", str: "string", "int[]": "int[]", "str[]": "string[]"}


def shipped_config() -> dict:
    """``{node: {parameter: value}}`` of the shipped ``config/inkdiag.yaml``."""
    import yaml  # noqa: PLC0415 - PyYAML ships with the ROS wheels (rclpy reads params files with it)

    text = resources.files("inkdiag_ros").joinpath("config/inkdiag.yaml").read_text()
    doc = yaml.safe_load(text) or {}
    return {key.rsplit("/", 1)[-1]: (val or {}).get("ros__parameters", {}) for key, val in doc.items()}


def _fmt(value) -> str:
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, float):
        return re.sub(r"e\+?(-?)0*(\d)", r"e\1\2", f"{value:g}")  # 1e+07 -> 1e7
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_fmt(v).strip('"') for v in value) + "]"
    return str(value)


def _range(kind, rng) -> str:
    if rng is None:
        return ""
    lo, hi = rng
    return f"{_fmt(kind(lo))} .. {_fmt(kind(hi))}"


def node_help(node_cls, prog: str) -> str:
    """What ``NODE --help`` prints: the node module's docstring and its parameters (plain text).

    ``prog`` names the node (a :data:`NODES` name, else the module of ``node_cls`` is used).
    """
    import inspect

    module = next((m for name, m, _ in NODES if name == prog), node_cls.__module__)
    mod = importlib.import_module(module)
    shipped = shipped_config().get(next((name for name, m, _ in NODES if m == module), ""), {})
    out = [f"usage: {prog} [--ros-args -r __ns:=/NAMESPACE -p NAME:=VALUE ... --params-file FILE]", "",
           inspect.cleandoc(mod.__doc__ or ""), "", "parameters (type, default[, shipped config]; range):"]
    for name, default, desc, kind, rng in mod.PARAMS:
        ship = f", shipped {_fmt(shipped[name])}" if name in shipped else ""
        span = f"; {_range(kind, rng)}" if rng is not None else ""
        out += [f"  {name} ({_KIND[kind]}, {_fmt(default)}{ship}{span})", f"      {desc}"]
    out += ["", "Reference: docs/parameters.md; topics and counters: docs/controller.md."]
    return "\n".join(out)


def render() -> str:
    """The Markdown parameter reference of every node."""
    shipped = shipped_config()
    out = [
        "# Node parameters",
        "",
        "Generated from the nodes' own declarations (`PARAMS` in each node module) by",
        "`python -m inkdiag_ros.paramdoc --write docs/parameters.md`; a test checks that this",
        "file matches the code. *default* is what the node declares; *shipped* is the value in",
        "`inkdiag_ros/config/inkdiag.yaml` (the graph runner and `scripts/run` load it first,",
        "then your `--ros-args`), where it sets one. Ranges are inclusive. Every parameter",
        "is fixed at start (read-only: `ros2 param describe` says so, `ros2 param set` is refused)",
        "unless its description says it may change at runtime. A `float`",
        "parameter takes a number with a decimal point (`-p frame_rate_hz:=5.0`; rclpy refuses `5`",
        "as an integer). Every node also has ROS's own `use_sim_time`, fixed at start too (a set is refused,",
        "though rclpy's own descriptor of it does not say read-only).",
        "",
    ]
    for node, module, what in NODES:
        params = importlib.import_module(module).PARAMS
        cfg = shipped.get(node, {})
        out += [f"## `{node}`", "", f"{what[0].upper()}{what[1:]}.", "",
                "| parameter | type | default | shipped | range | meaning |",
                "| --- | --- | --- | --- | --- | --- |"]
        for name, default, desc, kind, rng in params:
            ship = _fmt(cfg[name]) if name in cfg else ""
            out.append(f"| `{name}` | {_KIND[kind]} | {_fmt(default)} | {ship} | {_range(kind, rng)} | "
                       f"{desc.replace('|', '/')} |")
        unknown = sorted(set(cfg) - {p[0] for p in params})
        if unknown:
            raise ValueError(f"config/inkdiag.yaml sets {node} parameters it does not declare: {unknown}")
        out.append("")
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m inkdiag_ros.paramdoc", description=__doc__.splitlines()[0])
    g = ap.add_mutually_exclusive_group()
    g.add_argument("--write", metavar="PATH", help="write the reference to PATH")
    g.add_argument("--check", metavar="PATH", help="exit 1 if PATH is not what the code renders")
    args = ap.parse_args(argv)
    text = render()
    if args.write:
        Path(args.write).write_text(text)
    elif args.check:
        if Path(args.check).read_text() != text:
            print(f"{args.check} is out of date: python -m inkdiag_ros.paramdoc --write {args.check}",
                  file=sys.stderr)
            return 1
    else:
        sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
