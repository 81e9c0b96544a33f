"""``/volcap/diagnostics`` messages: a node's status as a diagnostic_msgs DiagnosticStatus."""
from __future__ import annotations

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from .conversions import make_header

LEVELS = {'ok': DiagnosticStatus.OK, 'warn': DiagnosticStatus.WARN, 'error': DiagnosticStatus.ERROR,
          'stale': DiagnosticStatus.STALE}


def diagnostic_status(name: str, level: str, message: str, values: dict | None = None,
                      hardware_id: str = '') -> DiagnosticStatus:
    return DiagnosticStatus(level=LEVELS[level], name=name, message=message, hardware_id=hardware_id,
                            values=[KeyValue(key=str(k), value=str(v)) for k, v in (values or {}).items()])


def diagnostic_array(statuses: list[DiagnosticStatus], stamp_ns: int) -> DiagnosticArray:
    return DiagnosticArray(header=make_header(stamp_ns, ''), status=statuses)


