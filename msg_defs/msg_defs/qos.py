"""QoS profiles of the inkdiag graph, named once.

Reliability and durability mismatches deliver nothing, silently, so every
publisher and subscriber takes its profile from here.

- ``TRACES_QOS``: sensor data (BEST_EFFORT, KEEP_LAST 5, VOLATILE), as
  ``rclpy.qos.qos_profile_sensor_data``: a late trace frame is worth less than
  the next one, and a best-effort subscriber also matches a reliable publisher
  (a printer controller may publish either way).
- ``RELIABLE_QOS``: labels, drying nozzles, estimates, ground truth
  (RELIABLE, KEEP_LAST 50, VOLATILE): operators and the FE node must not lose
  a verdict.
- ``DIAGNOSTICS_QOS``: RELIABLE, KEEP_LAST 10, as ROS diagnostics publishers use.
"""

from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)

__all__ = ["TRACES_QOS", "RELIABLE_QOS", "DIAGNOSTICS_QOS"]

TRACES_QOS = QoSProfile(
    reliability=qos_profile_sensor_data.reliability,
    history=qos_profile_sensor_data.history,
    depth=qos_profile_sensor_data.depth,
    durability=qos_profile_sensor_data.durability,
)

RELIABLE_QOS = QoSProfile(
    reliability=ReliabilityPolicy.RELIABLE,
    history=HistoryPolicy.KEEP_LAST,
    depth=50,
    durability=DurabilityPolicy.VOLATILE,
)

DIAGNOSTICS_QOS = QoSProfile(
    reliability=ReliabilityPolicy.RELIABLE,
    history=HistoryPolicy.KEEP_LAST,
    depth=10,
    durability=DurabilityPolicy.VOLATILE,
)
