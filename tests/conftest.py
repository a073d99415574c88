"""Shared fixtures: real rclpy on a per-test Context and domain id.

- ``ros``: a fresh :class:`rclpy.context.Context` initialised on a domain id of
  its own, a :class:`SingleThreadedExecutor` on it, a node factory and a
  ``spin_until(condition, timeout)`` that fails the test on timeout. Teardown
  runs in the order rclpy wants: executor.shutdown(), node.destroy_node(),
  rclpy.try_shutdown(context).

Every test run gets its base ``ROS_DOMAIN_ID`` from scripts/test (or the
caller); tests count up from it, so two tests never share a domain and
discovery never leaves this machine (``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``
is forced here too, in case pytest was started by hand).
"""

from __future__ import annotations

import itertools
import os
import time

import pytest

os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
if os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] != "LOCALHOST":  # never let tests leave loopback
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("ROS_DOMAIN_ID", str(os.getpid() % 100 + 1))
# the shipped Fast DDS profile (large shared-memory segment), as scripts/_bootstrap.sh sets it
os.environ.setdefault("FASTRTPS_DEFAULT_PROFILES_FILE", os.path.join(
    os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
    "inkdiag_ros", "inkdiag_ros", "config", "fastdds_profile.xml"))

_BASE_DOMAIN = int(os.environ["ROS_DOMAIN_ID"])
_domain_counter = itertools.count()


def next_domain_id() -> int:
    """A domain id not used by any earlier test of this run (1..101, safe on Linux)."""
    return (_BASE_DOMAIN - 1 + next(_domain_counter)) % 101 + 1


class RosHarness:
    """One test's rclpy world: context, executor, nodes, and a deadline spinner."""

    def __init__(self):
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor

        self.domain_id = next_domain_id()
        self.context = Context()
        rclpy.init(context=self.context, domain_id=self.domain_id)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.nodes = []

    def add(self, node):
        """Register a node built with ``context=harness.context`` and spin it."""
        self.nodes.append(node)
        self.executor.add_node(node)
        return node

    def node(self, name: str, **kwargs):
        """A plain rclpy Node on this context, spun by this executor."""
        from rclpy.node import Node

        return self.add(Node(name, context=self.context, **kwargs))

    def spin_until(self, condition, timeout: float = 10.0, what: str = "condition"):
        """Spin until ``condition()`` is true; fail the test after ``timeout`` s."""
        deadline = time.monotonic() + timeout
        while not condition():
            if time.monotonic() > deadline:
                pytest.fail(f"timed out after {timeout:.1f} s waiting for {what}")
            self.executor.spin_once(timeout_sec=0.02)

    def spin_for(self, seconds: float):
        """Spin for a fixed time (to show that something does *not* happen)."""
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.02)

    def close(self):
        import rclpy

        self.executor.shutdown()
        for node in self.nodes:
            node.destroy_node()
        rclpy.try_shutdown(context=self.context)


@pytest.fixture
def ros():
    harness = RosHarness()
    try:
        yield harness
    finally:
        harness.close()


@pytest.fixture(scope="session")
def fdi_model(tmp_path_factory):
    """A small but real FDI model (RF on KPI_Y, trained on simulated traces) with its manifest."""
    from inkdiag_core.fdi import train_default_model

    path = tmp_path_factory.mktemp("model") / "fdi_small.joblib"
    train_default_model(path, n_per_class=80, features="kpi_y", seed=0)
    return path


@pytest.fixture(scope="session")
def fdi_baseline_model(tmp_path_factory):
    """A small FaultDetector file with both branches (plain KPI_Y and KPI_Y + the nozzle's baseline)."""
    from inkdiag_core.fdi import train_default_model

    path = tmp_path_factory.mktemp("model") / "fdi_small_baseline.joblib"
    train_default_model(path, n_per_class=80, baseline=True, seed=0)
    return path
