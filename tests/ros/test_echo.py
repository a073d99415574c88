"""The bundled echo (README: "read every output with `ros2 topic echo` (or the bundled `inkdiag_echo`)"): what it
prints for a message on an inkdiag topic, a real process against a real publisher."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import numpy as np
import pytest


def _echo(ros, args, publish, timeout=30.0):
    """Run echo with ``args`` while ``publish()`` sends a message every 0.1 s; its exit status and output."""
    env = dict(os.environ, ROS_DOMAIN_ID=str(ros.domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    pr = subprocess.Popen([sys.executable, "-m", "inkdiag_ros.echo", *args], env=env, stdout=subprocess.PIPE,
                          stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + timeout
    try:
        while pr.poll() is None:
            if time.monotonic() > deadline:
                pytest.fail(f"echo {' '.join(args)} printed nothing in {timeout:g} s")
            publish()
            ros.spin_for(0.1)
        out, err = pr.communicate(timeout=10)
    finally:
        if pr.poll() is None:
            pr.kill()
            pr.communicate()
    return pr.returncode, out, err


def test_echo_labels_once_prints_the_json_as_ros2_topic_echo_does(ros):
    from msg_defs import LABELS_MSG_TYPE, RELIABLE_QOS, LabelsReport, decode_labels, encode_labels

    node = ros.node("labels_pub", namespace="/head_42")
    pub = node.create_publisher(LABELS_MSG_TYPE, "labels", RELIABLE_QOS)
    report = LabelsReport.from_arrays(frame_id=7, stamp=12.5, first_nozzle=200, model_id="m-1",
                                      classes=np.array(["healthy_nozzle", "deeply_dried"], dtype=object),
                                      confidence=np.array([0.9, 0.75]), valid=np.array([True, True]),
                                      reasons=np.array(["", ""], dtype=object))
    status, out, err = _echo(ros, ["labels", "--namespace", "/head_42", "--once"],
                             lambda: pub.publish(encode_labels(report)))
    assert status == 0 and "Traceback" not in err, err
    assert out.endswith("\n---\n") and out.count("---") == 1, out
    assert out.startswith("data: '{")
    import yaml

    echoed = yaml.safe_load(out.split("---")[0])["data"]  # ros2's layout: the string as one YAML scalar
    assert decode_labels(type(encode_labels(report))(data=echoed)) == report


def test_echo_diagnostics_cuts_long_arrays_at_max_items(ros):
    from msg_defs import DIAGNOSTICS_MSG_TYPE, DIAGNOSTICS_QOS, build_diagnostics

    node = ros.node("diag_pub")
    pub = node.create_publisher(DIAGNOSTICS_MSG_TYPE, "/diagnostics", DIAGNOSTICS_QOS)
    msg = build_diagnostics(namespace="/head_42", level="warn", message="3 frames dropped",
                            values={"frames_per_s": 5.0}, counts={"healthy_nozzle": 190, "deeply_dried": 2})
    status, out, err = _echo(ros, ["/diagnostics", "--once", "--max-items", "2"], lambda: pub.publish(msg))
    assert status == 0 and "Traceback" not in err, err
    assert "hardware_id: /head_42" in out and "message: 3 frames dropped" in out, out
    import yaml

    assert yaml.safe_load(out.split("---")[0])["status"][0]["level"] == "\x01", out  # WARN, as ros2 prints a byte
    n_values = len(msg.status[0].values)
    assert n_values > 2 and out.count("- key: ") == 2 and "- '...'" in out, out


def test_echo_shows_all_of_an_fdi_diagnostics_by_default(ros):
    """The default --max-items was 16: the fdi node's /diagnostics has more values, and the counts came last, cut
    (helper-88); now ros2 topic echo's 128."""
    from msg_defs import DIAGNOSTICS_MSG_TYPE, DIAGNOSTICS_QOS, build_diagnostics

    node = ros.node("diag_pub_all")
    pub = node.create_publisher(DIAGNOSTICS_MSG_TYPE, "/diagnostics", DIAGNOSTICS_QOS)
    msg = build_diagnostics(namespace="/head_43", level="ok", message="ok", gate_cleared=180,
                            values={f"value_{i}": float(i) for i in range(20)},
                            counts={"healthy_nozzle": 190, "deeply_dried": 2})
    n_values = len(msg.status[0].values)
    assert n_values > 16
    status, out, err = _echo(ros, ["/diagnostics", "--once"], lambda: pub.publish(msg))
    assert status == 0 and out.count("- key: ") == n_values and "'...'" not in out, out
    assert "key: count.gate_cleared" in out, out


def test_echo_into_a_reader_that_stops_early_ends_quietly(ros):
    """helper-112: `python -m inkdiag_ros.echo ... | head -c 800` ended in a BrokenPipeError traceback."""
    from msg_defs import LABELS_MSG_TYPE, RELIABLE_QOS, LabelsReport, encode_labels

    pub = ros.node("labels_pub", namespace="/head_43").create_publisher(LABELS_MSG_TYPE, "labels", RELIABLE_QOS)
    report = LabelsReport.from_arrays(frame_id=7, stamp=12.5, first_nozzle=0, model_id="m-1",
                                      classes=np.array(["healthy_nozzle"] * 300, dtype=object),
                                      confidence=np.full(300, 0.9), valid=np.ones(300, bool),
                                      reasons=np.array([""] * 300, dtype=object))
    env = dict(os.environ, ROS_DOMAIN_ID=str(ros.domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    pr = subprocess.Popen([sys.executable, "-m", "inkdiag_ros.echo", "labels", "--namespace", "/head_43"], env=env,
                          stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    import threading

    first = []
    reader = threading.Thread(target=lambda: first.append(pr.stdout.readline()), daemon=True)
    reader.start()
    try:
        deadline = time.monotonic() + 30
        while not first and time.monotonic() < deadline:  # read one line, then close: the reader is gone
            pub.publish(encode_labels(report))
            ros.spin_for(0.2)
        assert first, "echo printed nothing in 30 s"
        first = first[0]
        pr.stdout.close()
        for _ in range(50):  # the next messages hit the closed pipe
            pub.publish(encode_labels(report))
            ros.spin_for(0.1)
            if pr.poll() is not None:
                break
        err = pr.stderr.read().decode()
        pr.wait(timeout=10)
    finally:
        if pr.poll() is None:
            pr.kill()
    assert first.startswith(b"data: ") and pr.returncode == 0, (first, pr.returncode, err)
    assert "Traceback" not in err and "BrokenPipe" not in err, err


def test_a_bad_argument_is_one_line_and_status_2():
    """As the inkdiag verbs' (helper-145: a topic it does not know printed argparse's whole usage first)."""
    r = subprocess.run([sys.executable, "-m", "inkdiag_ros.echo", "nosuchtopic", "--once"], capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert r.stderr.startswith("inkdiag_echo: error: argument topic: invalid choice: 'nosuchtopic'"), r.stderr
