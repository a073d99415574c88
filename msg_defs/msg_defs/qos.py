"""QoS profiles of the inkdiag graph, named once.

Reliability and durability mismatches deliver nothing, silently, so every
publisher and subscriber takes its profile from here.

- ``TRACES_QOS``: sensor data (BEST_EFFORT, VOLATILE, as
  ``rclpy.qos.qos_profile_sensor_data``: a late trace frame is worth less than
  the next one, and a best-effort subscriber also matches a reliable publisher,
  so a printer controller may publish either way), but KEEP_LAST 32 instead of
  5: a head scan arrives as a burst of nozzle-range messages (2,656 nozzles in
  200-nozzle messages are 14), and a depth of 5 would drop most of a burst
  whenever the subscriber's executor is a few milliseconds late.
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
    depth=32,
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
