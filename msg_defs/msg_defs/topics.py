"""Topic names of the inkdiag graph.

Every name is *relative*, so it resolves inside the node's namespace: run one
printhead's nodes under ``/head_07`` and its traces are ``/head_07/traces``.
Only ``/diagnostics`` is absolute (one aggregator-friendly topic for all heads,
as ROS convention has it).
"""

__all__ = ["TRACES", "GROUND_TRUTH", "LABELS", "DRYING_NOZZLES", "FM_ESTIMATES",
           "FM_ESTIMATES_ARRAY", "DIAGNOSTICS", "ALL_TOPICS"]

#: Self-sensing traces, std_msgs/Float32MultiArray (nozzle x sample), sensor-data QoS.
TRACES = "traces"
#: Simulator ground truth per frame, std_msgs/String JSON (printhead_sim only).
GROUND_TRUTH = "ground_truth"
#: Fault labels per frame, std_msgs/String JSON, reliable.
LABELS = "labels"
#: Nozzle ids currently labelled dried, std_msgs/String JSON, reliable.
DRYING_NOZZLES = "drying_nozzles"
#: f_m estimates, std_msgs/String JSON, reliable.
FM_ESTIMATES = "fm_estimates"
#: f_m estimates, numeric std_msgs/Float64MultiArray (estimate x field), reliable.
FM_ESTIMATES_ARRAY = "fm_estimates/array"
#: diagnostic_msgs/DiagnosticArray, absolute.
DIAGNOSTICS = "/diagnostics"

ALL_TOPICS = (TRACES, GROUND_TRUTH, LABELS, DRYING_NOZZLES, FM_ESTIMATES,
              FM_ESTIMATES_ARRAY, DIAGNOSTICS)
