"""Helpers shared by test modules in several directories (``pythonpath = tests`` in pytest.ini).

Import as ``from _helpers import ...``; fixtures live in conftest.py.
"""

import importlib.util
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

#: Sampling rate of the synthetic traces, Hz.
FS = 10e6


def collect(ros, node, msg_type, topic, qos, decode=lambda m: m):
    """Subscribe ``node`` to ``topic``; returns the list the decoded messages are appended to."""
    got = []
    node.create_subscription(msg_type, topic, lambda m: got.append(decode(m)), qos)
    return got


def damped(f_hz, zeta, n, seed, n_samples=512):
    rng = np.random.default_rng(seed)
    t = np.arange(n_samples) / FS
    w0 = 2 * np.pi * f_hz / np.sqrt(1 - zeta**2)
    amp = rng.uniform(0.5, 1.5, (n, 1))
    phase = rng.uniform(-0.3, 0.3, (n, 1))  # the drive fixes the phase up to small spreads
    y = amp * np.exp(-zeta * w0 * t) * np.cos(2 * np.pi * f_hz * t + phase)
    return y + 0.005 * rng.standard_normal(y.shape)


def load_report(name):
    """The module of ``scripts/reports/NAME.py`` (a script, not a package: loaded from its file)."""
    spec = importlib.util.spec_from_file_location(f"{name}_report", ROOT / "scripts" / "reports" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod
