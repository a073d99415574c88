"""The foundation is the real thing: rclpy + Fast DDS from the venv, a pure core."""

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_rclpy_is_real_and_uses_fast_dds():
    import rclpy
    from rclpy.utilities import get_rmw_implementation_identifier

    assert Path(rclpy.__file__).resolve().is_relative_to(Path(sys.prefix).resolve())
    assert get_rmw_implementation_identifier() == "rmw_fastrtps_cpp"


def test_discovery_is_confined_to_localhost():
    assert os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    assert 0 < int(os.environ["ROS_DOMAIN_ID"]) <= 101


def test_core_imports_without_any_ros_module():
    code = (
        "import json, sys\n"
        "import inkdiag_core\n"
        "import inkdiag_core.model\n"
        "bad = [m for m in sys.modules if m.split('.')[0] in "
        "('rclpy', 'std_msgs', 'diagnostic_msgs', 'builtin_interfaces', 'rosidl_runtime_py', "
        "'msg_defs', 'inkdiag_ros')]\n"
        "print(json.dumps(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True)
    assert json.loads(out.stdout) == []


def test_no_core_source_file_imports_ros():
    import re

    pattern = re.compile(
        r"^\s*(import|from)\s+(rclpy|std_msgs|diagnostic_msgs|msg_defs|inkdiag_ros)\b", re.M
    )
    offenders = [
        str(p.relative_to(ROOT))
        for p in (ROOT / "inkdiag_core").rglob("*.py")
        if pattern.search(p.read_text())
    ]
    assert offenders == []


def test_each_package_is_an_ament_python_package():
    import xml.etree.ElementTree as ET

    for pkg in ("inkdiag_core", "msg_defs", "inkdiag_ros"):
        root = ROOT / pkg
        xml = ET.parse(root / "package.xml").getroot()
        assert xml.get("format") == "3"
        assert xml.findtext("name") == pkg
        assert xml.find("export").findtext("build_type") == "ament_python"
        assert (root / "resource" / pkg).is_file()
        assert (root / "setup.py").is_file() and (root / "setup.cfg").is_file()
        assert f"$base/lib/{pkg}" in (root / "setup.cfg").read_text()
