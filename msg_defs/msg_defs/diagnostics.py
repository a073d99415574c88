"""``/diagnostics``: one ``diagnostic_msgs/DiagnosticArray`` per head, node and period.

The fe node publishes its own, ``name`` ``"inkdiag fe: <namespace>"`` (its counters:
``inkdiag_ros.stats.FE_KEYS``, docs/controller.md). Each FDI node publishes, every
``diagnostics_period_s``, an array with one ``DiagnosticStatus``:

- ``name``: ``"inkdiag fdi: <namespace>"`` (e.g. ``inkdiag fdi: /head_07``);
- ``hardware_id``: the printhead's namespace;
- ``level``: ``OK``; ``WARN`` when a setting could not be honoured (``config_error``:
  e.g. per-nozzle baselines that did not load) or malformed, failed or dropped
  frames or invalid rows arrived in the last period; ``ERROR`` when no model is loaded; ``STALE`` when no frame arrived
  in the last period;
- ``message``: one line saying why;
- ``values`` (all strings, as the message type wants), keys :data:`KEYS`:
  ``model_id``, ``frames_received``, ``frames_labelled``, ``frames_malformed``,
  ``frames_failed`` (the model raised), ``frames_dropped`` (shed by a full labelling
  queue: the node was overloaded), ``rows_invalid``, ``rows_with_baseline`` (rows
  classified against their nozzle's recorded baseline); over the last period:
  ``frames_per_s``, ``traces_per_s``, ``frames_per_batch`` (frames labelled per
  classifier pass) and ``labeller_busy`` (fraction of the time the classifier
  was busy: in the labelling process, near 1 is the node at its capacity; on
  the executor thread, which also takes and publishes, capacity comes below 1); then
  ``last_error`` (the last malformed frame's reason), ``config_error`` (empty, or
  the setting the node runs without, and why) and then ``count.<class>``
  for each class value and ``count.invalid`` (cumulative rows per label;
  ``count.unknown`` for the rows the model's open-set layer found unlike every
  known class, once there has been one), and ``count.gate_cleared``: cumulative
  rows the healthy gate (``inkdiag_core.HealthyGate``) cleared without the full
  model (also counted under their class, so not part of the per-label sum; 0 when
  the node's baselines carry no reference traces).

The ``frames_*``, ``rows_*`` and ``count.*`` values are cumulative since the node
started (never reset). Each frame taken from ``traces`` is counted in
``frames_received`` and, once done, in exactly one of ``frames_malformed`` (refused
by the codec, at once), ``frames_labelled`` (its labels and drying message
published), ``frames_failed`` or ``frames_dropped``. So with a model loaded,
``frames_received = frames_labelled + frames_malformed + frames_failed +
frames_dropped + frames in flight`` (queued or being labelled at the snapshot: 0
once the node is idle). Not covered by that identity: frames received while no model
is loaded (level ERROR; counted only as received) and the frames a stopping node
leaves unlabelled. A batch that fails as a whole counts each of its frames in
``frames_failed``. ``rows_invalid``
(= ``count.invalid``) counts rows of labelled frames that were invalid, whatever
the reason (``non_finite``, ``out_of_range``, ``flat``, ``clipped``,
``non_finite_features``).
"""

from __future__ import annotations

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

__all__ = ["DIAGNOSTICS_MSG_TYPE", "GATE_CLEARED_KEY", "LEVELS", "KEYS", "build_diagnostics", "diagnostics_values"]

DIAGNOSTICS_MSG_TYPE = DiagnosticArray
#: Level names accepted by :func:`build_diagnostics` -> message constants (bytes values).
LEVELS = {
    "ok": DiagnosticStatus.OK,
    "warn": DiagnosticStatus.WARN,
    "error": DiagnosticStatus.ERROR,
    "stale": DiagnosticStatus.STALE,
}
#: Key (after :data:`COUNT_PREFIX`) of the rows the healthy gate cleared.
GATE_CLEARED_KEY = "gate_cleared"
KEYS = ("model_id", "frames_received", "frames_labelled", "frames_malformed", "frames_failed",
        "frames_dropped", "rows_invalid", "rows_with_baseline", "frames_per_s", "traces_per_s",
        "frames_per_batch", "labeller_busy", "last_error", "config_error")
COUNT_PREFIX = "count."


def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.6g}"
    return str(v)


def build_diagnostics(*, namespace: str, level: str, message: str, values: dict, counts: dict,
                      stamp=None, gate_cleared: int | None = None, node: str = "fdi") -> DiagnosticArray:
    """One head's DiagnosticArray (of its fdi node, or with ``node="fe"`` its fe node's).

    Parameters
    ----------
    namespace : str
        The head's namespace (``hardware_id``).
    level : {"ok", "warn", "error", "stale"}
    message : str
    values : dict
        Keys of :data:`KEYS` (others are appended after them).
    counts : dict of str -> int
        Cumulative rows per class value (and ``"invalid"``).
    stamp : builtin_interfaces/Time, optional
        ``header.stamp`` (the node's clock).
    gate_cleared : int, optional
        Cumulative rows the healthy gate cleared: ``count.gate_cleared`` (None: not sent).
    node : {"fdi", "fe"}
        Whose status: ``name`` is ``"inkdiag <node>: <namespace>"``.
    """
    status = DiagnosticStatus()
    status.level = LEVELS[level]
    status.name = f"inkdiag {node}: {namespace}"
    status.hardware_id = namespace
    status.message = message
    first = KEYS if node == "fdi" else ()  # fdi's documented order; fe's values as given (its FE_KEYS)
    ordered = [k for k in first if k in values] + [k for k in values if k not in first]
    kv = [KeyValue(key=k, value=_fmt(values[k])) for k in ordered] + [
        KeyValue(key=COUNT_PREFIX + c, value=str(int(n))) for c, n in sorted(counts.items())
    ]
    if gate_cleared is not None:
        kv.append(KeyValue(key=COUNT_PREFIX + GATE_CLEARED_KEY, value=str(int(gate_cleared))))
    status.values = kv
    arr = DiagnosticArray()
    if stamp is not None:
        arr.header.stamp = stamp
    arr.status = [status]
    return arr


def diagnostics_values(msg: DiagnosticArray) -> dict:
    """``{status.name: {"level": "ok"|..., "message": ..., key: value, ...}}`` of an array."""
    names = {v: k for k, v in LEVELS.items()}
    out = {}
    for st in msg.status:
        d = {"level": names.get(st.level, repr(st.level)), "message": st.message}
        d.update({kv.key: kv.value for kv in st.values})
        out[st.name] = d
    return out
