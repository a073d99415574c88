"""Shared helpers of the JSON messages (std_msgs/String): envelope and field checks."""

from __future__ import annotations

import json
import math
import struct
from json.encoder import encode_basestring_ascii as quote  # json.dumps' own string quoting (ensure_ascii)

from std_msgs.msg import String

from .errors import MessageError

#: Version of every inkdiag JSON schema; bumped on any incompatible change.
JSON_SCHEMA_VERSION = 1


#: One encoder for every message (``json.dumps`` with these options builds a new one per call).
_encode = json.JSONEncoder(separators=(",", ":"), allow_nan=False).encode


def dump(schema: str, body: dict) -> String:
    """``std_msgs/String`` holding ``{"schema": ..., "schema_version": ..., **body}``."""
    doc = {"schema": schema, "schema_version": JSON_SCHEMA_VERSION}
    doc.update(body)
    return String(data=_encode(doc))


#: A serialized message's first four bytes: plain CDR, little endian, no options.
_CDR_LE = b"\x00\x01\x00\x00"
_u32 = struct.Struct("<I").pack


def serialized(msg: String) -> bytes:
    """The CDR bytes of a JSON message (``std_msgs/String``), as ``rclpy.serialization.serialize_message``
    gives them: published as bytes (``Publisher.publish`` takes them), they skip rclpy's conversion of
    the message object. The fdi node's two answers are written as these bytes directly, without the
    message object or the ``json`` encoder (``labels.serialize_labels``, ``drying.serialize_drying``).

    Parameters
    ----------
    msg : std_msgs.msg.String
        Its text must have no NUL character (a JSON text escapes it).
    """
    if not isinstance(msg, String):  # published raw, the bytes skip rclpy's type check: keep it here
        raise TypeError(f"serialized takes a std_msgs/String, got {type(msg).__name__}")
    return cdr(msg.data)


def cdr(text: str) -> bytes:
    """The CDR bytes of a ``std_msgs/String`` holding ``text`` (no NUL character)."""
    b = text.encode("utf-8")
    return b"".join((_CDR_LE, _u32(len(b) + 1), b, b"\x00"))


class NotPlain(Exception):
    """A value the byte encoders do not write themselves (not exactly an int, a finite float or a str):
    the caller falls back to ``json``, which writes it, or raises, as :func:`dump` would."""


def plain(x, kind):
    """``x`` if it is exactly of ``kind`` (int: not bool; float: finite), else :class:`NotPlain`."""
    if type(x) is not kind or (kind is float and x - x != 0.0):  # inf - inf, nan - nan: nan
        raise NotPlain
    return x


def head(schema: str) -> str:
    """The opening of a message's JSON text, as :func:`dump` writes it, before its first body field."""
    return f'{{"schema":{quote(schema)},"schema_version":{JSON_SCHEMA_VERSION},'


def load(msg, schema: str) -> dict:
    """Parse a String message and check its envelope; raise MessageError otherwise."""
    if not isinstance(msg, String):
        raise MessageError(f"expected a std_msgs/String, got {type(msg).__name__}")
    try:
        doc = json.loads(msg.data)
    except ValueError as exc:
        raise MessageError(f"{schema}: not valid JSON ({exc})") from None
    except RecursionError:  # "[[[[...": json's decoder recurses per level (a node died of it: helper-101)
        raise MessageError(f"{schema}: not valid JSON (nested too deeply)") from None
    if not isinstance(doc, dict):
        raise MessageError(f"{schema}: expected a JSON object, got {type(doc).__name__}")
    if doc.get("schema") != schema:
        raise MessageError(f"expected schema {schema!r}, got {doc.get('schema')!r}")
    if doc.get("schema_version") != JSON_SCHEMA_VERSION:
        raise MessageError(
            f"{schema}: expected schema_version {JSON_SCHEMA_VERSION}, got {doc.get('schema_version')!r}"
        )
    return doc


def field(doc: dict, schema: str, name: str, kind, *, nonneg: bool = False):
    """``doc[name]`` checked to be of ``kind`` (int, float, str, list or dict)."""
    if name not in doc:
        raise MessageError(f"{schema}: missing field {name!r}")
    value = doc[name]
    if kind is float:
        try:  # an int too large for a double (10**400) overflows here: not a number we take
            ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
        except OverflowError:
            ok = False
    elif kind is int:
        ok = isinstance(value, int) and not isinstance(value, bool)
    else:
        ok = isinstance(value, kind)
    if not ok:
        raise MessageError(
            f"{schema}: field {name!r} must be {kind.__name__}, got {type(value).__name__} {value!r:.60}"
        )
    if nonneg and value < 0:
        raise MessageError(f"{schema}: field {name!r} must be >= 0, got {value!r}")
    return float(value) if kind is float else value


def finite_or_none(x):
    """JSON has no NaN/Inf: unknown numbers travel as null."""
    x = float(x)
    return x if math.isfinite(x) else None
