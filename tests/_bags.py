"""rosbag2 bags for the tests, written by ``rosbags`` directly (no rclpy, no msg_defs encoder).

Import as ``from _bags import write_bag`` (``pythonpath = tests`` in pytest.ini).
"""

import numpy as np

from msg_defs import HEADER_LEN, SCHEMA_VERSION

FS = 10e6
NS = "/head_00"


def typestore():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def frame_msg(ts, traces, *, first, frame_id, stamp_s, data_offset=HEADER_LEN):
    """A trace frame built with rosbags' own message classes (no rclpy, no msg_defs encoder)."""
    ma = ts.types
    n, s = traces.shape
    head = np.array([SCHEMA_VERSION, first, frame_id, 0, FS, stamp_s, 0, 0], dtype=np.float32)
    layout = ma["std_msgs/msg/MultiArrayLayout"](
        dim=[ma["std_msgs/msg/MultiArrayDimension"](label="nozzle", size=n, stride=n * s),
             ma["std_msgs/msg/MultiArrayDimension"](label="sample", size=s, stride=s)], data_offset=data_offset)
    return ma["std_msgs/msg/Float32MultiArray"](layout=layout, data=np.concatenate([head, traces.ravel()]))


def write_bag(path, frames, *, version=9, bad_frame=None, traces_type="std_msgs/msg/Float32MultiArray"):
    """A rosbag2 MCAP bag written by rosbags directly: ``frames`` is a list of (first_nozzle, traces)."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
    from rosbags.rosbag2 import StoragePlugin, Writer

    ts = typestore()
    qos = Qos(QosHistory.KEEP_LAST, 32, QosReliability.BEST_EFFORT, QosDurability.VOLATILE, QosTime(0, 0),
              QosTime(0, 0), QosLiveliness.AUTOMATIC, QosTime(0, 0), False)
    t0 = 1_700_000_000_000_000_000
    with Writer(path, version=version, storage_plugin=StoragePlugin.MCAP) as w:
        conn = w.add_connection(f"{NS}/traces", traces_type, typestore=ts, offered_qos_profiles=[qos])
        other = w.add_connection(f"{NS}/labels", "std_msgs/msg/String", typestore=ts)
        for k, (first, x) in enumerate(frames):
            if traces_type == "std_msgs/msg/String":
                msg = ts.types["std_msgs/msg/String"](data="not traces")
            else:
                msg = frame_msg(ts, x, first=first, frame_id=k, stamp_s=100 + k,
                                data_offset=3 if k == bad_frame else HEADER_LEN)
            w.write(conn, t0 + k * 100_000_000, ts.serialize_cdr(msg, traces_type))
            w.write(other, t0 + k * 100_000_000 + 1, ts.serialize_cdr(ts.types["std_msgs/msg/String"](data="{}"),
                                                                       "std_msgs/msg/String"))
    return path
