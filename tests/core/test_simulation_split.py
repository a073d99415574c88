"""The simulator split into ``inkdiag_core.simulation`` (issue 13, item 5).

- Bit for bit: seeded sha256 fingerprints of the traces and of every
  per-trace truth array of ``simulate`` (classes, spreads on and off,
  ``frame_seed``, ``draw_order``), ``simulate_nozzles``, ``simulate_nonlinear``,
  ``healthy_twin_frames`` and the scenario's ``simulate_head``, recorded on the
  code before the split (commit f2ca064).
- No module of the core imports another module's private (``_``) names.
- One topic per module, each with ``__all__``, re-exported by the package;
  the former import paths keep working.
"""

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

import inkdiag_core
from inkdiag_core import FaultClass as F
from inkdiag_core import simulation

CORE = Path(inkdiag_core.__file__).resolve().parent

# recorded with the same calls on f2ca064 (inkdiag_core/simulator.py, nonlinear.py
# and inkdiag_ros/scenario.py before the split)
FINGERPRINTS = {
    "healthy_twin_frames": {
        "frames": "3175386024e8f96a1f6e8a8970812d7cfe94d95e7a5aee14661ad806da5d04d8",
        "traces": "31c1f5f7baae2f869eabb8cde25399988513e466148f3339f1a79cad2542119e",
        "truth": "754652218a5ced7aace9b2f366b574c962ccd4c3c544b77e9116d6ae78d2cf1d",
    },
    "simulate_all": {
        "traces": "2b64289151da5e7b60c80631280e9eebbe6f78145183c01fd876f225c52b37f1",
        "truth": "40607d8103e62022ce6def443eead76eba90ccaafd8791d934963880c31a1885",
    },
    "simulate_draw_order": {
        "traces": "741e09b176c7506f93a5b5de8fa8f74e6ae18554a35104edf859fa065c9bfde7",
        "truth": "2eae0bd53de273b11701beb1b308a3ff80697b6bb5a480e5ceacec54cd81a077",
    },
    "simulate_frame": {
        "traces": "a5666e41cc43c5f68d213d6f31a64da64d5502542fee9e2d5cf4da8320474dfd",
        "truth": "64571da8d8dcaa1fa0bb467f92f216342f3ea4efc448fdaa0cf23c4dc46e3d8b",
    },
    "simulate_head": {
        "all": "330683359e0fdfbd4b5ede9bb83c3e826190ce0df367d082a38c98b8f14515a9",
    },
    "simulate_none": {
        "traces": "d80c88f9bd437c7b2be24048a9c310db273210be4fd5c746a147d2270d3655c3",
        "truth": "05ff8781a894ac483504ce1efb86a2a7e4c20121538bf98bb0947b3b19d8277f",
    },
    "simulate_nonlinear": {
        "traces": "3eb76fe57c35bc9dbd4eb3bdfcf9bd9239250a4ef930bc85d64ee3e72034ad93",
        "truth": "4c0b9926f455d4ca88b7b1657a94ce3192867d3e5a58f754694e0c889616731f",
    },
    "simulate_nozzles": {
        "traces": "61e0359d97de54f40bc96985b6c4921d3a7cf2ed52c6c0237b2d6931d18f369f",
        "truth": "67a5f931b1ebb0edd34ec5c1b9d028edbbe1d2553b6a8da7ca025b0b5b5bfc06",
    },
}


def _digest(r):
    out = {"traces": hashlib.sha256(np.ascontiguousarray(r.traces).tobytes()).hexdigest()}
    truth = hashlib.sha256()
    for name in ("mu_nozzle", "mu", "fm", "frequency_hz", "damping_ratio", "x0", "A",
                 "sensor_gain", "sensor_offset", "snr_db"):
        truth.update(name.encode())
        truth.update(np.ascontiguousarray(getattr(r, name)).tobytes())
    for k in sorted(r.params):
        truth.update(k.encode())
        truth.update(np.ascontiguousarray(r.params[k]).tobytes())
    truth.update(repr([getattr(c, "value", c) for c in r.labels]).encode())
    truth.update(np.float64(r.noise_std_v).tobytes())
    out["truth"] = truth.hexdigest()
    return out


def _simulate_head_digest():
    from inkdiag_core.simulation.scenario import HeadScenario, simulate_head

    sc = HeadScenario(n_nozzles=40, first_nozzle=100, fault_nozzles=(101, 102),
                      fault_classes=("intermediate_air_bubble", "partially_blocked"),
                      random_fault_fraction=0.2, drying_nozzles=(110, 111), faults_start_s=1.0, seed=4)
    rng = np.random.default_rng(77)
    h = hashlib.sha256()
    for t in (0.5, 3.0, 30.0):
        classes, mu = sc.at(t)
        traces, labels, fm, mu_nozzle = simulate_head(classes, mu, sample_rate_hz=10e6, n_samples=256,
                                                      head_seed=4, rng=rng)
        for a in (traces, fm, mu_nozzle):
            h.update(np.ascontiguousarray(a).tobytes())
        h.update(repr(list(labels)).encode())
    return {"all": h.hexdigest()}


def _nozzles_digest():
    classes = [list(F)[i % len(F)] for i in range(30)]
    mu = np.full(30, np.nan)
    mu[[k for k, c in enumerate(classes) if "dried" in c.value][::2]] = 0.02
    return _digest(simulation.simulate_nozzles(classes, mu_nozzle=mu, seed=8, frame_seed=2))


def _twins_digest():
    twins, frames = simulation.healthy_twin_frames(20, seed=12, n_frames=3, noise_std_v=0.01)
    d = _digest(twins)
    d["frames"] = hashlib.sha256(frames.tobytes()).hexdigest()
    return d


CASES = {
    "simulate_all": lambda: _digest(simulation.simulate({c: 7 for c in F}, seed=3)),
    "simulate_none": lambda: _digest(simulation.simulate({c: 7 for c in F}, seed=4,
                                                         spreads=simulation.Spreads.none())),
    "simulate_frame": lambda: _digest(simulation.simulate(
        {F.HEALTHY_NOZZLE: 9, F.SLIGHTLY_DRIED: 5, F.EMPTY_CHANNEL_2: 4, F.PARTIALLY_BLOCKED: 3},
        seed=5, frame_seed=11, n_samples=300, chunk_size=7)),
    "simulate_draw_order": lambda: _digest(simulation.simulate(
        {list(F)[0]: 6, list(F)[3]: 12}, seed=6, draw_order=np.random.default_rng(1).permutation(18),
        drive=simulation.DriveWaveform(amplitude_v=18.0))),
    "simulate_nozzles": _nozzles_digest,
    "simulate_nonlinear": lambda: _digest(simulation.simulate_nonlinear({c: 1 for c in F}, seed=9,
                                                                        n_samples=128)),
    "healthy_twin_frames": _twins_digest,
    "simulate_head": _simulate_head_digest,
}


# the same calls recorded on another platform (AMD EPYC, Zen 4), whose BLAS and libm round
# differently in the last bits: see the file's "about"
OTHER_PLATFORM = json.loads((Path(__file__).parent / "data" / "split_fingerprints_zen4.json").read_text())


@pytest.mark.parametrize("name", sorted(CASES))
def test_split_is_bit_for_bit(name):
    assert CASES[name]() in (FINGERPRINTS[name], OTHER_PLATFORM["simulation"][name])


def test_simulation_modules_have_one_topic_each_and_are_re_exported():
    import importlib

    for path in sorted((CORE / "simulation").glob("*.py")):
        n_lines = len(path.read_text().splitlines())
        assert n_lines <= 600, f"{path.name}: {n_lines} lines"
        if path.name == "__init__.py":
            continue
        mod = importlib.import_module(f"inkdiag_core.simulation.{path.stem}")
        assert mod.__all__, path.name
        for name in mod.__all__:
            assert getattr(simulation, name) is getattr(mod, name), f"{path.stem}.{name} not re-exported"
            assert name in simulation.__all__
    for name in ("simulator.py", "nonlinear.py", "scorecard.py"):
        assert len((CORE / name).read_text().splitlines()) <= 600


def test_former_import_paths_still_work():
    from inkdiag_core import nonlinear, scorecard, simulator
    from inkdiag_core.simulation import scenario

    for name in simulator.__all__:
        assert getattr(simulator, name) is getattr(simulation, name)
    for name in nonlinear.__all__:
        assert getattr(nonlinear, name) is getattr(simulation, name)
    assert inkdiag_core.simulate is simulation.simulate
    assert inkdiag_core.simulate_nonlinear is simulation.simulate_nonlinear
    assert inkdiag_core.healthy_twin_frames is simulation.healthy_twin_frames
    assert scenario.HeadScenario is simulation.HeadScenario
    assert scorecard.Scorecard.__module__ == "inkdiag_core.scorecard"


def test_channel_draw_is_a_typed_container_of_per_trace_arrays():
    classes = [(F.HEALTHY_NOZZLE, 3), (F.EMPTY_CHANNEL_1, 1), (F.DEEPLY_DRIED, 2)]  # declaration order
    ch = simulation.draw_channels(classes, inkdiag_core.InkChannelParams(), simulation.Spreads(),
                                  np.random.default_rng(0))
    assert isinstance(ch, simulation.ChannelDraw)
    for name in ("k_r", "k_n", "d_r", "d_n", "b_r", "b_n", "drive", "fm", "mu", "mu_nozzle", "kinds"):
        assert getattr(ch, name).shape == (6,), name
    assert (ch.fm[:4] == 0).all() and (ch.fm[4:] < 0).all()
    assert ch.params["drive_v"] is None and ch.params["R_n"].shape == (6,)
    res = simulation.simulate(dict(classes), seed=0)
    np.testing.assert_array_equal(res.fm, ch.fm)
    np.testing.assert_array_equal(res.mu_nozzle, ch.mu_nozzle)
