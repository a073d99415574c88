"""Module boundaries in the core (issue 13): no private names across modules, the
baselines split by job, the recorder's own nozzle-id bound (not the wire's), and the
default-model cache in the core with ``python -m inkdiag_ros.model_cache`` kept."""

import ast
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
CORE = ROOT / "inkdiag_core" / "inkdiag_core"



def _module_name(path: Path) -> str:
    parts = path.relative_to(CORE).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imported_module(importer: Path, node: ast.ImportFrom) -> str | None:
    """The core module (dotted, relative to ``inkdiag_core``) a ``from ... import`` reads, or None."""
    if node.level == 0:
        if not (node.module or "").startswith("inkdiag_core"):
            return None
        return (node.module or "").removeprefix("inkdiag_core").lstrip(".")
    package = list(importer.relative_to(CORE).parent.parts)
    base = package[: len(package) - (node.level - 1)] if node.level > 1 else package
    return ".".join(base + ([node.module] if node.module else []))


def _private_imports():
    """``(importer, source module, name)`` of every private name a core module imports from another."""
    found = []
    for path in sorted(CORE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if not isinstance(node, ast.ImportFrom):
                continue
            source = _imported_module(path, node)
            if source is None:
                continue
            for alias in node.names:
                name = alias.name
                if name.startswith("_") and not (name.startswith("__") and name.endswith("__")):
                    found.append((_module_name(path), source, name))
    return found


def test_no_core_module_imports_another_modules_private_name():
    assert _private_imports() == []


def test_the_checker_sees_relative_and_absolute_private_imports(tmp_path):
    # the checker itself: a relative, a parent-relative and an absolute import are all resolved
    core_file = CORE / "baselines" / "recorder.py"
    rel = ast.parse("from .store import _x\nfrom ..kpis import _y\nfrom inkdiag_core.fdi import _z\n").body
    assert [_imported_module(core_file, n) for n in rel] == ["baselines.store", "kpis", "fdi"]


@pytest.mark.parametrize("module", ["features", "training", "recorder", "store"])
def test_baselines_are_split_by_job_and_the_old_path_still_imports(module):
    import importlib

    import inkdiag_core
    import inkdiag_core.baseline as old

    mod = importlib.import_module(f"inkdiag_core.baselines.{module}")
    for name in mod.__all__:  # each public name: the same object by every path
        assert getattr(old, name) is getattr(mod, name)
        if name in inkdiag_core.__all__:
            assert getattr(inkdiag_core, name) is getattr(mod, name)


# a limit of 2**24 written any of these ways
_WIRE_VALUE = re.compile(r"2\s*\*\*\s*24|1\s*<<\s*24|16_?777_?216")
_WIRE_WORDS = re.compile(r"wire|trace format|header|msg_defs|codec|message format", re.I)


def test_the_core_never_calls_the_wires_2_24_limit_its_own():
    """The trace header's 2**24 bound lives in msg_defs; the core names no wire limit."""
    offenders = []
    for path in sorted(CORE.rglob("*.py")):
        text = path.read_text()
        if re.search(r"^\s*MAX_NOZZLES\s*=", text, re.M):
            offenders.append(f"{path.name}: defines MAX_NOZZLES")
        for i, line in enumerate(text.splitlines(), 1):
            if _WIRE_VALUE.search(line) and _WIRE_WORDS.search(line):
                offenders.append(f"{path.name}:{i}: {line.strip()}")
    assert offenders == []


def test_the_recorders_nozzle_id_bound_is_its_own_parameter():
    from inkdiag_core import BaselineRecorder
    from inkdiag_core.baselines import DEFAULT_MAX_NOZZLES

    assert BaselineRecorder().max_nozzles == DEFAULT_MAX_NOZZLES
    rec = BaselineRecorder(n_frames=1, max_nozzles=16)
    x = np.zeros((2, 512))
    with pytest.raises(ValueError, match="below 16") as info:
        rec.add(15, x)
    assert "memory" in str(info.value) and "wire" not in str(info.value)
    assert rec.add(14, x) == 0  # all-zero rows are screened out, but the ids are accepted
    for bad in (0, -1, True, 2.5):
        with pytest.raises(ValueError, match="max_nozzles"):
            BaselineRecorder(max_nozzles=bad)


def test_the_model_cache_is_core_code_and_the_ros_entry_point_is_thin():
    import inkdiag_core.model_cache as core
    import inkdiag_ros.model_cache as ros

    for name in ("DEFAULT_MODEL", "DEFAULT_FEATURES", "DEFAULT_SETTINGS", "default_config",
                 "ensure_default_model", "train_default_model"):
        assert getattr(ros, name) is getattr(core, name)
    # the core module imports no ROS (it runs in a fresh interpreter)
    code = ("import sys, inkdiag_core.model_cache\n"
            "print([m for m in sys.modules if m.split('.')[0] in ('rclpy', 'msg_defs', 'inkdiag_ros')])")
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True)
    assert out.stdout.strip() == "[]"
    for mod in ("inkdiag_ros.model_cache", "inkdiag_core.model_cache"):
        out = subprocess.run([sys.executable, "-m", mod, "--help"], check=True, capture_output=True, text=True)
        assert f"python -m {mod}" in out.stdout and "verify or train" in out.stdout
