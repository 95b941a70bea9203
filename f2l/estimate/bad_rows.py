"""The ``estimates`` row of a record that could not be estimated (every executor writes the same)."""

from __future__ import annotations

from f2l.estimate.record import _base_row

DUPLICATE_STATUS = "duplicate_face_id"
"""The status of a record whose face_id a run read before (only the first is estimated)."""


def bad_row(bad, model: str) -> dict:
    """The row of :class:`~f2l.io.shards.BadRecord` ``bad`` for ``model``: status ``bad_record``
    (or :data:`DUPLICATE_STATUS`), message ``str(bad)`` (file, face and reason)."""
    row = _base_row({"face_id": bad.face_id or "", "source_path": bad.source}, model)
    status = DUPLICATE_STATUS if bad.reason.startswith("duplicate face_id") else "bad_record"
    row.update(status=status, message=str(bad))
    return row
